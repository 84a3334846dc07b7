"""The grasper model in CasADi symbols (eq. 4.4) and its 1 ms discretisations (appendix A).

``continuous_dynamics()`` is xdot = f(x, u, p) with the smoothed sign of eq. 4.19.
``implicit_step()`` is the real-time discretisation of appendix A: 15 forward-Euler substeps
give a predictor for x[k+1]; one Newton step with the exact (automatic-differentiation)
Jacobian then solves the implicit trapezoidal equation
    R(z) = z - x - dt/2 (f(x, u) + f(z, u)) = 0.
``rk4_step()`` is the explicit fixed-step RK4 that appendix A warns against, kept for the
comparison, and ``reference_simulation()`` a tight-tolerance variable-step BDF solution.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from pointfence.kernels.errors import InputError

from .params import DT, GRAVITY, IDX, NP, NX

#: Number of forward-Euler predictor substeps (appendix A).
PREDICTOR_SUBSTEPS = 15


def smooth_sign(v):
    """Differentiable sign, eq. 4.19: sgn(v) ~ 10 v / sqrt(1 + 100 v^2)."""
    return 10.0 * v / ca.sqrt(1.0 + 100.0 * v * v)


def cable_force(x, p):
    """gamma of eq. 4.4: exponential antagonistic cable spring plus damping [N]."""
    qm, ql, dqm, dql = x[0], x[1], x[2], x[3]
    rm, rl, ke, be = p[IDX["r_m"]], p[IDX["r_l"]], p[IDX["k_e"]], p[IDX["b_e"]]
    d = qm * rm - ql * rl
    return ke * (ca.exp(d) - ca.exp(-d)) + 2.0 * be * (dqm * rm - dql * rl)


def dynamics_expr(x, u, p, tau_ext_extra=0.0):
    """xdot of eq. 4.4 for symbolic x (4), u (motor torque), p (NP).

    ``tau_ext_extra`` is an additional external link torque (the plant's contact model);
    the model's own external torque is the parameter tau_l.
    """
    qm, ql, dqm, dql = x[0], x[1], x[2], x[3]
    g = cable_force(x, p)
    Fm = p[IDX["Fc_m"]] * smooth_sign(dqm) + p[IDX["Fv_m"]] * dqm
    Fl = p[IDX["Fc_l"]] * smooth_sign(dql) + p[IDX["Fv_l"]] * dql
    N = p[IDX["m_l"]] * p[IDX["L_cm"]] * GRAVITY * ca.sin(ql)
    ddqm = (u - p[IDX["r_m"]] * g - Fm) / p[IDX["J_m"]]
    ddql = (p[IDX["tau_l"]] + tau_ext_extra + p[IDX["r_l"]] * g - Fl - N) / p[IDX["J_l"]]
    return ca.vertcat(dqm, dql, ddqm, ddql)


def _syms():
    return ca.SX.sym("x", NX), ca.SX.sym("u"), ca.SX.sym("p", NP)


def continuous_dynamics() -> ca.Function:
    x, u, p = _syms()
    return ca.Function("cable_f", [x, u, p], [dynamics_expr(x, u, p)], ["x", "u", "p"], ["xdot"])


def implicit_step_expr(f, x, u, p, dt=DT, substeps=PREDICTOR_SUBSTEPS, newton=1):
    """Appendix A: Euler predictor (``substeps``) then ``newton`` Newton steps, trapezoidal rule.

    ``f(x, u, p)`` returns a symbolic xdot. Returns the symbolic x[k+1].
    """
    h = dt / substeps
    z = x
    for _ in range(substeps):
        z = z + h * f(z, u, p)
    zs, xs = ca.SX.sym("z", x.shape[0]), ca.SX.sym("xs", x.shape[0])
    us, ps = ca.SX.sym("us", u.shape[0]), ca.SX.sym("ps", p.shape[0])
    res = zs - xs - 0.5 * dt * (f(xs, us, ps) + f(zs, us, ps))
    jac = ca.jacobian(res, zs)
    newton_fn = ca.Function("newton", [zs, xs, us, ps], [zs - ca.solve(jac, res)])
    for _ in range(newton):
        z = newton_fn(z, x, u, p)
    return z


def implicit_step(dt=DT, substeps=PREDICTOR_SUBSTEPS) -> ca.Function:
    """x[k+1] = G(x[k], u[k], p) by the implicit step of appendix A."""
    x, u, p = _syms()
    xn = implicit_step_expr(dynamics_expr, x, u, p, dt, substeps)
    return ca.Function("cable_step", [x, u, p], [xn], ["x", "u", "p"], ["xnext"])


def rk4_step(dt=DT) -> ca.Function:
    """Explicit classical RK4 at ``dt`` (the method appendix A shows is wrong here)."""
    x, u, p = _syms()
    k1 = dynamics_expr(x, u, p)
    k2 = dynamics_expr(x + 0.5 * dt * k1, u, p)
    k3 = dynamics_expr(x + 0.5 * dt * k2, u, p)
    k4 = dynamics_expr(x + dt * k3, u, p)
    xn = x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("cable_rk4", [x, u, p], [xn], ["x", "u", "p"], ["xnext"])


def simulate_steps(step: ca.Function, x0, u_seq, p) -> np.ndarray:
    """Apply a discrete step function over a torque sequence; returns states (n+1, 4)."""
    u_seq = np.asarray(u_seq, dtype=float).ravel()
    x0 = np.asarray(x0, dtype=float).ravel()
    if x0.shape != (NX,):
        raise InputError(f"initial state has {x0.size} entries, expected {NX} (q_m, q_l, qd_m, qd_l)")
    roll = step.mapaccum(u_seq.size)
    X = np.array(roll(x0, u_seq.reshape(1, -1), np.asarray(p, dtype=float).reshape(-1, 1)))
    return np.hstack([x0.reshape(-1, 1), X]).T


def reference_simulation(x0, u_seq, p, dt=DT, tol=1e-10) -> np.ndarray:
    """Tight-tolerance variable-step (CVODES BDF) solution with zero-order-hold input.

    Returns states at the sample instants, shape (n+1, 4): the reference of fig. A.1.
    """
    x, u, pp = _syms()
    dae = {"x": x, "p": ca.vertcat(u, pp), "ode": dynamics_expr(x, u, pp)}
    F = ca.integrator("ref", "cvodes", dae, 0.0, dt,
                      {"abstol": tol, "reltol": tol, "max_num_steps": 200000})
    roll = F.mapaccum(len(u_seq))
    pcol = np.asarray(p, dtype=float).reshape(-1, 1)
    P = np.vstack([np.asarray(u_seq, dtype=float).reshape(1, -1), np.repeat(pcol, len(u_seq), axis=1)])
    X = np.array(roll(x0=np.asarray(x0, dtype=float), p=P)["xf"])
    return np.hstack([np.asarray(x0, dtype=float).reshape(-1, 1), X]).T
