"""Unscented Kalman filter for joint state and parameter estimation (algorithm 4.2.1, eq. 4.2).

The augmented state is x^a = [q_m, q_l, qd_m, qd_l, z] where z holds the estimated
parameters (a chosen subset of ``PARAM_NAMES``, e.g. the cable parameters, the friction
coefficients, or the external link torque tau_l), each divided by a fixed scale so that the
filter works on numbers of order one. Parameters follow a random walk. The only measurement is
the quantised motor angle; the input is the commanded motor torque.

One filter step (sigma points, propagation through the implicit 1 ms step of appendix A, time
update, redraw of sigma points, measurement update) is a single CasADi function, generated to C
and called on preallocated buffers (``BufferedCall``): no allocation per step.
"""
from __future__ import annotations

import dataclasses
import math

import casadi as ca
import numpy as np

from pointfence.kernels.errors import InputError

from .codegen import BufferedCall, compile_functions
from .model import dynamics_expr, implicit_step_expr
from .params import DT, ENCODER_RES, IDX, NP, NX, PARAM_NAMES, GrasperParams

#: Default scale of each parameter in the filter (z = p / scale).
PARAM_SCALE = {
    "J_m": 1e-5, "J_l": 1e-5, "r_m": 1e-2, "r_l": 1e-2, "k_e": 1e4, "b_e": 1.0,
    "Fc_m": 1e-2, "Fc_l": 1e-2, "Fv_m": 1e-4, "Fv_l": 1e-4, "m_l": 1e-2, "L_cm": 1e-2,
    "tau_l": 1e-2,
}


def _check_names(names) -> tuple[int, ...]:
    idx = []
    for n in names:
        if n not in IDX:
            raise InputError(f"cannot estimate unknown parameter {n!r}; expected names from {', '.join(PARAM_NAMES)}")
        idx.append(IDX[n])
    if len(set(idx)) != len(idx):
        raise InputError(f"estimated parameter list {list(names)!r} has duplicates")
    return tuple(idx)


def ukf_function(est_names, alpha=1.0, beta=2.0, kappa=0.0) -> ca.Function:
    """CasADi function (xa, P, u, y, p, scale, Q, R) -> (xa+, P+, innovation)."""
    est = _check_names(est_names)
    nz = len(est)
    L = NX + nz
    lam = alpha * alpha * (L + kappa) - L
    wm = np.full(2 * L + 1, 1.0 / (2 * (L + lam)))
    wc = wm.copy()
    wm[0] = lam / (L + lam)
    wc[0] = lam / (L + lam) + (1.0 - alpha * alpha + beta)
    gamma = math.sqrt(L + lam)

    # sigma points of (mean, cov): SX, Cholesky inlined
    m, Pm = ca.SX.sym("m", L), ca.SX.sym("P", L, L)
    S = ca.chol(0.5 * (Pm + Pm.T) + 1e-14 * ca.SX.eye(L)).T  # lower, S S' = P
    sig = ca.horzcat(m, ca.repmat(m, 1, L) + gamma * S, ca.repmat(m, 1, L) - gamma * S)
    sigma_fn = ca.Function("ukf_sigma", [m, Pm], [sig])

    # process model of one sigma point: implicit step with parameters from z
    xa, u, p, sc = ca.SX.sym("xa", L), ca.SX.sym("u"), ca.SX.sym("p", NP), ca.SX.sym("sc", nz)
    pf = p
    for j, i in enumerate(est):
        pf = ca.vertcat(pf[:i], xa[NX + j] * sc[j], pf[i + 1:])
    xn = implicit_step_expr(dynamics_expr, xa[:NX], u, pf, DT)
    prop = ca.Function("ukf_prop", [xa, u, p, sc], [ca.vertcat(xn, xa[NX:])])
    prop_map = prop.map(2 * L + 1)

    def mean_cov(X, add):
        mu = X @ ca.DM(wm)
        D = X - ca.repmat(mu, 1, 2 * L + 1)
        return mu, D @ ca.diag(ca.DM(wc)) @ D.T + add, D

    Xs = ca.SX.sym("X", L, 2 * L + 1)
    Qd, R, y = ca.SX.sym("Q", L), ca.SX.sym("R"), ca.SX.sym("y")
    mu, Pp, _ = mean_cov(Xs, ca.diag(Qd))
    Xr = sigma_fn(mu, Pp)  # redraw (algorithm 4.2.1)
    Y = Xr[0, :]  # H: the motor angle
    yhat = Y @ ca.DM(wm)
    Dy = Y - yhat
    Dx = Xr - ca.repmat(mu, 1, 2 * L + 1)
    Pyy = Dy @ ca.diag(ca.DM(wc)) @ Dy.T + R
    Pxy = Dx @ ca.diag(ca.DM(wc)) @ Dy.T
    K = Pxy / Pyy
    innov = y - yhat
    xnew = mu + K * innov
    Pnew = Pp - K @ Pyy @ K.T
    Pnew = 0.5 * (Pnew + Pnew.T)
    update_fn = ca.Function("ukf_update", [Xs, Qd, R, y], [xnew, Pnew, innov])

    Xa, Pa = ca.MX.sym("xa", L), ca.MX.sym("P", L, L)
    Um, Ym, Pp_, Sc = ca.MX.sym("u"), ca.MX.sym("y"), ca.MX.sym("p", NP), ca.MX.sym("scale", nz)
    Qm, Rm = ca.MX.sym("Q", L), ca.MX.sym("R")
    Xsig = sigma_fn(Xa, Pa)
    Xprop = prop_map(Xsig, Um, Pp_, Sc)
    xo, Po, io = update_fn(Xprop, Qm, Rm, Ym)
    name = "ukf_" + "_".join(PARAM_NAMES[i] for i in est) if est else "ukf_states"
    return ca.Function(name, [Xa, Pa, Um, Ym, Pp_, Sc, Qm, Rm], [xo, Po, io],
                       ["xa", "P", "u", "y", "p", "scale", "Q", "R"], ["xa_next", "P_next", "innovation"])


