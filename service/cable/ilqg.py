"""Model predictive control by iLQG (dissertation section 4.6) on the CasADi grasper model.

Cost (eq. 4.17/4.18): l = 80 (q_l - q_ld)^2 + 2e-3 tau^2 + B(tau),
B(tau) = exp(-a (tau + tau_max)) + exp(a (tau - tau_max)), a = 30, tau_max = 0.2 N m; terminal
cost 80 (q_l - q_ld)^2. Horizon 10 steps of 1 ms, 3 iterations per tick, warm start by
shifting the previous solution (eq. 4.8).

Dynamics: the forward passes use the implicit step of appendix A. The backward pass uses its
linearisation (A, B) from the implicit function theorem applied to the trapezoidal equation,
with exact Jacobians of eq. 4.4 by automatic differentiation (the dissertation had to fall
back to a one-step Euler model in the backward pass; generated C makes the exact one cheap).
The second derivatives of the dynamics are dropped (iLQG rather than full DDP).

A backtracking line search without branches: each iteration rolls out the step sizes
alpha in {1, 0.5, 0.2, 0.05} and keeps the cheapest of those and the current plan, so the cost never
increases. The whole tick (10 rollouts, 3 backward passes) is one CasADi function, generated
to C and called on preallocated buffers.
"""
from __future__ import annotations

import dataclasses
import math

import casadi as ca
import numpy as np

from pointfence.kernels.errors import InputError

from .codegen import BufferedCall, compile_functions
from .model import PREDICTOR_SUBSTEPS, dynamics_expr, implicit_step_expr
from .params import DT, NP, NX

ALPHAS = (1.0, 0.5, 0.2, 0.05)


@dataclasses.dataclass(frozen=True)
class MPCConfig:
    horizon: int = 10
    iterations: int = 3
    w_track: float = 80.0
    w_tau: float = 2e-3
    barrier_a: float = 30.0
    tau_max: float = 0.2

    def __post_init__(self):
        if not (isinstance(self.horizon, int) and 1 <= self.horizon <= 200):
            raise InputError(f"MPC horizon={self.horizon!r} must be an integer in [1, 200] steps")
        if not (isinstance(self.iterations, int) and 1 <= self.iterations <= 50):
            raise InputError(f"MPC iterations={self.iterations!r} must be an integer in [1, 50]")
        for f in ("w_track", "w_tau", "barrier_a", "tau_max"):
            v = getattr(self, f)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"MPC {f}={v!r} must be a finite number > 0")


def barrier(tau, a, tau_max):
    """eq. 4.18."""
    return ca.exp(-a * (tau + tau_max)) + ca.exp(a * (tau - tau_max))


def _sx_parts(cfg: MPCConfig):
    x, u, p, qd = ca.SX.sym("x", NX), ca.SX.sym("u"), ca.SX.sym("p", NP), ca.SX.sym("qd")
    xn = implicit_step_expr(dynamics_expr, x, u, p, DT, PREDICTOR_SUBSTEPS)
    step = ca.Function("mpc_step", [x, u, p], [xn])

    # linearisation of the trapezoidal map by the implicit function theorem
    z = ca.SX.sym("z", NX)
    fx, fz = dynamics_expr(x, u, p), dynamics_expr(z, u, p)
    h2 = 0.5 * DT
    M = ca.SX.eye(NX) - h2 * ca.jacobian(fz, z)
    A = ca.solve(M, ca.SX.eye(NX) + h2 * ca.jacobian(fx, x))
    B = ca.solve(M, h2 * (ca.jacobian(fx, u) + ca.jacobian(fz, u)))
    lin = ca.Function("mpc_lin", [x, u, p, z], [ca.densify(A), ca.densify(B)])

    l = cfg.w_track * (x[1] - qd) ** 2 + cfg.w_tau * u * u + barrier(u, cfg.barrier_a, cfg.tau_max)
    lf = cfg.w_track * (x[1] - qd) ** 2
    cost = ca.Function("mpc_cost", [x, u, qd], [l])
    tcost = ca.Function("mpc_tcost", [x, qd], [lf])
    lx, lxx = ca.gradient(l, x), ca.hessian(l, x)[0]
    lu, luu = ca.gradient(l, u), ca.hessian(l, u)[0]
    lfx, lfxx = ca.gradient(lf, x), ca.hessian(lf, x)[0]
    tder = ca.Function("mpc_tder", [x, qd], [ca.densify(lfx), ca.densify(lfxx)])

    # one backward-pass stage (m = 1, so Quu is a scalar); l_ux = 0 for this cost
    Vx, Vxx = ca.SX.sym("Vx", NX), ca.SX.sym("Vxx", NX, NX)
    Am, Bm = ca.SX.sym("A", NX, NX), ca.SX.sym("B", NX, 1)
    Qx = lx + Am.T @ Vx
    Qu = lu + Bm.T @ Vx
    Qxx = lxx + Am.T @ Vxx @ Am
    Quu = ca.fmax(luu + Bm.T @ Vxx @ Bm, 1e-9)
    Qux = Bm.T @ Vxx @ Am  # 1 x NX
    kff = -Qu / Quu
    Kfb = -Qux / Quu
    Vx_n = Qx + Kfb.T * Quu * kff + Kfb.T * Qu + Qux.T * kff
    Vxx_n = Qxx + Kfb.T @ Kfb * Quu + Kfb.T @ Qux + Qux.T @ Kfb
    Vxx_n = 0.5 * (Vxx_n + Vxx_n.T)
    back = ca.Function("mpc_back", [x, u, qd, Am, Bm, Vx, Vxx],
                       [kff, ca.densify(Kfb.T), ca.densify(Vx_n), ca.densify(Vxx_n)])

    # one forward-pass stage with feedback
    xh, xnom, k, K, al = ca.SX.sym("xh", NX), ca.SX.sym("xnom", NX), ca.SX.sym("k"), ca.SX.sym("K", NX), ca.SX.sym("al")
    # the barrier keeps the optimum inside +-tau_max; clamping the trial torque at 1.5 tau_max
    # keeps a far-off linearisation from proposing absurd steps
    un = ca.fmin(ca.fmax(u + al * k + K.T @ (xh - xnom), -1.5 * cfg.tau_max), 1.5 * cfg.tau_max)
    fwd = ca.Function("mpc_fwd", [xh, xnom, u, k, K, al, p], [step(xh, un, p), un])
    return step, lin, cost, tcost, tder, back, fwd


