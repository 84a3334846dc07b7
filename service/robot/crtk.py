"""A CRTK robot over ROS 2 (``[robot] model = "crtk"``): a dVRK PSM, or any arm that speaks CRTK.

The arm's controller runs elsewhere (its own computer, its own process); pointfence streams the
setpoint on ``<ns>/servo_cp`` (``geometry_msgs/PoseStamped``, a full pose in the arm's base
frame: the tick's position, the orientation of the setpoint, which is seated on the measured
orientation when the arm holds or is enabled) and reads ``<ns>/measured_cp``,
``<ns>/measured_js`` and ``<ns>/operating_state`` (crtk_wire.py). With ``jaw = true`` the jaw's
setpoint (the master's grasp, rad) streams on ``<ns>/jaw/servo_jp`` (``sensor_msgs/JointState``,
one position) and its angle is read from ``<ns>/jaw/measured_js``, as the dVRK names them; until
the arm has reported its jaw the service does not command it. ``CrtkRobot`` is the robot
interface of service/robot/base.py over that exchange; ``ros2/crtk_bridge.CrtkBridge`` is its rclpy side.

Threads: the arm's ``step`` (the tick, or the robot process's period) takes the measured_cp and
measured_js messages that arrived since the last step from the bridge (ros2/crtk_bridge.py:
``poll``, no executor thread in between), checks them, and publishes its setpoint on
``servo_cp``; the bridge's node thread serves the slow topics (operating_state, the jaw) and
swaps in the newest of each as a tuple.
Live runs (``[service] robot_process = true``) build the arm in the robot process
(robot/hosted_child.py), which is then the arms' ROS bridge; the service's process sees the
shared-memory exchange only (its copy of the arm is built with ``connect=False``).

Safety (SAFETY.md S3, S9). Each ``step`` checks, before anything is sent:

* a ``measured_cp`` newer than ``measured_timeout_s`` (the watchdog; a ``measured_js`` too);
* that it is a finite rigid pose (a unit quaternion) in frame ``frame_id``;
* that ``measured_js`` has ``dof`` finite positions (and velocities, efforts where given);
* that the operating state is ``ENABLED`` (unless ``operating_state_type = "none"``).

Any of them failing puts the arm in FAULT with the reason (``fault_reason``); the service's
tick holds an arm in FAULT, and nothing is published while the arm is not ENABLED (HOLDING:
held by the service; FAULT). The measured pose keeps the last valid one. ``enable()`` (the
service's clear-faults path) clears a FAULT only while every check passes on fresh state; else
``last_error`` says why. Commands outside ``workspace_min``/``workspace_max`` are refused with an
InputError, as every model refuses them.

Round trip: ``round_trip_us()`` (ros2/crtk_bridge.py), where the arm echoes servo_cp's stamp.
"""
from __future__ import annotations

import math
import time
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from .. import limits
from ..ros2 import crtk_wire as wire
from .base import Robot, RobotMode

#: default watchdog (s): 20 ms is 20 periods of a 1 kHz measured_cp (the dVRK publishes at 1 kHz
#: and more): a lost sample or two, a scheduling hiccup of the bridge, never a dead arm
MEASURED_TIMEOUT_S = 0.02
#: the largest joint value an unknown controller's joints may take (its limits are its own)
_NO_LIMIT = 1e9