_CACHE: dict = {}


def compiled_ukf(est_names) -> tuple[ca.Function, str]:
    key = tuple(est_names)
    if key not in _CACHE:
        f = ukf_function(key)
        fns, how = compile_functions([f], f.name())
        _CACHE[key] = (fns[f.name()], how)
    return _CACHE[key]


@dataclasses.dataclass
class UKFConfig:
    """Which parameters to estimate and the filter's noise model."""

    estimate: tuple = ("tau_l",)
    #: process noise variances of the states per 1 ms step
    q_state: tuple = (1e-9, 1e-9, 2e-3, 2e-2)
    #: random-walk variance per step of each estimated (scaled) parameter
    q_param: tuple = (1e-3,)
    #: initial standard deviation of each estimated (scaled) parameter
    p0_param: tuple = (1.0,)
    #: measurement noise variance [rad^2]; default: quantisation noise (res^2 / 12), doubled
    r_meas: float = ENCODER_RES ** 2 / 6.0

    def __post_init__(self):
        self.estimate = tuple(self.estimate)
        _check_names(self.estimate)
        nz = len(self.estimate)
        for name in ("q_param", "p0_param"):
            v = tuple(getattr(self, name))
            if len(v) == 1 and nz > 1:
                v = v * nz
            if len(v) != nz:
                raise InputError(f"UKFConfig.{name} has {len(v)} entries, expected {nz} (one per estimated "
                                 f"parameter {self.estimate})")
            setattr(self, name, v)
        if len(self.q_state) != NX:
            raise InputError(f"UKFConfig.q_state has {len(self.q_state)} entries, expected {NX}")
        vals = list(self.q_state) + list(self.q_param) + list(self.p0_param) + [self.r_meas]
        if not all(math.isfinite(v) and v >= 0 for v in vals) or self.r_meas <= 0:
            raise InputError(f"UKFConfig variances must be finite and >= 0 (r_meas > 0); got {self}")


