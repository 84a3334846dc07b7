"""Simulated grasper plant: the true model plus encoder quantisation, torque noise and loads.

The plant integrates eq. 4.4 with "true" parameters at 0.1 ms substeps (implicit trapezoidal
rule, Euler predictor and two Newton iterations each) under a zero-order-hold motor torque.
Loads on the link: tissue contact by Hunt-Crossley beyond a contact angle,
F = k x^n + lambda x^n xdot (x > 0, F >= 0), x the jaw-tip penetration, and optionally a linear
spring (the dissertation's validation load of fig. 4.4). The motor encoder is quantised at
2000 counts/rev; the applied torque carries white noise.
"""
from __future__ import annotations

import dataclasses
import math

import casadi as ca
import numpy as np

from pointfence.kernels.errors import InputError

from .codegen import BufferedCall, compile_functions
from .model import dynamics_expr
from .params import DT, ENCODER_CPR, NP, NX, GrasperParams

PLANT_SUBSTEPS = 10
NC = 8  #: load vector: q_c, lever, k, n, lambda, q_s, k_s, spring_on


@dataclasses.dataclass(frozen=True)
class HuntCrossley:
    """Tissue beyond link angle ``q_contact`` [rad]; ``lever`` [m] from joint to contact point.

    Force F = k x^n + lam x^n xdot on penetration x = lever (q_l - q_contact) > 0, F >= 0; the
    link feels -F lever. Defaults give ~0.07 N m at 0.4 rad penetration (soft tissue).
    """

    q_contact: float = 0.0
    lever: float = 0.02
    k: float = 8.0e3      # N / m^n
    n: float = 1.5
    lam: float = 8.0e4    # N s / m^(n+1)

    def __post_init__(self):
        for f in ("q_contact", "lever", "k", "n", "lam"):
            v = getattr(self, f)
            if not math.isfinite(v):
                raise InputError(f"HuntCrossley.{f}={v!r} must be finite")
        if self.lever <= 0 or self.k < 0 or self.lam < 0 or self.n < 1:
            raise InputError(f"HuntCrossley needs lever > 0, k >= 0, lam >= 0, n >= 1; got {self}")


@dataclasses.dataclass(frozen=True)
class LinearSpring:
    """Extension spring on the link: torque -k (q_l - q0) while q_l > q0 [N m/rad, rad]."""

    k: float = 0.05
    q0: float = 0.0

    def __post_init__(self):
        if not (math.isfinite(self.k) and math.isfinite(self.q0)) or self.k < 0:
            raise InputError(f"LinearSpring needs a finite k >= 0 and finite q0; got {self}")


def load_torque_expr(x, c):
    ql, dql = x[1], x[3]
    pen = ca.fmax(c[1] * (ql - c[0]), 0.0)
    pn = pen ** c[3]
    f = ca.fmax(c[2] * pn + c[4] * pn * c[1] * dql, 0.0)
    spring = -c[6] * ca.fmax(ql - c[5], 0.0) * c[7]
    return -f * c[1] + spring


def plant_step_function(dt=DT, substeps=PLANT_SUBSTEPS) -> ca.Function:
    x, u, p, c = ca.SX.sym("x", NX), ca.SX.sym("u"), ca.SX.sym("p", NP), ca.SX.sym("c", NC)

    def f(z):
        return dynamics_expr(z, u, p, load_torque_expr(z, c))

    zs, xs = ca.SX.sym("z", NX), ca.SX.sym("xs", NX)
    h = dt / substeps
    res = zs - xs - 0.5 * h * (f(xs) + f(zs))
    newton = ca.Function("pn", [zs, xs, u, p, c], [zs - ca.solve(ca.jacobian(res, zs), res)])
    z = x
    for _ in range(substeps):
        z0 = z
        z = z0 + h * f(z0)
        z = newton(z, z0, u, p, c)
        z = newton(z, z0, u, p, c)
    return ca.Function("cable_plant", [x, u, p, c], [z, load_torque_expr(z, c)],
                       ["x", "u", "p", "c"], ["xnext", "tau_env"])