def mpc_function(cfg: MPCConfig = MPCConfig()) -> ca.Function:
    """CasADi function (x0, U0, qd, p) -> (U, X, J): one MPC tick of ``cfg.iterations`` iLQG iterations."""
    N = cfg.horizon
    step, lin, cost, tcost, tder, back, fwd = _sx_parts(cfg)
    x0, U0 = ca.MX.sym("x0", NX), ca.MX.sym("U0", N)
    qd, p = ca.MX.sym("qd", N + 1), ca.MX.sym("p", NP)

    def total(X, U):
        J = tcost(X[N], qd[N])
        for i in range(N):
            J += cost(X[i], U[i], qd[i])
        return J

    U = [U0[i] for i in range(N)]
    X = [x0]
    for i in range(N):
        X.append(step(X[i], U[i], p))
    J = total(X, U)
    for _ in range(cfg.iterations):
        Vx, Vxx = tder(X[N], qd[N])
        ks, Ks = [None] * N, [None] * N
        for i in reversed(range(N)):
            A, B = lin(X[i], U[i], p, X[i + 1])
            ks[i], Ks[i], Vx, Vxx = back(X[i], U[i], qd[i], A, B, Vx, Vxx)
        best_X, best_U, best_J = X, U, J
        for al in ALPHAS:
            Xn, Un = [x0], []
            for i in range(N):
                xn, un = fwd(Xn[i], X[i], U[i], ks[i], Ks[i], al, p)
                Xn.append(xn)
                Un.append(un)
            Jn = total(Xn, Un)
            better = Jn < best_J  # false when Jn is NaN
            best_X = [ca.if_else(better, a, b) for a, b in zip(Xn, best_X)]
            best_U = [ca.if_else(better, a, b) for a, b in zip(Un, best_U)]
            best_J = ca.if_else(better, Jn, best_J)
        X, U, J = best_X, best_U, best_J
    return ca.Function("cable_mpc", [x0, U0, qd, p], [ca.vertcat(*U), ca.horzcat(*X), J],
                       ["x0", "U0", "qd", "p"], ["U", "X", "J"])


_CACHE: dict = {}


def compiled_mpc(cfg: MPCConfig = MPCConfig()):
    if cfg not in _CACHE:
        f = mpc_function(cfg)
        fns, how = compile_functions([f], "cable_mpc")
        _CACHE[cfg] = (fns["cable_mpc"], how)
    return _CACHE[cfg]


class ILQGController:
    """Receding-horizon iLQG: ``solve(x, p, qd)`` returns the motor torque for this tick."""

    def __init__(self, config: MPCConfig | None = None):
        self.config = config or MPCConfig()
        self.fn, self.how = compiled_mpc(self.config)
        self._call = BufferedCall(self.fn)
        self._x0, self._U0, self._qd, self._p = self._call.args
        self._U, self._X, self._J = self._call.res
        self.N = self.config.horizon

    def reset(self) -> None:
        self._U0[:] = 0.0

    @property
    def qd(self) -> np.ndarray:
        """Desired link angles over the horizon, N+1 values (write in place before ``solve``)."""
        return self._qd

    @property
    def plan(self) -> np.ndarray:
        return self._U

    @property
    def predicted(self) -> np.ndarray:
        return self._X

    @property
    def cost(self) -> float:
        return float(self._J[0])

    def solve(self, x: np.ndarray, p: np.ndarray) -> float:
        """One tick: optimise from state ``x`` with parameters ``p``, shift the plan (eq. 4.8)."""
        self._x0[:] = x
        self._p[:] = p
        self._call()
        u = float(self._U[0])
        self._U0[:-1] = self._U[1:]
        self._U0[-1] = self._U[-1]
        return u