class UKF:
    """Joint state/parameter UKF over the grasper model, stepped at 1 kHz."""

    def __init__(self, params: GrasperParams, config: UKFConfig | None = None):
        self.config = config or UKFConfig()
        self.est_idx = _check_names(self.config.estimate)
        self.fn, self.how = compiled_ukf(self.config.estimate)
        self._call = BufferedCall(self.fn)
        (self._xa, self._P, self._u, self._y, self._p, self._sc, self._Q, self._R) = self._call.args
        self._xo, self._Po, self._innov = self._call.res
        self.L = NX + len(self.est_idx)
        self._sc[:] = [PARAM_SCALE[n] for n in self.config.estimate]
        self._Q[:NX] = self.config.q_state
        self._Q[NX:] = self.config.q_param
        self._R[0] = self.config.r_meas
        nz = len(self.est_idx)
        # (learn=False: the parameter block and its copy, preallocated views)
        self._xz, self._Pzz = self._xa[NX:], self._P[NX:, NX:]
        self._Pxz, self._Pzx = self._P[:NX, NX:], self._P[NX:, :NX]
        self._zkeep, self._Pzz_keep = np.zeros(nz), np.zeros((nz, nz))
        self.set_params(params)
        self.reset()

    def set_fixed(self, name: str, value: float) -> None:
        """Set a parameter the filter does not estimate (e.g. the external torque ``tau_l`` [N m]
        from another filter) for the following steps; allocation-free."""
        i = IDX[name]
        if i in self.est_idx:
            raise InputError(f"parameter {name!r} is estimated by this filter; set_fixed applies to fixed ones")
        self._p[i] = value

    def set_params(self, params: GrasperParams) -> None:
        """Fixed parameters (and the starting values of the estimated ones)."""
        self._p[:] = params.vector()
        self.base_params = params

    def reset(self, q_m: float = 0.0, params: GrasperParams | None = None) -> None:
        """Start from rest at motor angle ``q_m`` with the link at the matching angle."""
        if params is not None:
            self.set_params(params)
        p = self._p
        self._xa[:] = 0.0
        self._xa[0] = q_m
        self._xa[1] = q_m * p[IDX["r_m"]] / p[IDX["r_l"]]
        for j, i in enumerate(self.est_idx):
            self._xa[NX + j] = p[i] / self._sc[j]
        self._P[:] = 0.0
        d = np.array([1e-6, 1e-2, 1e-2, 1e-1] + [s * s for s in self.config.p0_param])
        np.fill_diagonal(self._P, d)

    def step(self, u_prev: float, y: float, learn: bool = True) -> None:
        """Time update with the torque applied over the last period, measurement update with y.

        With ``learn`` False the estimated parameters are held for this step (treated as known: the
        states update, the parameters and their variance do not, and their correlation with the
        states is dropped), e.g. while a load the model lacks would push them off.
        """
        self._u[0] = u_prev
        self._y[0] = y
        if not learn:
            self._zkeep[:] = self._xz
            self._Pzz_keep[:] = self._Pzz
        self._call()
        self._xa[:] = self._xo
        self._P[:] = self._Po
        if not learn:
            self._xz[:] = self._zkeep
            self._Pzz[:] = self._Pzz_keep
            self._Pxz.fill(0.0)
            self._Pzx.fill(0.0)

    @property
    def x(self) -> np.ndarray:
        """Current state estimate [q_m, q_l, qd_m, qd_l] (a view; copy to keep)."""
        return self._xa[:NX]

    @property
    def innovation(self) -> float:
        return float(self._innov[0])

    def estimates(self) -> dict:
        """Estimated parameters in physical units."""
        return {n: float(self._xa[NX + j] * self._sc[j]) for j, n in enumerate(self.config.estimate)}

    def estimate(self, j: int) -> float:
        """The ``j``-th estimated parameter (order of ``config.estimate``) in physical units, without
        building a dict (for the 1 kHz path)."""
        return float(self._xa[NX + j] * self._sc[j])

    def estimate_std(self) -> dict:
        return {n: float(math.sqrt(max(self._P[NX + j, NX + j], 0.0)) * self._sc[j])
                for j, n in enumerate(self.config.estimate)}

    def params_vector(self, out: np.ndarray | None = None) -> np.ndarray:
        """Full parameter vector with the estimated entries filled in (written into ``out``)."""
        out = np.empty(NP) if out is None else out
        out[:] = self._p
        for j, i in enumerate(self.est_idx):
            out[i] = self._xa[NX + j] * self._sc[j]
        return out

    def healthy(self) -> bool:
        return bool(np.isfinite(self._xa).all() and np.isfinite(self._P).all())