class CrtkRobot(Robot):
    """A CRTK arm over ROS 2 (module docstring). World = the service's frame; the arm's poses on
    the wire are in its base frame, ``T_world_base`` maps them.

    Options (``[robot] model = "crtk"``): ``namespace`` ("PSM1"), ``frame_id`` (the base frame's
    name in the arm's messages; default "<namespace>_base"), ``dof`` (joints in measured_js),
    ``T_world_base``, ``workspace_min``/``workspace_max`` (world, m), ``measured_timeout_s``
    (the watchdog, s), ``operating_state_type`` ("crtk", "string", "none"), topic overrides
    ``servo_cp_topic``, ``measured_cp_topic``, ``measured_js_topic``, ``operating_state_topic``
    (relative names are under the namespace), ``connect_timeout_s`` (how long the constructor
    waits for the arm's first valid state; without it the arm starts in FAULT), ``control_rate_hz``.
    ``connect=False`` opens no ROS connection: a copy for geometry and checks (the service's
    side of an arm in the robot process), whose state is adopted (``adopt_state``).
    """

    model = "crtk"
    #: a real arm: it cannot be placed (``reset``) by the robot process after a restart
    simulated = False

    def __init__(self, *, namespace: str = "PSM1", frame_id: str = "", dof: int = 6, T_world_base=None,
                 workspace_min=None, workspace_max=None, measured_timeout_s: float = MEASURED_TIMEOUT_S,
                 operating_state_type: str = "crtk", servo_cp_topic: str = "", measured_cp_topic: str = "",
                 measured_js_topic: str = "", operating_state_topic: str = "", connect_timeout_s: float = 5.0,
                 control_rate_hz: float = 1000.0, jaw: bool = False, jaw_min: float = 0.0,
                 jaw_max: float = 0.5 * math.pi, connect: bool = True):
        ns = wire.check_namespace(namespace)
        if isinstance(dof, bool) or not isinstance(dof, int) or not 1 <= dof <= 32:
            raise InputError(f"dof = {dof!r}; expected the number of joints in the arm's measured_js (1-32)")
        if operating_state_type not in wire.STATE_KINDS:
            raise InputError(f"operating_state_type = {operating_state_type!r}; expected one of "
                             f"{', '.join(wire.STATE_KINDS)}")
        self.measured_timeout_s = limits.check("robot.measured_timeout_s", measured_timeout_s, "measured_timeout_s")
        if not (isinstance(connect_timeout_s, (int, float)) and 0 < connect_timeout_s <= 60):
            raise InputError(f"connect_timeout_s = {connect_timeout_s!r}; expected a number of seconds in (0, 60]")
        super().__init__([f"joint{i}" for i in range(dof)], [-_NO_LIMIT] * dof, [_NO_LIMIT] * dof,
                         T_world_base=T_world_base, workspace_min=workspace_min, workspace_max=workspace_max,
                         control_rate_hz=control_rate_hz)
        if not (isinstance(jaw_min, (int, float)) and isinstance(jaw_max, (int, float)) and math.isfinite(jaw_min)
                and math.isfinite(jaw_max) and -math.pi <= jaw_min < jaw_max <= math.pi):
            raise InputError(f"jaw_min = {jaw_min!r}, jaw_max = {jaw_max!r}; expected -pi <= jaw_min < jaw_max <= pi (rad)")
        #: (lo, hi) the jaw's range (rad), None: the arm's jaw is not driven ([robot] jaw = false)
        self.jaw_limits = (float(jaw_min), float(jaw_max)) if jaw else None
        self._jaw = math.nan               # measured jaw angle (rad), NaN until the arm reports it
        self._jaw_d = math.nan             # jaw setpoint (rad), NaN: none to send
        self.namespace = ns
        self.frame_id = frame_id or f"{ns.replace('/', '_') or 'arm'}_base"
        self.state_kind = operating_state_type
        self.topics = {"servo_cp": wire.topic(ns, "servo_cp", servo_cp_topic),
                       "measured_cp": wire.topic(ns, "measured_cp", measured_cp_topic),
                       "measured_js": wire.topic(ns, "measured_js", measured_js_topic),
                       "operating_state": wire.topic(ns, "operating_state", operating_state_topic)}
        if jaw:
            self.topics.update({"jaw_servo_jp": wire.topic(ns, "jaw/servo_jp"),
                                "jaw_measured_js": wire.topic(ns, "jaw/measured_js")})
        self._T_meas_ok = True             # the measured pose is taken, never computed (no kinematics here)
        self._base = np.eye(4)             # scratch: a pose in the base frame
        self._cp_seen = self._js_seen = self._bad_seen = self._bad_js_seen = None
        self._cp_bad: Optional[str] = None
        self._js_bad: Optional[str] = None
        self._bridge = None
        if connect:
            from ..ros2.crtk_bridge import CrtkBridge

            self._bridge = CrtkBridge(ns, self.topics, self.frame_id, operating_state_type)
            self._connect(connect_timeout_s)

    def _connect(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` for valid state; then ENABLED with the setpoint on the measured
        pose, else FAULT saying what is missing."""
        end = time.monotonic() + timeout_s
        why = self._take()
        while why is not None and time.monotonic() < end:
            time.sleep(0.01)
            why = self._take()
        if why is None:
            self._seat()
            self._mode = RobotMode.ENABLED
        else:
            self.fault(f"{why} (after waiting {timeout_s:g} s: is the arm's ROS node running, in this ROS_DOMAIN_ID?)")

    # ---------------------------------------------------------------- the state, from the bridge
    def _take(self) -> Optional[str]:
        """Take the bridge's newest messages (checked; a bad one is not taken) and say why the
        arm may not be commanded now (None: it may)."""
        b = self._bridge
        b.poll()
        now = time.monotonic()
        cp = b.cp
        if cp is None:
            return f"no measured_cp on {self.topics['measured_cp']} yet"
        bad = b.bad_cp
        if bad is not self._bad_seen:      # a bad sample since the last step, even if a good one followed
            self._bad_seen = bad
            if cp is not self._cp_seen:
                self._cp_seen = cp
                self._cp_bad = self._take_cp(cp)
            return f"measured_cp on {self.topics['measured_cp']} {bad[1]}"
        if cp is not self._cp_seen:
            self._cp_seen = cp
            self._cp_bad = self._take_cp(cp)
        if self._cp_bad is not None:
            return self._cp_bad
        age = now - cp[0]
        if age > self.measured_timeout_s:
            return (f"no fresh measured_cp on {self.topics['measured_cp']} for {1e3 * age:.0f} ms "
                    f"(measured_timeout_s = {1e3 * self.measured_timeout_s:.0f} ms)")
        bad = b.bad_js
        if bad is not self._bad_js_seen:   # (as for measured_cp: a message that could not be read)
            self._bad_js_seen = bad
            return f"measured_js on {self.topics['measured_js']} {bad[1]}"
        js = b.js
        if js is None:
            return f"no measured_js on {self.topics['measured_js']} yet"
        if js is not self._js_seen:
            self._js_seen = js
            self._js_bad = self._take_js(js)
        if self._js_bad is not None:
            return self._js_bad
        age = now - js[0]
        if age > self.measured_timeout_s:
            return (f"no fresh measured_js on {self.topics['measured_js']} for {1e3 * age:.0f} ms "
                    f"(measured_timeout_s = {1e3 * self.measured_timeout_s:.0f} ms)")
        if self.state_kind != "none":
            st = b.state
            if st is None:
                return f"no operating_state on {self.topics['operating_state']} yet"
            if st[1] != wire.ENABLED:
                return f"operating state {st[1]!r} on {self.topics['operating_state']}; expected {wire.ENABLED!r}"
        if b.error is not None:
            return f"the ROS 2 node stopped: {b.error}"
        jaw = b.jaw
        if jaw is not None and self.jaw_limits is not None:
            if len(jaw[1]) != 1 or not math.isfinite(jaw[1][0]):
                return f"jaw/measured_js on {self.topics['jaw_measured_js']} has positions {list(jaw[1])}; expected one finite angle"
            self._jaw = jaw[1][0]
        return None

    def _take_cp(self, cp: tuple) -> Optional[str]:
        if cp[2] != self.frame_id:
            return (f"measured_cp on {self.topics['measured_cp']} has frame_id {cp[2]!r}; expected "
                    f"{self.frame_id!r} ([robot] frame_id)")
        pose = cp[3:]
        why = wire.pose_problem(pose)
        if why is not None:
            return f"measured_cp on {self.topics['measured_cp']} {why}"
        wire.pose_to_matrix(pose, self._base)
        if self._identity_mount:
            np.copyto(self._T_meas, self._base)
        else:
            np.matmul(self._T_world_base, self._base, out=self._T_meas)
        return None

    def _take_js(self, js: tuple) -> Optional[str]:
        _, q, dq, tau = js
        n = self.dof
        where = self.topics["measured_js"]
        if len(q) != n:
            return f"measured_js on {where} has {len(q)} positions; expected {n} ([robot] dof = {len(q)} for this arm?)"
        for name, v in (("velocity", dq), ("effort", tau)):
            if len(v) not in (0, n):
                return f"measured_js on {where} has {len(v)} {name} values; expected {n} or none"
        if not math.isfinite(sum(q) + sum(dq) + sum(tau)):
            return f"measured_js on {where} is not finite: position {list(q)}"
        self._q[:] = q
        self._dq[:] = dq if dq else [0.0] * n
        self._tau[:] = tau if tau else [0.0] * n
        return None

    def _seat(self) -> None:
        """The setpoint onto the measured pose, joints and jaw (no motion)."""
        np.copyto(self._T_d, self._T_meas)
        self._q_d[:] = self._q
        self._jaw_d = self._jaw

    # ---------------------------------------------------------------- the Robot hooks
    def _fk(self, q, out):
        raise InputError("a CRTK arm's kinematics are its controller's: pointfence has no forward kinematics "
                         "for it (measured_cp is the arm's own)")

    def _ik(self, T_base, seed):
        raise InputError("a CRTK arm's kinematics are its controller's: servo_cp sends the pose itself")

    def _stop(self) -> None:
        """A FAULT stops sending; the measured joints stay what the arm says they are."""

    def _advance(self, dt: float) -> None:
        """One exchange with the arm: take its newest state, fault on any failed check, and
        stream the setpoint (base frame) while ENABLED."""
        why = self._take()
        if why is not None:
            if self._mode is not RobotMode.FAULT:
                self.fault(why)
            return
        if self._mode is RobotMode.ENABLED:
            base = self._base
            if self._identity_mount:
                np.copyto(base, self._T_d)
            else:
                np.matmul(self._T_base_world, self._T_d, out=base)
            self._bridge.send(wire.pose_of(base))
            if self.jaw_limits is not None and self._jaw_d == self._jaw_d:     # (not NaN)
                self._bridge.send_jaw(self._jaw_d)

    def step(self, dt: float = 1e-3) -> None:
        """Exchange with the arm (``_advance``) and advance the time by ``dt`` (s). An arm with no
        connection (``connect=False``) only advances its time."""
        if not (dt > 0.0) or dt == math.inf:
            raise InputError(f"step: dt = {dt!r}; expected a finite number > 0")
        if self._bridge is not None:
            self._advance(dt)
        self.t += dt

    # ---------------------------------------------------------------- commands
    def servo_cp(self, T) -> bool:
        """Stream a Cartesian setpoint: a 4x4 world pose, or a position (3,) with the setpoint's
        orientation; it leaves at the next ``step``. InputError (counted, nothing sent) on a
        malformed, non-finite or out-of-workspace pose; False, nothing sent, unless ENABLED."""
        pose = self.checked_setpoint(T, out=self._scratch4)
        if self._mode is not RobotMode.ENABLED:
            self.ignored_commands += 1
            return False
        np.copyto(self._T_d, pose)
        return True

    def measured_jaw(self) -> float:
        """The jaw's angle from ``jaw/measured_js`` (rad; NaN until the arm has reported it)."""
        return self._jaw

    def servo_jaw(self, angle: float) -> bool:
        """Stream a jaw setpoint (rad, within ``jaw_limits``) on ``jaw/servo_jp`` from the next
        ``step``. InputError (counted) without a jaw, on a non-finite angle or one outside the
        range; False, nothing sent, unless ENABLED."""
        if self.jaw_limits is None:
            self._reject(f"servo_jaw: the CRTK arm {self.namespace!r} has no jaw ([robot] jaw = false)")
        lo, hi = self.jaw_limits
        if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not lo <= angle <= hi:
            self._reject(f"servo_jaw: angle = {angle!r} rad; expected a finite number in [{lo:g}, {hi:g}] "
                         "([robot] jaw_min, jaw_max)")
        if self._mode is not RobotMode.ENABLED:
            self.ignored_commands += 1
            return False
        self._jaw_d = float(angle)
        return True

    def servo_jp(self, q) -> bool:
        raise InputError("servo_jp is not sent to a CRTK arm: pointfence streams servo_cp only")

    def hold(self) -> None:
        """Stop streaming; the setpoint moves onto the measured pose (the next resume streams from
        where the arm is). The arm keeps its last servo_cp, one rate-limited increment ahead at most."""
        if self._mode is RobotMode.ENABLED:
            self._seat()
            self._mode = RobotMode.HOLDING

    def enable(self) -> None:
        """Clear a FAULT (or leave HOLDING) only while the arm's state is fresh, valid and ENABLED;
        else stay and say why in ``last_error``. The setpoint re-seats on the measured pose."""
        if self._bridge is not None:
            why = self._take()
            if why is not None:
                self.last_error = f"enable refused: {why}"
                return
        if self._mode is RobotMode.FAULT:
            self._seat()
            self._fault = None
        self._mode = RobotMode.ENABLED

    def reset(self, q=None) -> None:
        """A real arm cannot be placed: with ``q`` an InputError; without, the setpoint re-seats on
        the measured pose (as ``hold``, keeping the mode)."""
        if q is not None:
            raise InputError("reset(q): a CRTK arm cannot be placed; move it with its own controller")
        self._seat()

    # ---------------------------------------------------------------- extras
    @property
    def connected(self) -> bool:
        return self._bridge is not None

    def round_trip_us(self, taken: bool = False) -> list:
        """servo_cp -> echoing measured_cp times (us) so far, where the arm echoes the stamp: to
        its reception (``taken``: to the step that took it)."""
        return [] if self._bridge is None else self._bridge.round_trip_us(taken)

    def close(self) -> None:
        """Stop the ROS node (idempotent); the arm then reads FAULT at its next step."""
        if self._bridge is not None:
            self._bridge.close()
            self._bridge = None
            self.fault("the CRTK arm's ROS node was closed")
