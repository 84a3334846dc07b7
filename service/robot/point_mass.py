"""The minimal robot: a Cartesian point mass servoed by a PD controller.

    m xdd = F - c xd,    F = sat(Kp (x_d - x) - Kd xd, |F| <= max_force),    |xd| <= max_velocity

per axis, integrated semi-implicitly at the control rate (1 kHz). The derivative acts on the
measured velocity, so the mass lags a moving setpoint by (Kd + c) / Kp * velocity (0.9 mm at
5 cm/s with the defaults) and a stop settles in a few tens of ms. Force and velocity are
saturated on their norms (the direction is kept). Its "joints" are the three Cartesian
coordinates x, y, z of the base frame; the joint limits are the workspace box. The orientation
is kinematic: a 4x4 command sets it at once and measured_cp reports it unchanged.

Defaults: mass 0.5 kg, damping 2 Ns/m, bandwidth 100 rad/s, damping ratio 0.9 (Kp = m wn^2 =
5000 N/m, Kd = 2 zeta wn m - c = 88 Ns/m), max_force 10 N, max_velocity 0.5 m/s, workspace
[-0.5, 0.5]^3 m (the scene configuration's default), fault_error 0.05 m per axis.
"""
from __future__ import annotations

import math

import numpy as np

from pointfence.kernels.errors import InputError

from .base import Robot, _fmt, as_vector

AXES = ("x", "y", "z")


def _positive(v, name: str, zero_ok: bool = False) -> float:
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (v >= 0 if zero_ok else v > 0)
    if not ok:
        raise InputError(f"{name} = {v!r}; expected a number {'>= 0' if zero_ok else '> 0'}")
    return float(v)


class PointMass(Robot):
    """Cartesian point-mass robot (3 prismatic 'joints' x, y, z in the base frame).

    Options: ``mass`` (kg), ``damping`` (Ns/m), ``bandwidth`` (rad/s), ``damping_ratio`` (or
    explicit ``kp`` N/m, ``kd`` Ns/m), ``max_force`` (N, norm), ``max_velocity`` (m/s, norm),
    ``workspace_min`` / ``workspace_max`` (the box, in the base frame, the mass may occupy: its
    joint limits), ``x0`` (start position), ``T_world_base``, ``fault_error`` (m per axis, 0
    disables the following-error fault), ``control_rate_hz``.
    """

    model = "point-mass"

    def __init__(self, *, mass: float = 0.5, damping: float = 2.0, bandwidth: float = 100.0,
                 damping_ratio: float = 0.9, kp=None, kd=None, max_force: float = 10.0,
                 max_velocity: float = 0.5, workspace_min=(-0.5, -0.5, -0.5), workspace_max=(0.5, 0.5, 0.5),
                 x0=None, T_world_base=None, fault_error=0.05, control_rate_hz: float = 1000.0):
        self.mass = _positive(mass, "mass")
        self.damping = _positive(damping, "damping", zero_ok=True)
        wn = _positive(bandwidth, "bandwidth")
        zeta = _positive(damping_ratio, "damping_ratio")
        self.kp = self.mass * wn * wn if kp is None else _positive(kp, "kp")
        self.kd = max(2.0 * zeta * wn * self.mass - self.damping, 0.0) if kd is None else _positive(kd, "kd", zero_ok=True)
        self.max_force = _positive(max_force, "max_force")
        self.max_velocity = _positive(max_velocity, "max_velocity")
        fe = _positive(fault_error, "fault_error", zero_ok=True)
        lo = as_vector(workspace_min, 3, "workspace_min")
        hi = as_vector(workspace_max, 3, "workspace_max")
        # the box bounds the joints (base frame); the base class checks only joint limits then
        super().__init__(AXES, lo, hi, T_world_base=T_world_base, fault_error=None if fe == 0 else (fe,) * 3,
                         control_rate_hz=control_rate_hz)
        self._R = np.eye(3)          # kinematic orientation (base frame)
        self._h = -1.0
        self._set_period(self.control_period)
        if x0 is None:
            x0 = 0.5 * (self._lower + self._upper)
        self.reset(x0)

    @property
    def home(self) -> np.ndarray:
        return 0.5 * (self._lower + self._upper)

    # ------------------------------------------------------------------ kinematics hooks
    def _fk(self, q, out):
        out[:3, :3] = self._R
        out[0, 3], out[1, 3], out[2, 3] = q[0], q[1], q[2]
        out[3] = (0.0, 0.0, 0.0, 1.0)
        return out

    def _ik(self, T_base, seed):
        p = T_base[:3, 3]
        lo, hi = self._lo, self._hi
        for i in range(3):
            if not (lo[i] <= p[i] <= hi[i]):
                raise InputError(f"position {_fmt(p)} m (base frame) is outside the workspace "
                                 f"[{_fmt(self._lower)}, {_fmt(self._upper)}] on axis {AXES[i]}")
        return p.copy()

    def servo_cp(self, T) -> bool:
        applied = super().servo_cp(T)
        if applied:
            R_base = self._T_d[:3, :3] if self._identity_mount else self._T_base_world[:3, :3] @ self._T_d[:3, :3]
            if not np.array_equal(R_base, self._R):
                self._R[...] = R_base
                self._T_meas_ok = False
        return applied

    # ------------------------------------------------------------------ dynamics
    def _set_period(self, h: float) -> None:
        self._h = h
        self._hm = h / self.mass
        self._iv = 1.0 / (1.0 + h * self.damping / self.mass)

    def _advance(self, dt: float) -> None:
        n = max(1, int(math.ceil(dt / self.control_period - 1e-9)))
        h = dt / n
        if h != self._h:
            self._set_period(h)
        x, v, f, xd = self._q, self._dq, self._tau, self._q_d
        kp, kd, fmax, vmax, hm, iv = self.kp, self.kd, self.max_force, self.max_velocity, self._hm, self._iv
        lo, hi = self._lo, self._hi
        for _ in range(n):
            fx = kp * (xd[0] - x[0]) - kd * v[0]
            fy = kp * (xd[1] - x[1]) - kd * v[1]
            fz = kp * (xd[2] - x[2]) - kd * v[2]
            fn = math.sqrt(fx * fx + fy * fy + fz * fz)
            if fn > fmax:
                s = fmax / fn
                fx, fy, fz = fx * s, fy * s, fz * s
            f[0], f[1], f[2] = fx, fy, fz
            vx = (v[0] + fx * hm) * iv
            vy = (v[1] + fy * hm) * iv
            vz = (v[2] + fz * hm) * iv
            vn = math.sqrt(vx * vx + vy * vy + vz * vz)
            if vn > vmax:
                s = vmax / vn
                vx, vy, vz = vx * s, vy * s, vz * s
            v[0], v[1], v[2] = vx, vy, vz
            for i in range(3):
                xi = x[i] + v[i] * h
                if xi < lo[i]:
                    xi, v[i] = lo[i], 0.0
                elif xi > hi[i]:
                    xi, v[i] = hi[i], 0.0
                x[i] = xi
