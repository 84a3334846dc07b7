"""One 1 kHz control tick: UKF estimate from the motor encoder, iLQG MPC, safety checks.

``CableLoop`` is the allocation-free core shared by the real-time thread
(``controller.CableController``) and the offline simulations (``experiments``): it owns the
UKF (states + external link torque, optionally the cable stiffness for online tension
estimation) and the MPC, and produces the motor torque for the next period. Non-finite
measurements, estimates or torques, and an estimated parameter that leaves its physical range
(e.g. k_e <= 0, a negative friction or damping), latch a fault: the torque is zero until ``reset()``.
"""
from __future__ import annotations

import math
import time

import numpy as np

from .ilqg import ILQGController, MPCConfig
from .params import _NONNEG, _POSITIVE, IDX, NP, PARAM_NAMES, GrasperParams
from .ukf import UKF, UKFConfig

#: Default online estimator: states and the external link torque (section 4.5).
ONLINE_UKF = UKFConfig(estimate=("tau_l",), q_param=(5e-5,), p0_param=(1.0,), q_state=(1e-9, 1e-9, 2e-3, 2e-3))
#: Online estimator that also tracks the cable stiffness (slow random walk) for chapter 5.
ONLINE_UKF_TENSION = UKFConfig(estimate=("tau_l", "k_e"), q_param=(5e-5, 1e-9), p0_param=(1.0, 0.05),
                               q_state=(1e-9, 1e-9, 2e-3, 2e-3))


class CableLoop:
    def __init__(self, params: GrasperParams, ukf_config: UKFConfig | None = None,
                 mpc_config: MPCConfig | None = None):
        self.params = params
        self.ukf = UKF(params, ukf_config or ONLINE_UKF)
        self.mpc = ILQGController(mpc_config)
        # physical range of each estimated parameter: (index, lower bound, strict)
        self._ranges = tuple((i, 0.0, PARAM_NAMES[i] in _POSITIVE) for i in self.ukf.est_idx
                             if PARAM_NAMES[i] in _POSITIVE or PARAM_NAMES[i] in _NONNEG)
        self.N = self.mpc.N
        self._p = np.zeros(NP)
        self.u_prev = 0.0
        self.fault: str | None = None
        self.last_compute_s = 0.0
        self.reset()

    @property
    def qd(self) -> np.ndarray:
        """Desired link angle over the horizon (N+1 values); write in place before ``tick``."""
        return self.mpc.qd

    def reset(self, q_m: float = 0.0, params: GrasperParams | None = None) -> None:
        if params is not None:
            self.params = params
        self.ukf.reset(q_m, params)
        self.mpc.reset()
        self.u_prev = 0.0
        self.fault = None

    def set_params(self, params: GrasperParams) -> None:
        """Swap in re-identified parameters (keeps the current state estimate)."""
        self.params = params
        x = self.ukf.x.copy()
        est = self.ukf.estimates()
        self.ukf.set_params(params)
        self.ukf._xa[:4] = x
        for j, n in enumerate(self.ukf.config.estimate):
            if n == "tau_l":
                self.ukf._xa[4 + j] = est[n] / self.ukf._sc[j]

    def tick(self, y: float) -> float:
        """Measurement y (motor angle) in, torque for the next period out. Zero when faulted."""
        t0 = time.perf_counter()
        if self.fault is not None:
            self.u_prev = 0.0
            return 0.0
        if not math.isfinite(y):
            return self._trip(f"motor encoder reading is not finite ({y})")
        self.ukf.step(self.u_prev, y)
        if not self.ukf.healthy():
            return self._trip("state estimator produced NaN/inf")
        p = self.ukf.params_vector(self._p)
        for i, lo, strict in self._ranges:
            if p[i] < lo or (strict and p[i] == lo):
                return self._trip(f"estimated parameter {PARAM_NAMES[i]}={p[i]:.4g} left its physical range "
                                  f"({'>' if strict else '>='} {lo:g})")
        u = self.mpc.solve(self.ukf.x, self._p)
        if not math.isfinite(u):
            return self._trip("MPC produced a non-finite torque")
        self.u_prev = u
        self.last_compute_s = time.perf_counter() - t0
        return u

    def _trip(self, why: str) -> float:
        self.fault = why
        self.u_prev = 0.0
        return 0.0

    @property
    def tau_l_estimate(self) -> float:
        est = self.ukf.estimates()
        return est.get("tau_l", float(self._p[IDX["tau_l"]]))

    @property
    def k_e_estimate(self) -> float:
        return self.ukf.estimates().get("k_e", self.params.k_e)
