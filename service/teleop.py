"""Teleoperation for B master-robot pairs: registration, scaling, clutch and indexing, the three
fixture architectures (dissertation eqs. 3.1-3.3), switching without jumps, the speed limit.

All quantities are world-frame positions (m) in (B, 3) arrays updated in place every tick.

* Registration and scaling: a master displacement dx (master frame) moves the mapped master
  point X_m by ``scale * R_world_master dx``. At start X_m is the robot's position (or, with no
  robot, ``T_world_master`` applied to ``scale * x``).
* Clutch (foot pedal) with indexing: while the pedal is up, or the master gives no valid
  sample, X_m stays where it is and the robot holds; the operator may move the master freely.
  On every re-engagement (pedal down, teleoperation engaged, recovery from a hold) X_m is
  re-anchored so that the robot's command goal equals its current command: re-engaging never
  moves the robot.
* Architectures (``ARCHITECTURES``): I: HIP = X_m, X_r* = X_m; II: HIP = X_r, X_r* = X_m;
  III: HIP = X_m, X_r* = X_proxy. With haptic rendering disengaged there is no proxy and
  III's goal becomes X_m (the fixture is off).
* Changes of control law (architecture switch, haptics or teleoperation engaged or disengaged,
  new fixture parameters) re-anchor every arm (``reanchor_all``): X_m moves onto the command,
  so no such change moves a robot by itself (SAFETY.md S1). After any re-anchoring an arm's
  command stays where it is until its master has moved ``ANCHOR_RELEASE`` (0.1 mm): what
  moves the arm then is the operator, not the fixture settling on a noisy cloud.
* No jumps: whenever the HIP's source changes (architecture switch, re-anchoring), the HIP keeps
  its value and an offset e_hip = HIP - target takes up the difference; e_hip then shrinks by at
  most ``max_robot_speed * dt`` per tick, so the spring force changes by at most
  ``k_s * max_robot_speed * dt`` per tick from the switch. In III the proxies move towards the
  target itself (``proxy_hip``): the proxy is the robot's goal there, and the offset exists
  only for the force. Every robot command is rate-limited:
  the commanded point X_r* moves at most ``max_robot_speed * dt`` per tick towards its goal
  (this is architecture III's limit against the proxy jumping at edges; it also makes switching
  I <-> III smooth, and bounds I and II as a safety limit).
* Slip lift (III, ``slip_lift`` > 0 with the proxies' normals bound, ``bind_normals``): a proxy
  pressed into a noisy cloud slips sideways across its bumps faster than the rate-limited
  command follows, and the straight path to it cuts through them. The command's goal is then
  raised along the proxy's surface normal by min(L^2 / slip_lift, slip_lift), L the command's
  distance to the proxy across the normal: zero while the command keeps up, at most
  ``slip_lift`` (the fixture radius) over a slip.

Orientation and the jaw (unit quaternions w, x, y, z; angles in rad):

* Registration and indexing: the mapped master orientation is ``q_m = q_R q_dev q_off``
  (``q_R``: the registration's rotation R_world_master; ``q_dev``: the master's sample in its
  own frame; ``q_off``: the indexing offset). While the pedal is up or the sample is invalid,
  ``q_m`` stays and ``q_off`` takes up whatever the master does; at every re-anchor (the same
  events as X_m's) ``q_m`` is set to the commanded orientation and ``q_off`` re-seated to match:
  re-engaging never rotates the tool. An anchored arm's orientation, too, is held until the
  master has moved ``ANCHOR_RELEASE`` or rotated ``ANCHOR_RELEASE_RAD``.
* The commanded orientation ``q_cmd`` follows ``q_m`` under every architecture (the fixture
  acts on the tool tip only), at most ``max_angular_speed * dt`` per tick; a robot that
  decouples keeps its measured orientation.
* The jaw follows the master's grasp, clamped to the robot's jaw range, at most
  ``max_jaw_speed * dt`` per tick, for coupled arms. After a re-anchor it waits until the
  grasp reaches it (crosses the jaw's angle, or comes within one step), as the dVRK's jaw does:
  re-engaging never moves the jaw either. A robot that decouples keeps its measured jaw;
  where the robot's jaw angle is unknown (NaN) the jaw is not commanded.

The arithmetic runs in the compiled tick core (``native/tick_core.c``, ``pf_teleop_*``) on this
class's arrays; ``Service.step`` calls it there directly, the methods here call the same
functions one at a time.
"""
from __future__ import annotations

