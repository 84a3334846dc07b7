"""A simulated Raven II arm: DH kinematics, closed-form IK, per-joint PID at 1 kHz.

Joint dynamics (one decoupled second-order system per joint, reflected to the joint side)::

    J_i qdd_i = tau_i - b_i qd_i + Q_i(q)           (Q: gravity on shoulder, elbow, insertion)
    tau_i     = sat(Kp_i e_i + Ki_i int(e_i) - Kd_i qd_i + g_ff_i,  +/- tau_max_i),  e = q_d - q
    |qd_i|   <= v_max_i,   q_i clamped at the hard stops (the joint limits), velocity zeroed there

integrated semi-implicitly (viscous term implicit) at the control rate (1 kHz). The derivative
acts on the measured velocity (no kick when a servo setpoint steps); there is no velocity
feed-forward, so the arm lags a moving setpoint by about (Kd + b) / Kp * velocity, i.e. a
realistic tracking error. Gravity is a lumped mass at the wrist, compensated by a model-based
feed-forward that is deliberately imperfect (``gravity_compensation`` < 1); the integral term,
clamped for anti-windup, removes the residual.

Default values (per joint: shoulder, elbow, insertion, tool roll, wrist, grasper yaw), chosen
to land in the Raven II's range (reflected motor inertias of the cable-driven joints, the
controller's 1 kHz rate, V_MAX = 3 rad/s from the Raven's defines.h):

=================  ======  ======  =========  ======  ======  ======
quantity           should. elbow   insertion  roll    wrist   yaw
=================  ======  ======  =========  ======  ======  ======
inertia J          0.06    0.04    0.40 kg    2e-5    2e-5    2e-5    (kg m^2 unless noted)
viscous b          0.05    0.04    2.0 Ns/m   1e-5    1e-5    1e-5    (Nm s/rad)
bandwidth wn       120     120     150        200     200     200     (rad/s)
damping ratio      0.8     0.8     0.8        0.8     0.8     0.8
integral rate wi   10      10      10         10      10      10      (1/s: Ki = Kp wi)
tau_max            8       8       40 N       0.05    0.05    0.05    (Nm)
v_max              3       3       0.3 m/s    10      10      10      (rad/s)
fault_error        0.3     0.3     0.05 m     1.0     1.0     1.0     (rad)
integral_band      1e-3    1e-3    1e-4 m     5e-3    5e-3    5e-3    (rad)
=================  ======  ======  =========  ======  ======  ======

The integral only accumulates while the joint's setpoint rests and |e| <= integral_band
(conditional integration, clamped to a quarter of the torque range): it removes static offsets
(the gravity residual) once a setpoint is held, but is frozen while setpoints stream, so during
motion the arm behaves as the PD loop (lag and a small gravity droop) and a stop settles
without an integral overshoot.

Kp = J wn^2, Kd = 2 zeta wn J - b. With these, a 5 cm/s straight line of the tool tip is
followed with about 0.5-0.7 mm of error (depending on the direction and the pose) and a stop
settles to < 0.05 mm within a few tens of ms (see tests/test_robot_raven2.py).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from pointfence.kernels.errors import InputError

from .base import Robot, as_pose, as_vector
from .raven2_kinematics import D4, JOINT_HOME, JOINT_LOWER, JOINT_NAMES, JOINT_UPPER, Raven2Kinematics

DEFAULTS = dict(
    inertia=(0.06, 0.04, 0.40, 2e-5, 2e-5, 2e-5),
    damping=(0.05, 0.04, 2.0, 1e-5, 1e-5, 1e-5),
    bandwidth=(120.0, 120.0, 150.0, 200.0, 200.0, 200.0),
    damping_ratio=(0.8,) * 6,
    integral_rate=(10.0,) * 6,
    max_torque=(8.0, 8.0, 40.0, 0.05, 0.05, 0.05),
    max_velocity=(3.0, 3.0, 0.3, 10.0, 10.0, 10.0),
    fault_error=(0.3, 0.3, 0.05, 1.0, 1.0, 1.0),
    integral_band=(1e-3, 1e-3, 1e-4, 5e-3, 5e-3, 5e-3),
)
#: fraction of the integral term's torque budget: |Ki * integral| <= this * tau_max
INTEGRAL_SHARE = 0.25


class Raven2(Robot):
    """Simulated Raven II arm (6 joints: shoulder, elbow, insertion, tool roll, wrist, grasper yaw).

    Options (all SI; per-joint ones take 6 values):
    ``arm`` ('right' | 'left'), ``q0`` (start joints, default the Raven's home), ``T_world_base``
    (mount, 4x4 or 16 numbers, default identity: the world frame is the base frame whose origin
    is the RCM), ``joint_lower`` / ``joint_upper`` (narrow the Raven's limits), ``workspace_min`` /
    ``workspace_max`` (a world-frame box the tip must stay in), ``inertia``, ``damping``,
    ``bandwidth``, ``damping_ratio``, ``integral_rate`` (or explicit ``kp``, ``ki``, ``kd``),
    ``max_torque``, ``max_velocity``, ``fault_error``, ``integral_band``, ``gravity`` (bool), ``gravity_vector``
    (world, m/s^2), ``tool_mass`` (kg, lumped at the wrist), ``gravity_compensation`` (0..1),
    ``control_rate_hz`` (1000).
    """

    model = "raven2"

    def __init__(self, *, arm: str = "right", q0=None, T_world_base=None, joint_lower=None, joint_upper=None,
                 workspace_min=None, workspace_max=None, inertia=None, damping=None, bandwidth=None,
                 damping_ratio=None, integral_rate=None, kp=None, ki=None, kd=None, max_torque=None,
                 max_velocity=None, fault_error=None, integral_band=None, gravity: bool = True,
                 gravity_vector: Sequence[float] = (0.0, 0.0, -9.81), tool_mass: float = 0.3,
                 gravity_compensation: float = 0.9, control_rate_hz: float = 1000.0):
        lower = JOINT_LOWER if joint_lower is None else as_vector(joint_lower, 6, "joint_lower")
        upper = JOINT_UPPER if joint_upper is None else as_vector(joint_upper, 6, "joint_upper")
        for i in range(6):
            if lower[i] < JOINT_LOWER[i] - 1e-12 or upper[i] > JOINT_UPPER[i] + 1e-12:
                raise InputError(f"joint limits of {JOINT_NAMES[i]!r} [{lower[i]:.6g}, {upper[i]:.6g}] exceed the "
                                 f"Raven II's [{JOINT_LOWER[i]:.6g}, {JOINT_UPPER[i]:.6g}]")
        super().__init__(JOINT_NAMES, lower, upper, T_world_base=T_world_base, workspace_min=workspace_min,
                         workspace_max=workspace_max,
                         fault_error=DEFAULTS["fault_error"] if fault_error is None else fault_error,
                         control_rate_hz=control_rate_hz)
        self.kin = Raven2Kinematics(arm, self._lower, self._upper)
        self.arm = arm

        def vec(v, key, positive=True, zero_ok=False):
            a = as_vector(DEFAULTS[key] if v is None else v, 6, key)
            if (positive and np.any(a <= 0)) or (zero_ok and np.any(a < 0)):
                raise InputError(f"{key} = {list(a)}; expected {'non-negative' if zero_ok else 'positive'} values")
            return a

        self.inertia = vec(inertia, "inertia")
        self.damping = vec(damping, "damping", positive=False, zero_ok=True)
        wn = vec(bandwidth, "bandwidth")
        zeta = vec(damping_ratio, "damping_ratio")
        wi = vec(integral_rate, "integral_rate", positive=False, zero_ok=True)
        self.kp = self.inertia * wn ** 2 if kp is None else as_vector(kp, 6, "kp")
        self.kd = np.maximum(2.0 * zeta * wn * self.inertia - self.damping, 0.0) if kd is None else as_vector(kd, 6, "kd")
        self.ki = self.kp * wi if ki is None else as_vector(ki, 6, "ki")
        for name in ("kp", "kd", "ki"):
            if np.any(getattr(self, name) < 0):
                raise InputError(f"{name} = {list(getattr(self, name))}; expected non-negative gains")
        self.max_torque = vec(max_torque, "max_torque")
        self.max_velocity = vec(max_velocity, "max_velocity")
        self.integral_band = vec(integral_band, "integral_band", positive=False, zero_ok=True)
        if not isinstance(gravity, bool):
            raise InputError(f"gravity = {gravity!r}; expected true or false")
        self.gravity = gravity
        g_world = as_vector(gravity_vector, 3, "gravity_vector")
        self._g_base = self._T_base_world[:3, :3] @ g_world
        if not (isinstance(tool_mass, (int, float)) and math.isfinite(tool_mass) and tool_mass >= 0):
            raise InputError(f"tool_mass = {tool_mass!r}; expected a number >= 0 (kg)")
        self.tool_mass = float(tool_mass)
        if not (isinstance(gravity_compensation, (int, float)) and 0.0 <= gravity_compensation <= 1.0):
            raise InputError(f"gravity_compensation = {gravity_compensation!r}; expected a number in [0, 1]")
        self.gravity_compensation = float(gravity_compensation)
        self._f_grav = tuple((self.tool_mass * self._g_base).tolist())

        # integral clamp (anti-windup); per-joint constants as Python floats for the scalar loop
        i_max = np.where(self.ki > 0, INTEGRAL_SHARE * self.max_torque / np.maximum(self.ki, 1e-300), 0.0)
        self._c_kp, self._c_ki, self._c_kd = self.kp.tolist(), self.ki.tolist(), self.kd.tolist()
        self._c_imax, self._c_band = i_max.tolist(), self.integral_band.tolist()
        self._c_tmax, self._c_vmax = self.max_torque.tolist(), self.max_velocity.tolist()
        self._int = [0.0] * 6
        self._qd_prev = [0.0] * 6
        self._grav = [0.0] * 6
        self._h = -1.0
        self._c_hj = [0.0] * 6
        self._c_iv = [0.0] * 6
        self._set_period(self.control_period)

        self.reset(JOINT_HOME if q0 is None else q0)

    # ------------------------------------------------------------------ kinematics hooks
    def _fk(self, q, out):
        return self.kin.fk_into(q, out)

    def _ik(self, T_base, seed):
        return self.kin.ik(T_base, seed)

    @property
    def home(self) -> np.ndarray:
        return np.clip(JOINT_HOME, self._lower, self._upper)

    # ------------------------------------------------------------------ dynamics
    def _set_period(self, h: float) -> None:
        self._h = h
        J, b = self.inertia.tolist(), self.damping.tolist()
        for i in range(6):
            self._c_hj[i] = h / J[i]
            self._c_iv[i] = 1.0 / (1.0 + h * b[i] / J[i])

    def _reset_controller(self) -> None:
        self._int[:] = [0.0] * 6

    def gravity_torque(self, q=None) -> np.ndarray:
        """Joint-space gravity load (Nm, Nm, N, 0, 0, 0) of the lumped tool mass at ``q``."""
        out = [0.0] * 6
        self._gravity_into(self._q if q is None else as_vector(q, 6, "q").tolist(), out)
        return np.array(out)

    def _gravity_into(self, q, out) -> None:
        """Generalised gravity force of the tool mass at the wrist point p = (d3 + d4) z3:
        Q_shoulder = z1 . (p x F), Q_elbow = z2 . (p x F) (both axes pass the RCM), Q_ins = z3 . F."""
        kin = self.kin
        ca, sa = kin._ca, kin._sa
        off = kin.arm.offset
        th1, th2 = q[0] + off[0], q[1] + off[1]
        c1, s1, c2, s2 = math.cos(th1), math.sin(th1), math.cos(th2), math.sin(th2)
        # shaft z3 = RotX(a0) RotZ(th1) RotX(a1) RotZ(th2) (0, -s a2, c a2)
        wx, wy, wz = s2 * sa[2], -c2 * sa[2], ca[2]
        mx, my, mz = wx, ca[1] * wy - sa[1] * wz, sa[1] * wy + ca[1] * wz
        vx, vy, vz = c1 * mx - s1 * my, s1 * mx + c1 * my, mz
        ux, uy, uz = vx, ca[0] * vy - sa[0] * vz, sa[0] * vy + ca[0] * vz
        # elbow axis z2 = RotX(a0) RotZ(th1) (0, -s a1, c a1); shoulder axis z1 = RotX(a0) e_z
        ex, ey, ez = s1 * sa[1], -c1 * sa[1], ca[1]
        z2x, z2y, z2z = ex, ca[0] * ey - sa[0] * ez, sa[0] * ey + ca[0] * ez
        z1y, z1z = -sa[0], ca[0]
        L = q[2] + D4
        px, py, pz = L * ux, L * uy, L * uz
        fx, fy, fz = self._f_grav
        cx, cy, cz = py * fz - pz * fy, pz * fx - px * fz, px * fy - py * fx
        out[0] = z1y * cy + z1z * cz
        out[1] = z2x * cx + z2y * cy + z2z * cz
        out[2] = ux * fx + uy * fy + uz * fz

    def _advance(self, dt: float) -> None:
        n = max(1, int(math.ceil(dt / self.control_period - 1e-9)))
        h = dt / n
        if h != self._h:
            self._set_period(h)
        q, dq, tau, qd, integ, grav = self._q, self._dq, self._tau, self._q_d, self._int, self._grav
        qprev = self._qd_prev
        kp, ki, kd, imax, band = self._c_kp, self._c_ki, self._c_kd, self._c_imax, self._c_band
        tmax, vmax, hj, iv, lo, hi = self._c_tmax, self._c_vmax, self._c_hj, self._c_iv, self._lo, self._hi
        gravity, comp = self.gravity, self.gravity_compensation
        for _ in range(n):
            if gravity:
                self._gravity_into(q, grav)
            for i in range(6):
                qi = q[i]
                e = qd[i] - qi
                # conditional integration (setpoint at rest, error in the band), clamped
                if qd[i] == qprev[i]:
                    if -band[i] <= e <= band[i]:
                        v = integ[i] + e * h
                        m = imax[i]
                        integ[i] = m if v > m else (-m if v < -m else v)
                else:
                    qprev[i] = qd[i]
                g = grav[i]
                t = kp[i] * e + ki[i] * integ[i] - kd[i] * dq[i] - comp * g
                m = tmax[i]
                if t > m:
                    t = m
                elif t < -m:
                    t = -m
                tau[i] = t
                # plant, viscous term implicit: dq+ = (dq + h (tau + Q) / J) / (1 + h b / J)
                v = (dq[i] + (t + g) * hj[i]) * iv[i]
                m = vmax[i]
                if v > m:
                    v = m
                elif v < -m:
                    v = -m
                qi += v * h
                # hard stops
                if qi < lo[i]:
                    qi, v = lo[i], 0.0
                elif qi > hi[i]:
                    qi, v = hi[i], 0.0
                q[i] = qi
                dq[i] = v

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def mount_tool_down(rcm_world=(0.0, 0.0, 0.0), arm: str = "right", q=None) -> np.ndarray:
        """A ``T_world_base`` that puts the RCM at ``rcm_world`` and turns the base so that, at
        joints ``q`` (default the home pose), the tool shaft points straight down (-z world)
        and the shoulder axis lies in the world x-z plane. For demos and tests; the real Raven
        is registered instead."""
        kin = Raven2Kinematics(arm)
        q = JOINT_HOME if q is None else as_vector(q, 6, "q")
        _, u = kin.wrist_point(q)
        L = q[2] + D4
        d = np.array(u) * (1.0 if L > 0 else -1.0)   # RCM -> wrist, base frame
        z1, _ = kin.joint_axes(q)
        # world axes expressed in the base frame: -z_w = d; x_w from the shoulder axis
        zw = -d / np.linalg.norm(d)
        xw = np.array(z1) - np.dot(z1, zw) * zw
        xw /= np.linalg.norm(xw)
        yw = np.cross(zw, xw)
        R_base_world = np.column_stack([xw, yw, zw])
        T = np.eye(4)
        T[:3, :3] = R_base_world.T
        T[:3, 3] = as_vector(rcm_world, 3, "rcm_world")
        return as_pose(T, "T_world_base")
