"""One arm of the robot process (robot/hosted.py ``RobotHost``), as the service sees it: the robot
interface of robot/base.py over the shared-memory exchange; geometry from a local copy of the
model, state as of the arm's last ``step``, commands queued for the child.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from .base import JointState, RobotMode, RobotState
from .hosted_block import ENABLE, FAULT, HOLD, RESUME

_MODES = tuple(RobotMode)


class HostedRobot:
    """One arm of a ``RobotHost``: the robot interface the service and the self-filter use (the
    ``robot/base.py`` interface, each member spelt out here; nothing else of the model is reached).

    Geometry (``kin``, ``joint_limits``, ``workspace``, ``T_world_base``, ``home``, the
    kinematics) is the local model's, which never changes. Reads (``t``, ``state``,
    ``fault_reason``, ``measured_cp``, ``measured_js``, ``setpoint_cp`` ...) are the child's state
    as of this arm's last ``step``. Commands (``servo_cp``, ``hold``, ``resume``, ``enable``,
    ``fault``) go to the child. A FAULT of the robot process itself (silent, dead, non-finite
    state) is latched here: the arm reads FAULT with that reason, sends nothing, and only
    ``enable()`` clears it, once ``RobotHost.ready`` allows. ``rejected_commands`` and
    ``ignored_commands`` count the child's and this side's (a setpoint refused or ignored here
    never reaches the child).
    """

    hosted = True

    def __init__(self, host, index: int, local):
        self._host, self._b, self._r = host, index, local
        self._L = host._L
        self.model: str = local.model
        self.dof: int = local.dof
        self.joint_names: tuple = local.joint_names
        self.control_period: float = local.control_period
        self._child_rejected = 0          # setpoints the child rejected (out of reach)
        self._rejected_seen = 0           # ... of which servo_cp has reported
        self._local_rejected = 0          # setpoints refused here (malformed, workspace)
        self._child_ignored = 0           # commands the child ignored
        self._local_ignored = 0           # setpoints not sent: the arm was not ENABLED here
        self._last_error: Optional[str] = None
        self._latched: Optional[str] = None   # FAULT of the robot process (reason), until enable()
        self._pose = np.eye(4)            # the setpoint being sent (scratch), and its 16 floats
        self._pose16 = memoryview(self._pose.reshape(16))
        #: (lo, hi) the jaw's range (rad) where the model has a jaw, else None
        self.jaw_limits = local.jaw_limits
        self._jaw = math.nan              # the child's measured jaw (rad; NaN: none or not known)

    def __repr__(self) -> str:
        return f"HostedRobot({self.model!r}, arm {self._b}, process {self._host.pid})"

    # --- geometry: the model's ------------------------------------------------------------------
    @property
    def kin(self):
        """The model's kinematics object where it has one (Raven II: the instrument's axis for the
        self-filter, robot/tool.py); None otherwise."""
        return getattr(self._r, "kin", None)

    @property
    def joint_limits(self) -> tuple:
        return self._r.joint_limits

    @property
    def workspace(self) -> Optional[tuple]:
        return self._r.workspace

    @property
    def T_world_base(self) -> np.ndarray:
        return self._r.T_world_base

    @property
    def home(self) -> np.ndarray:
        return self._r.home

    def forward_kinematics(self, q) -> np.ndarray:
        return self._r.forward_kinematics(q)

    def inverse_kinematics(self, T, seed=None) -> np.ndarray:
        return self._r.inverse_kinematics(T, seed)

    # --- state: the child's, as of this arm's last step ------------------------------------------
    @property
    def t(self) -> float:
        """The child's time (s) of the state last taken."""
        return self._r.t

    @property
    def state(self) -> RobotMode:
        return self._r.state

    @property
    def fault_reason(self) -> Optional[str]:
        return self._r.fault_reason

    @property
    def last_error(self) -> Optional[str]:
        return self._last_error

    @property
    def rejected_commands(self) -> int:
        return self._child_rejected + self._local_rejected

    @property
    def ignored_commands(self) -> int:
        return self._child_ignored + self._local_ignored

    @property
    def latched(self) -> bool:
        """Whether the arm is in a FAULT of the robot process (cleared only by ``enable()``)."""
        return self._latched is not None

    def measured_cp(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        return self._r.measured_cp(out)

    def measured_cp_position(self) -> np.ndarray:
        return self._r.measured_cp_position()

    def measured_jp_into(self, out: np.ndarray) -> None:
        self._r.measured_jp_into(out)

    def measured_js(self) -> JointState:
        return self._r.measured_js()

    def setpoint_cp(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        return self._r.setpoint_cp(out)

    def setpoint_js(self) -> JointState:
        return self._r.setpoint_js()

    def read_state(self) -> RobotState:
        st = self._r.read_state()
        st.rejected_commands, st.ignored_commands, st.last_error = (self.rejected_commands, self.ignored_commands,
                                                                    self._last_error)
        return st

    # --- RobotHost's calls ----------------------------------------------------------------------
    def take_state(self, row: list, T_meas, T_d, servo_sent: int, modes_sent: int) -> None:
        """Take the child's state row (``row`` as floats; ``T_meas`` and ``T_d``: its two poses, 16
        floats each, as memoryviews or arrays), given the setpoints and mode commands sent to this arm so far.
        Nothing while latched."""
        if self._latched is not None:
            return                         # latched until the host answers again and enable() is called
        r, L = self._r, self._L
        mode = _MODES[int(row[L.mode])] if row[L.mode_seq] >= modes_sent else None   # our mode commands applied
        r.adopt_state(row[L.t], row[L.q], row[L.dq], row[L.tau], T_meas, mode)
        self._child_rejected = int(row[L.rejected])
        self._child_ignored = int(row[L.ignored])
        if row[L.servo_seq] >= servo_sent:  # else keep the setpoint just sent
            r.adopt_setpoint(T_d, row[L.q_d])
        self._jaw = row[L.jaw] if row[L.jaw_known] == 1.0 else math.nan

    def take_texts(self, fault: Optional[str], err: Optional[str]) -> None:
        """Take the child's fault reason and last error (a latched reason stays)."""
        self._r.adopt_texts(self._r.fault_reason if self._latched is not None else fault, err)
        self._last_error = err

    def latch_fault(self, why: str) -> None:
        """Latch a FAULT of the robot process (the first reason stays) and brake the child's arm."""
        if self._latched is not None:
            return
        self._latched = why
        self._r.fault(why)                 # local copy: FAULT, joints stopped; servo_cp sends nothing
        self._host.send_mode(self._b, FAULT)

    # --- the robot interface: commands ----------------------------------------------------------
    def step(self, dt: float = 1e-3) -> None:
        """The child steps on its own clock: this sends every setpoint queued so far and takes this
        arm's newest state (``RobotHost.step_arm``). Right in any order of the arms' calls."""
        if not (dt > 0.0) or dt == math.inf:
            raise InputError(f"step: dt = {dt!r}; expected a finite number > 0")
        self._host.step_arm(self._b)

    def servo_cp(self, T) -> bool:
        """Send a Cartesian setpoint (4x4 world pose, or a position (3,) with the setpoint's
        orientation); it leaves at this arm's ``step``. Raises InputError, sending nothing, on a
        malformed or non-finite pose, a workspace violation, or when the child rejected the previous
        setpoint (its message). Returns False, sending nothing, unless the arm is ENABLED."""
        r = self._r
        if self._child_rejected > self._rejected_seen:
            self._rejected_seen = self._child_rejected
            raise InputError(self._last_error or "servo_cp: the robot rejected the previous setpoint")
        try:
            r.checked_setpoint(T, out=self._pose)    # checks it into the scratch, as the arm in the tick does
        except InputError as e:
            self._local_rejected += 1
            self._last_error = str(e)
            raise
        if self._latched is not None or r.state is not RobotMode.ENABLED:
            self._local_ignored += 1
            return False
        self._host.stage_pose(self._b, self._pose16)
        r.adopt_setpoint(self._pose16)
        return True

    def measured_jaw(self) -> float:
        """The child's measured jaw angle (rad; NaN: the model has none, or has not reported it)."""
        return self._jaw

    def servo_jaw(self, angle: float) -> bool:
        """Send a jaw setpoint (rad, within ``jaw_limits``); it leaves at this arm's ``step``.
        InputError (counted, nothing sent) without a jaw, on a non-finite angle or one outside the
        range; False, nothing sent, unless the arm is ENABLED."""
        lim = self.jaw_limits
        if lim is None or isinstance(angle, bool) or not isinstance(angle, (int, float)) or \
                not lim[0] <= angle <= lim[1]:
            self._local_rejected += 1
            self._last_error = (f"servo_jaw: a {self.model} robot has no jaw" if lim is None else
                                f"servo_jaw: angle = {angle!r} rad; expected a finite number in [{lim[0]:g}, {lim[1]:g}]")
            raise InputError(self._last_error)
        if self._latched is not None or self._r.state is not RobotMode.ENABLED:
            self._local_ignored += 1
            return False
        self._host.stage_jaw(self._b, angle)
        return True

    def servo_jp(self, q) -> bool:
        raise InputError("servo_jp is not streamed to a hosted robot; use servo_cp, or run the robots in the "
                         "haptic loop ([service] robot_process = false)")

    def _mode_cmd(self, code: int, local) -> None:
        self._host.send_mode(self._b, code)
        local()

    def hold(self) -> None:
        self._mode_cmd(HOLD, self._r.hold)

    def resume(self) -> None:
        self._mode_cmd(RESUME, self._r.resume)

    def enable(self) -> None:
        """Clear a FAULT (the setpoint re-seats on the measured joints: no motion). A FAULT of the
        robot process stays, with ``last_error`` saying why, unless ``RobotHost.ready`` allows:
        the process runs and steps and this arm's state is finite."""
        if self._latched is not None:
            why = self._host.ready(self._b)
            if why is not None:
                self._last_error = f"enable refused: {why}"
                return
            self._latched = None
        self._mode_cmd(ENABLE, self._r.enable)

    def fault(self, reason: str) -> None:
        self._mode_cmd(FAULT, lambda: self._r.fault(reason))

    def reset(self, q=None) -> None:
        raise InputError("reset places a simulated robot for set-up; a hosted robot starts at its q0 "
                         "(set it in [robot]), or run the robots in the haptic loop ([service] robot_process = false)")

    def close(self) -> None:
        """Nothing: the host owns the process (``RobotHost.close``)."""


__all__ = ["HostedRobot"]
