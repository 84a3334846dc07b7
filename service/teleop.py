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
"""
from __future__ import annotations

import numpy as np

from pointfence.kernels.errors import InputError

ARCHITECTURES = ("I", "II", "III")
#: master motion (world frame, m, after scaling) that ends an arm's anchoring after a re-anchor
ANCHOR_RELEASE = 1e-4
ARCH_CODE = {"I": 1, "II": 2, "III": 3}
_TINY = 1e-12


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
    """

    def __init__(self, n: int, T_world_master=None, scale: float = 0.5, max_robot_speed: float = 0.05,
                 dt: float = 1e-3, architecture="III"):
        T = np.eye(4) if T_world_master is None else np.asarray(T_world_master, dtype=float)
        self.n = int(n)
        self.R = np.ascontiguousarray(T[:3, :3])
        self.RT = np.ascontiguousarray(self.R.T)
        self.p = T[:3, 3].copy()
        self.scale = float(scale)
        self.vmax = float(max_robot_speed)
        self.dt = float(dt)
        self.arch = arch_code(architecture)
        z = lambda: np.zeros((self.n, 3))  # noqa: E731
        self.dev_prev = z()      # last valid master sample (master frame)
        self.X_m = z()           # mapped master point (world)
        self.hip = z()           # HIP used this tick
        self.e_hip = z()         # HIP blend offset
        self.target = z()        # the HIP's target (X_m, or X_r in II) without the blend offset
        self._blending = False   # e_hip may be non-zero
        self.cmd = z()           # robot command X_r* (world)
        self.goal = z()          # command goal before the rate limit
        self._t3 = z()
        self._t3b = z()
        self._nrm = np.zeros(self.n)
        self._fac = np.zeros(self.n)
        self.live = np.zeros(self.n, bool)      # master sample valid and pedal down, last tick
        #: re-anchored arms whose command stays put until their master has moved ANCHOR_RELEASE
        self.anchored = np.zeros(self.n, bool)
        self._moved = np.zeros(self.n)
        self._act = np.zeros(self.n, bool)
        self._inact = np.zeros(self.n, bool)
        self.rebase = True                       # next HIP update keeps the HIP continuous
        self._anchoring = False
        self.law_changed = False                 # set by set_architecture, taken by the service

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
        self._blending = False
        self.live[:] = False
        self.anchored[:] = False
        self._anchoring = False
        self.rebase = False

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

    # --- per tick --------------------------------------------------------------------------------
    def map_masters(self, dev: np.ndarray, pedal: np.ndarray, ok: np.ndarray) -> None:
        """Integrate master motion into X_m for arms whose pedal is down and whose sample is valid
        on this tick and the previous one (indexing: anything else leaves X_m where it is)."""
        act, inact, d = self._act, self._inact, self._t3
        np.logical_and(pedal, ok, out=act)
        np.logical_and(act, self.live, out=inact)   # active now and last tick
        self.live[:] = act
        act[:] = inact
        np.logical_not(act, out=inact)
        np.subtract(dev, self.dev_prev, out=d)
        np.copyto(d, 0.0, where=inact[:, None])      # also clears NaN from invalid samples
        np.matmul(d, self.RT, out=self._t3b)
        self._t3b *= self.scale
        if self._anchoring:      # an anchored arm's X_m stays on its command; the motion only counts
            self._moved += self._norms(self._t3b)
            np.logical_and(self.anchored, self._moved < ANCHOR_RELEASE, out=self.anchored)
            np.copyto(self._t3b, 0.0, where=self.anchored[:, None])
            self._anchoring = bool(self.anchored.any())
        self.X_m += self._t3b
        np.copyto(self.dev_prev, dev, where=ok[:, None])

    def hip_target(self, xr: np.ndarray, out: np.ndarray) -> np.ndarray:
        """The HIP by architecture: X_r for II, X_m otherwise."""
        out[:] = xr if self.arch == 2 else self.X_m
        return out

    def proxy_hip(self) -> np.ndarray:
        """The point the proxies move towards this tick (after ``update_hip``): the HIP, except in
        III, where the proxy is the robot's goal: there it is X_m itself, so that the HIP's
        decaying blend offset, which keeps the force continuous, never moves the robot (S1)."""
        return self.target if self.arch == 3 else self.hip

    def update_hip(self, xr: np.ndarray) -> np.ndarray:
        """This tick's HIP: target plus the decaying blend offset (continuous across switches)."""
        target = self.hip_target(xr, self.target)
        if self.rebase:
            np.subtract(self.hip, target, out=self.e_hip)
            self.rebase = False
            self._blending = True
        if self._blending:       # an offset left by a switch or a re-anchoring decays to zero
            self._shrink(self.e_hip, self.vmax * self.dt)
            self._blending = bool(self.e_hip.any())
            np.add(target, self.e_hip, out=self.hip)
        else:
            self.hip[:] = target
        return self.hip

    def command_goal(self, proxies, haptics_running: bool) -> np.ndarray:
        """X_r* before the rate limit: the proxy in III (while rendering), X_m otherwise."""
        if self.arch == 3 and haptics_running:
            self.goal[:] = proxies
        else:
            self.goal[:] = self.X_m
        return self.goal

    def reanchor(self, mask: np.ndarray) -> None:
        """Indexing for arms in ``mask`` that (re)couple (pedal down, recovery from a hold): X_m
        shifts by (command - goal), so that the goal equals the current command and the robot
        does not move (S1), while the operator's push into a fixture (X_m beyond the proxy) is
        kept. In III the goal is the proxy: the caller places it on the command (``Service.tick``;
        it was frozen while the arm held). The HIP stays continuous."""
        m = np.asarray(mask, bool)[:, None]
        d = self._t3b
        np.subtract(self.cmd, self.goal, out=d)
        np.copyto(d, 0.0, where=~m)
        self.X_m += d
        np.copyto(self.goal, self.cmd, where=m)
        self._anchor(m[:, 0])
        self.rebase = True

    def _anchor(self, mask) -> None:
        """Arms in ``mask`` keep their command (and X_m) until their master has moved
        ``ANCHOR_RELEASE`` (S1: after a re-anchor the arm follows only new master motion, not the
        fixture's response to depth noise); motion before the releasing tick's is not mapped."""
        self.anchored |= mask
        np.copyto(self._moved, 0.0, where=mask)
        self._anchoring = bool(self.anchored.any())

    def reanchor_all(self) -> None:
        """A change of control law (architecture, haptics or teleoperation engaged or not, new
        fixture parameters): every arm's X_m moves onto its command, so that under any law the
        goal is the command and no robot moves by itself (S1); in III the caller places the
        proxies on the commands, which then move towards ``proxy_hip()``: X_m itself, not the
        decaying HIP. The HIP stays continuous, so the force does not jump."""
        self.X_m[:] = self.cmd
        self.goal[:] = self.cmd
        self._anchor(True)
        self.rebase = True

    def limit_command(self, coupled: np.ndarray) -> np.ndarray:
        """Move the command of coupled arms towards the goal by at most ``max_robot_speed * dt``."""
        d = self._t3
        np.subtract(self.goal, self.cmd, out=d)
        if self._anchoring or not coupled.all():
            np.logical_not(coupled, out=self._inact)
            np.logical_or(self._inact, self.anchored, out=self._inact)
            np.copyto(d, 0.0, where=self._inact[:, None])
        self._clamp(d, self.vmax * self.dt)
        self.cmd += d
        return self.cmd

    # --- vector helpers (in place, no allocation) -------------------------------------------------
    def _norms(self, v: np.ndarray) -> np.ndarray:
        np.einsum("ij,ij->i", v, v, out=self._nrm)
        np.sqrt(self._nrm, out=self._nrm)
        return self._nrm

    def _clamp(self, v: np.ndarray, length: float) -> None:
        """Scale rows of ``v`` longer than ``length`` down to it."""
        n = self._norms(v)
        np.maximum(n, length, out=self._fac)
        np.maximum(self._fac, _TINY, out=self._fac)
        np.divide(length, self._fac, out=self._fac)
        np.minimum(self._fac, 1.0, out=self._fac)
        v *= self._fac[:, None]

    def _shrink(self, v: np.ndarray, length: float) -> None:
        """Shorten every row of ``v`` by ``length`` (rows shorter than that become zero)."""
        n = self._norms(v)
        np.maximum(n, _TINY, out=self._fac)
        np.divide(length, self._fac, out=self._fac)
        np.subtract(1.0, self._fac, out=self._fac)
        np.maximum(self._fac, 0.0, out=self._fac)
        v *= self._fac[:, None]