_PLANT_FN = {}


def _plant_fn():
    if "fn" not in _PLANT_FN:
        fns, how = compile_functions([plant_step_function()], "cable_plant")
        _PLANT_FN["fn"], _PLANT_FN["how"] = fns["cable_plant"], how
    return _PLANT_FN["fn"]


class SimulatedPlant:
    """The "hardware": ``measure()`` reads the quantised motor encoder, ``actuate(tau)`` applies
    a motor torque for one period (dt) and advances the true state.
    """

    def __init__(self, params: GrasperParams | None = None, *, contact: HuntCrossley | None = None,
                 spring: LinearSpring | None = None, torque_noise_std: float = 5e-4,
                 encoder_cpr: int = ENCODER_CPR, torque_limit: float = 0.5, seed: int = 0,
                 x0=None, dt: float = DT):
        if not math.isfinite(torque_noise_std) or torque_noise_std < 0:
            raise InputError(f"torque_noise_std={torque_noise_std!r} must be a finite number >= 0")
        if int(encoder_cpr) <= 0:
            raise InputError(f"encoder_cpr={encoder_cpr!r} must be a positive count per revolution")
        if not torque_limit > 0:
            raise InputError(f"torque_limit={torque_limit!r} must be > 0 N m")
        if abs(dt - DT) > 1e-12:
            raise InputError(f"the plant runs at dt={DT} s; got dt={dt!r}")
        self.params = params or GrasperParams()
        self.contact, self.spring = contact, spring
        self.noise_std, self.torque_limit = float(torque_noise_std), float(torque_limit)
        self.res = 2.0 * math.pi / int(encoder_cpr)
        self.dt = dt
        self._call = BufferedCall(_plant_fn())
        self._x, self._u, self._p, self._c = self._call.args
        self._xn, self._tau_env = self._call.res
        self._p[:] = self.params.vector()
        self.set_loads(contact, spring)
        x0 = np.zeros(NX) if x0 is None else np.asarray(x0, dtype=float).ravel()
        if x0.shape != (NX,):
            raise InputError(f"x0 has {x0.size} entries, expected {NX} (q_m, q_l, qd_m, qd_l)")
        self._x[:] = x0
        self._rng = np.random.default_rng(seed)
        self._noise = np.empty(4096)
        self._ni = self._noise.size
        self.t = 0.0
        self.applied_torque = 0.0

    def set_loads(self, contact: HuntCrossley | None, spring: LinearSpring | None) -> None:
        c = np.zeros(NC)
        if contact is not None:
            c[:5] = (contact.q_contact, contact.lever, contact.k, contact.n, contact.lam)
        else:
            c[:5] = (1e9, 1.0, 0.0, 1.0, 0.0)  # contact never reached
        if spring is not None:
            c[5:8] = (spring.q0, spring.k, 1.0)
        self._c[:] = c
        self.contact, self.spring = contact, spring

    def set_params(self, params: GrasperParams) -> None:
        self.params = params
        self._p[:] = params.vector()

    @property
    def state(self) -> np.ndarray:
        """True state [q_m, q_l, qd_m, qd_l] (ground truth, not available to the controller)."""
        return self._x.copy()

    @property
    def link_angle(self) -> float:
        return float(self._x[1])

    @property
    def env_torque(self) -> float:
        """Torque the loads (tissue, spring) put on the link after the last step [N m]."""
        return float(self._tau_env[0])

    def measure(self) -> float:
        """Quantised motor angle [rad] (2000 counts/rev by default)."""
        return math.floor(self._x[0] / self.res) * self.res

    def actuate(self, tau: float) -> None:
        if self._ni >= self._noise.size:
            self._rng.standard_normal(out=self._noise)
            self._ni = 0
        tau = min(max(float(tau), -self.torque_limit), self.torque_limit)
        self.applied_torque = tau
        self._u[0] = tau + self.noise_std * self._noise[self._ni]
        self._ni += 1
        self._call()
        self._x[:] = self._xn
        self.t += self.dt