import ctypes

import numpy as np

from pointfence.kernels.errors import InputError
from pointfence.native import TeleopCore, lib, ptr, ptr_to

ARCHITECTURES = ("I", "II", "III")
#: master motion (world frame, m, after scaling) that ends an arm's anchoring after a re-anchor
ANCHOR_RELEASE = 1e-4
#: master rotation (rad) that ends an arm's anchoring after a re-anchor (0.06 deg)
ANCHOR_RELEASE_RAD = 1e-3
#: the jaw range of an arm whose robot states none (an ideal robot), rad
DEFAULT_JAW_RANGE = (0.0, 0.5 * np.pi)
ARCH_CODE = {"I": 1, "II": 2, "III": 3}


def quat_of_rotation(R) -> np.ndarray:
    """The unit quaternion (w, x, y, z; w >= 0) of 3x3 rotation ``R`` (the tick core's)."""
    R = np.ascontiguousarray(R, dtype=float).reshape(3, 3)
    q = np.zeros(4)
    lib.pf_quats_of_matrices(ptr(R, np.float64, "R"), 3, 1, ptr(q, np.float64, "q"))
    return q


def quat_mul(a, b) -> np.ndarray:
    """Hamilton product of quaternions (w, x, y, z) ``a`` and ``b`` (rows broadcast)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def quat_angle(a, b) -> np.ndarray:
    """The angle (rad) between orientations ``a`` and ``b`` (unit quaternions w, x, y, z)."""
    d = quat_mul(a, np.asarray(b, float) * (1.0, -1.0, -1.0, -1.0))       # a b^-1
    return 2.0 * np.arctan2(np.linalg.norm(d[..., 1:], axis=-1), np.abs(d[..., 0]))


def _unit_rows(q) -> np.ndarray:
    """Rows of ``q`` (n, 4) as unit quaternions with w >= 0; identity where a row is not finite or ~0."""
    q = np.array(q, dtype=float).reshape(-1, 4)
    n = np.linalg.norm(q, axis=1)
    bad = ~np.isfinite(n) | (n < 1e-12)
    q[bad] = (1.0, 0.0, 0.0, 0.0)
    n[bad] = 1.0
    q /= np.where(q[:, 0] < 0, -n, n)[:, None]
    return q


def arch_code(architecture) -> int:
    """``"I" | "II" | "III"`` (or 1, 2, 3) -> 1, 2, 3."""
    if isinstance(architecture, str) and architecture.upper() in ARCH_CODE:
        return ARCH_CODE[architecture.upper()]
    if isinstance(architecture, (int, np.integer)) and int(architecture) in (1, 2, 3):
        return int(architecture)
    raise InputError(f"architecture = {architecture!r}; expected 'I', 'II' or 'III' (eqs. 3.1-3.3)")


class Teleop:
    """The teleoperation state of B arms; see the module docstring.

    Args:
        n: number of master-robot pairs (one proxy each).
        T_world_master: 4x4 registration of the master frame in the world frame.
        scale: motion scaling (robot motion per master motion).
        max_robot_speed: bound on the command's (and the HIP blend's) speed, m/s.
        dt: tick period, s.
        architecture: initial architecture.
        max_angular_speed: bound on the commanded orientation's angular speed, rad/s.
        max_jaw_speed: bound on the jaw command's speed, rad/s.
        jaw_range: (B, 2) each arm's jaw range (rad), or one (lo, hi) for all.
        slip_lift: III's slip lift radius, m (0: off; the fixture radius turns it on, with
            ``bind_normals``).

    State, (B, 3) world-frame arrays updated in place: ``X_m`` (mapped master point), ``hip``
    (this tick's HIP), ``cmd`` (robot command X_r*), ``goal`` (the command's goal before the
    rate limit), ``target`` (the HIP without its blend offset), ``e_hip`` (the blend offset);
    ``dev_prev`` (last valid master sample, master frame); (B,) ``live`` (valid and pedal down
    last tick), ``anchored`` (re-anchored, command held until the master moves).
    Orientation and jaw: (B, 4) unit quaternions (w, x, y, z) ``q_m`` (mapped master
    orientation, world), ``q_cmd`` (commanded orientation, world), ``q_off`` (indexing offset),
    ``q_last`` (last valid master orientation, master frame); (B,) ``grasp`` (last valid grasp,
    rad), ``jaw_cmd`` (the jaw command, rad; NaN: unknown, not commanded), ``jaw_lo``/``jaw_hi``.
    ``core`` is the compiled core's view of all of it (``native.TeleopCore``).
    """

    def __init__(self, n: int, T_world_master=None, scale: float = 0.5, max_robot_speed: float = 0.05,
                 dt: float = 1e-3, architecture="III", max_angular_speed: float = 3.0,
                 max_jaw_speed: float = 3.0, jaw_range=DEFAULT_JAW_RANGE, slip_lift: float = 0.0):
        T = np.eye(4) if T_world_master is None else np.asarray(T_world_master, dtype=float)
        self.n = int(n)
        self.R = np.ascontiguousarray(T[:3, :3])
        self.RT = np.ascontiguousarray(self.R.T)
        self.p = T[:3, 3].copy()
        self.scale = float(scale)
        self.vmax = float(max_robot_speed)
        self.dt = float(dt)
        z = lambda: np.zeros((self.n, 3))  # noqa: E731
        self.dev_prev = z()
        self.X_m = z()
        self.hip = z()
        self.e_hip = z()
        self.target = z()
        self.cmd = z()
        self.goal = z()
        self._moved = np.zeros(self.n)
        self.live = np.zeros(self.n, bool)
        self.anchored = np.zeros(self.n, bool)
        c = self.core = TeleopCore(n=self.n, scale=self.scale, vmax=self.vmax, dt=self.dt,
                                   anchor_release=ANCHOR_RELEASE)
        c.R[:] = self.R.ravel().tolist()
        c.p[:] = self.p.tolist()
        for name in ("dev_prev", "X_m", "hip", "e_hip", "target", "cmd", "goal"):
            setattr(c, name, ptr(getattr(self, name), np.float64, name))
        c.moved = ptr(self._moved, np.float64, "moved")
        c.live, c.anchored = ptr(self.live, bool, "live"), ptr(self.anchored, bool, "anchored")
        self.wmax, self.jaw_vmax = float(max_angular_speed), float(max_jaw_speed)
        self.qR = quat_of_rotation(self.R)
        ident = lambda: np.tile([1.0, 0.0, 0.0, 0.0], (self.n, 1))  # noqa: E731
        self.q_last, self.q_off, self.q_m, self.q_cmd = ident(), ident(), ident(), ident()
        self._ang_moved = np.zeros(self.n)
        self.grasp = np.zeros(self.n)
        self.jaw_cmd = np.zeros(self.n)
        jr = np.broadcast_to(np.asarray(jaw_range, dtype=float), (self.n, 2))
        if not np.isfinite(jr).all() or np.any(jr[:, 0] >= jr[:, 1]):
            raise InputError(f"jaw_range = {jr.tolist()}; expected finite (lo, hi) with lo < hi (rad) per arm")
        self.jaw_lo, self.jaw_hi = np.ascontiguousarray(jr[:, 0]), np.ascontiguousarray(jr[:, 1])
        self._jaw_side = np.zeros(self.n)
        self.jaw_wait = np.zeros(self.n, bool)
        c.wmax, c.jaw_vmax, c.anchor_release_rad = self.wmax, self.jaw_vmax, ANCHOR_RELEASE_RAD
        c.qR[:] = self.qR.tolist()
        for name in ("q_last", "q_off", "q_m", "q_cmd", "grasp", "jaw_cmd", "jaw_lo", "jaw_hi"):
            setattr(c, name, ptr(getattr(self, name), np.float64, name))
        c.ang_moved, c.jaw_side = ptr(self._ang_moved, np.float64, "ang_moved"), ptr(self._jaw_side, np.float64, "jaw_side")
        c.jaw_wait = ptr(self.jaw_wait, bool, "jaw_wait")
        self.ref = ctypes.byref(c)
        self.slip_lift = slip_lift
        self._normals = None                     # the bound normals array (kept alive for the core)
        self.arch = arch_code(architecture)
        self.rebase = True                       # next HIP update keeps the HIP continuous
        self.law_changed = False                 # set by set_architecture, taken by the service

    # --- the core's flags ---------------------------------------------------------------------------
    @property
    def arch(self) -> int:
        """The architecture's code: 1, 2, 3 (I, II, III)."""
        return self.core.arch

    @arch.setter
    def arch(self, code: int) -> None:
        self.core.arch = int(code)

    @property
    def rebase(self) -> bool:
        """The next HIP update keeps the HIP continuous (takes up the jump in ``e_hip``)."""
        return bool(self.core.rebase)

    @rebase.setter
    def rebase(self, on: bool) -> None:
        self.core.rebase = int(bool(on))

    @property
    def slip_lift(self) -> float:
        """III's slip lift radius, m (0: off); see the module docstring."""
        return self.core.slip_lift

    @slip_lift.setter
    def slip_lift(self, radius: float) -> None:
        r = float(radius)
        if not (np.isfinite(r) and 0.0 <= r <= 0.1):
            raise InputError(f"slip_lift = {radius!r} m; expected 0 (off) to 0.1 m (the fixture radius)")
        self.core.slip_lift = r

    def bind_normals(self, normals) -> None:
        """The proxies' surface normals, a (B, 3) float32 C-contiguous array the proxy batch
        updates in place every tick (``HapticScene.normals``); None unbinds (no slip lift).
        Bind once, when the batch is made; the array is kept alive here."""
        if normals is None:
            self._normals, self.core.normals = None, None
            return
        if not isinstance(normals, np.ndarray) or normals.shape != (self.n, 3):
            raise InputError(f"normals: expected a ({self.n}, 3) float32 array; got "
                             f"{getattr(normals, 'shape', type(normals).__name__)}")
        self.core.normals = ptr(normals, np.float32, "normals")
        self._normals = normals

    # --- set-up ---------------------------------------------------------------------------------
    def register(self, dev, out) -> np.ndarray:
        """World position of master-frame point(s) ``dev`` under the registration (no indexing)."""
        np.matmul(np.asarray(dev, dtype=float) * self.scale, self.RT, out=out)
        out += self.p
        return out

    def start(self, dev, robot_positions=None, quat=None, grasp=None, robot_orientations=None,
              robot_jaws=None) -> None:
        """Initial state: X_m on the robot (or the registered master with no robot), command on
        the robot, HIP on X_m; the commanded orientation on the robot's (or the registered
        master's: ``q_R quat``) and the mapped one on it; the jaw on the robot's (or, with no
        robot, the master's grasp clamped to the jaw range), waiting for the grasp to reach it."""
        dev = np.asarray(dev, dtype=float).reshape(self.n, 3)
        ok = np.isfinite(dev).all(axis=1)
        self.dev_prev[:] = np.where(ok[:, None], dev, 0.0)
        if robot_positions is not None:
            self.X_m[:] = robot_positions
        else:
            self.register(self.dev_prev, self.X_m)
        self.cmd[:] = self.X_m
        self.goal[:] = self.X_m
        self.hip[:] = self.X_m
        self.e_hip[:] = 0.0
        self.live[:] = False
        self.anchored[:] = False
        self.q_last[:] = _unit_rows(np.tile([1.0, 0.0, 0.0, 0.0], (self.n, 1)) if quat is None else quat)
        self.q_cmd[:] = _unit_rows(quat_mul(self.qR, self.q_last) if robot_orientations is None else robot_orientations)
        g = np.zeros(self.n) if grasp is None else np.asarray(grasp, dtype=float).reshape(self.n)
        self.grasp[:] = np.where(np.isfinite(g), g, 0.0)
        if robot_jaws is None:
            self.jaw_cmd[:] = np.clip(self.grasp, self.jaw_lo, self.jaw_hi)
        else:
            self.jaw_cmd[:] = np.asarray(robot_jaws, dtype=float).reshape(self.n)
        self._ang_moved[:] = 0.0
        lib.pf_teleop_reanchor(self.ref, ptr_to(np.ones(self.n, bool), bool, (self.n,), "mask"))   # q_m, q_off, jaw
        self.anchored[:] = False
        c = self.core
        c.blending = c.anchoring = c.rebase = 0

    def set_architecture(self, architecture) -> None:
        """A new architecture (applied between ticks); ``law_changed`` tells the service to
        re-anchor every arm on its next tick (S1), whoever made the switch."""
        code = arch_code(architecture)
        if code != self.arch:
            self.arch = code
            self.rebase = True
            self.law_changed = True

    @property
    def architecture(self) -> str:
        return ARCHITECTURES[self.arch - 1]

    # --- per tick (``Service.step`` runs these inside the core's ``pf_step_pre`` / ``_post``) ----------
    def map_masters(self, dev: np.ndarray, pedal: np.ndarray, ok: np.ndarray, quat=None, grasp=None) -> None:
        """Integrate master motion into X_m and q_m for arms whose pedal is down and whose sample
        is valid on this tick and the previous one (indexing: anything else leaves them where they
        are). An anchored arm's X_m and q_m stay put until its master has moved ``ANCHOR_RELEASE``
        or rotated ``ANCHOR_RELEASE_RAD``. ``quat`` (B, 4) the master orientations (master
        frame, w x y z; default: the last ones), ``grasp`` (B,) rad (default: the last)."""
        n = self.n
        quat = self.q_last.copy() if quat is None else quat
        grasp = self.grasp.copy() if grasp is None else grasp
        lib.pf_teleop_map_masters(self.ref, ptr_to(dev, float, (n, 3), "dev"), ptr_to(quat, float, (n, 4), "quat"),
                                  ptr_to(grasp, float, (n,), "grasp"), ptr_to(pedal, bool, (n,), "pedal"),
                                  ptr_to(ok, bool, (n,), "ok"))

    def proxy_hip(self) -> np.ndarray:
        """The point the proxies move towards this tick (after ``update_hip``): the HIP, except in
        III, where the proxy is the robot's goal: there it is X_m itself, so that the HIP's
        decaying blend offset, which keeps the force continuous, never moves the robot (S1)."""
        return self.target if self.arch == 3 else self.hip

    def update_hip(self, xr: np.ndarray) -> np.ndarray:
        """This tick's HIP: its target (X_r ``xr`` in II, X_m otherwise) plus the decaying blend
        offset (continuous across switches)."""
        lib.pf_teleop_update_hip(self.ref, ptr_to(xr, float, (self.n, 3), "xr"))
        return self.hip

    def command_goal(self, proxies, haptics_running: bool) -> np.ndarray:
        """X_r* before the rate limit: the proxy in III (while rendering; raised by the slip
        lift when it is on), X_m otherwise."""
        lib.pf_teleop_command_goal(self.ref, ptr_to(proxies, np.float32, (self.n, 3), "proxies"),
                                   int(bool(haptics_running)))
        return self.goal

    def reanchor(self, mask: np.ndarray) -> None:
        """Indexing for arms in ``mask`` that (re)couple (pedal down, recovery from a hold): X_m
        shifts by (command - goal), so that the goal equals the current command and the robot
        does not move (S1), while the operator's push into a fixture (X_m beyond the proxy) is
        kept. In III the goal is the proxy: the caller places it on the command (``Service.step``;
        it was frozen while the arm held). The HIP stays continuous. The arms stay anchored
        (command held) until their master has moved ``ANCHOR_RELEASE``: after a re-anchor an arm
        follows only new master motion, not the fixture's response to depth noise."""
        lib.pf_teleop_reanchor(self.ref, ptr_to(mask, bool, (self.n,), "mask"))

    def reanchor_all(self) -> None:
        """A change of control law (architecture, haptics or teleoperation engaged or not, new
        fixture parameters): every arm's X_m moves onto its command, so that under any law the
        goal is the command and no robot moves by itself (S1); in III the caller places the
        proxies on the commands, which then move towards ``proxy_hip()``: X_m itself, not the
        decaying HIP. The HIP stays continuous, so the force does not jump."""
        lib.pf_teleop_reanchor_all(self.ref)

    def limit_command(self, coupled: np.ndarray) -> np.ndarray:
        """Move the command of coupled, unanchored arms towards the goal by at most
        ``max_robot_speed * dt``."""
        lib.pf_teleop_limit_command(self.ref, ptr_to(coupled, bool, (self.n,), "coupled"))
        return self.cmd

