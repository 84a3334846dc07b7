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
ARCH_CODE = {"I": 1, "II": 2, "III": 3}


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
        slip_lift: III's slip lift radius, m (0: off; the fixture radius turns it on, with
            ``bind_normals``).

    State, (B, 3) world-frame arrays updated in place: ``X_m`` (mapped master point), ``hip``
    (this tick's HIP), ``cmd`` (robot command X_r*), ``goal`` (the command's goal before the
    rate limit), ``target`` (the HIP without its blend offset), ``e_hip`` (the blend offset);
    ``dev_prev`` (last valid master sample, master frame); (B,) ``live`` (valid and pedal down
    last tick), ``anchored`` (re-anchored, command held until the master moves).
    ``core`` is the compiled core's view of all of it (``native.TeleopCore``).
    """

    def __init__(self, n: int, T_world_master=None, scale: float = 0.5, max_robot_speed: float = 0.05,
                 dt: float = 1e-3, architecture="III", slip_lift: float = 0.0):
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

    def start(self, dev, robot_positions=None) -> None:
        """Initial state: X_m on the robot (or the registered master with no robot), command on
        the robot, HIP on X_m."""
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
    def map_masters(self, dev: np.ndarray, pedal: np.ndarray, ok: np.ndarray) -> None:
        """Integrate master motion into X_m for arms whose pedal is down and whose sample is valid
        on this tick and the previous one (indexing: anything else leaves X_m where it is). An
        anchored arm's X_m stays put until its master has moved ``ANCHOR_RELEASE``."""
        n = self.n
        lib.pf_teleop_map_masters(self.ref, ptr_to(dev, float, (n, 3), "dev"), ptr_to(pedal, bool, (n,), "pedal"),
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

