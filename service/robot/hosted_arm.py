"""One arm of the robot process (robot/hosted.py ``RobotHost``), as the service sees it: the robot
interface of robot/base.py over the shared-memory exchange; geometry from a local copy of the
model, state as of the arm's last ``step``, commands queued for the child.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError
from pointfence.native import SERVO_IGNORED, SERVO_QUEUED, SERVO_REJECTED

from .base import JointState, RobotMode, RobotState
from .hosted_block import ENABLE, FAULT, HOLD, RESUME

_MODES = tuple(RobotMode)


class HostedRobot:
    """One arm of a ``RobotHost``: the robot interface the service and the self-filter use (the
    ``robot/base.py`` interface, each member spelt out here; nothing else of the model is reached).

    Geometry (``kin``, ``joint_limits``, ``workspace``, ``T_world_base``, ``home``, the
    kinematics) is the local model's, which never changes. Reads (``t``, ``state``,
    ``fault_reason``, ``measured_cp``, ``measured_js``, ``setpoint_cp`` ...) are the child's state
    as of this arm's last ``step``: the tick's reads (``state``, ``measured_cp``, ``measured_jaw``,
    ``measured_jp_into``) straight from the row the compiled exchange gave the arm, the others
    from the local model, which adopts that row when one of them asks (``_sync``). Commands
    (``servo_cp``, ``hold``, ``resume``, ``enable``, ``fault``) go to the child. A FAULT of the
    robot process itself (silent, dead, non-finite state) is latched here: the arm reads FAULT
    with that reason, sends nothing, and only ``enable()`` clears it, once ``RobotHost.ready``
    allows. ``rejected_commands`` and ``ignored_commands`` count the child's and this side's (a
    setpoint refused or ignored here never reaches the child).
    """

    hosted = True

    def __init__(self, host, index: int, local):
        self._host, self._b, self._r = host, index, local
        self._L = host.layout
        self.model: str = local.model
        self.dof: int = local.dof
        self.joint_names: tuple = local.joint_names
        self.control_period: float = local.control_period
        self._local_rejected = 0          # setpoints refused here (malformed, workspace)
        self._local_ignored = 0           # setpoints not sent: the arm was not ENABLED here
        self._last_error: Optional[str] = None
        self._latched: Optional[str] = None   # FAULT of the robot process (reason), until enable()
        self._pose = np.eye(4)            # the setpoint being sent (scratch, the checked path)
        #: (lo, hi) the jaw's range (rad) where the model has a jaw, else None
        self.jaw_limits = local.jaw_limits
        L = self._L
        row = host.taken_row(index)       # the row this arm took last (the exchange writes it)
        self._row = memoryview(row)       # (an element of a memoryview is a Python float)
        self._T_meas4 = row[L.T_meas].reshape(4, 4)
        self._T_meas16 = memoryview(row[L.T_meas])
        self._q_row = row[L.q]
        self._mode = memoryview(host.mode_of_all())[index:index + 1]

    @property
    def host(self):
        """The ``RobotHost`` this arm belongs to."""
        return self._host

    @property
    def index(self) -> int:
        """This arm's index in its host (its row in the shared block)."""
        return self._b

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
    def _sync(self) -> None:
        """The local model takes the row this arm took last, if it has not yet, and the setpoint
        and mode the exchange holds (the reads that are not the tick's, and this side's mode
        commands, work on the model)."""
        host, b, r, L = self._host, self._b, self._r, self._L
        T_d, q_d, mode = host.setpoint_of(b)
        if host.take_fresh(b):             # (else the model has the row, and the mode: this side set it)
            row = self._row
            r.adopt_state(row[L.t], row[L.q], row[L.dq], row[L.tau], self._T_meas16, mode)
        r.adopt_setpoint(memoryview(T_d), q_d.tolist())

    def _push(self) -> None:
        """Give the exchange the local model's mode and setpoint after a command of this side."""
        r = self._r
        self._host.set_local(self._b, int(r.state), r.setpoint_cp(), r.setpoint_js().position)

    @property
    def t(self) -> float:
        """The child's time (s) of the state last taken."""
        return self._row[self._L.t]

    @property
    def state(self) -> RobotMode:
        return _MODES[int(self._mode[0])]

    @property
    def fault_reason(self) -> Optional[str]:
        return self._r.fault_reason

    @property
    def last_error(self) -> Optional[str]:
        return self._last_error

    @property
    def rejected_commands(self) -> int:
        return int(self._row[self._L.rejected]) + self._local_rejected

    @property
    def ignored_commands(self) -> int:
        return int(self._row[self._L.ignored]) + self._local_ignored

    @property
    def latched(self) -> bool:
        """Whether the arm is in a FAULT of the robot process (cleared only by ``enable()``)."""
        return self._latched is not None

    def measured_cp(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        if out is None:
            return self._T_meas4.copy()
        np.copyto(out, self._T_meas4)
        return out

    def measured_cp_position(self) -> np.ndarray:
        return self._T_meas4[:3, 3].copy()

    def measured_jp_into(self, out: np.ndarray) -> None:
        out[: self.dof] = self._q_row

    def measured_jp_view(self) -> np.ndarray:
        """The measured joints (dof,) as a live view of the row this arm took (rad or m per
        joint): the exchange rewrites it in place at every step (``ToolPoseRing`` copies it)."""
        return self._q_row

    def measured_js(self) -> JointState:
        self._sync()
        return self._r.measured_js()

    def setpoint_cp(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        self._sync()
        return self._r.setpoint_cp(out)

    def setpoint_js(self) -> JointState:
        self._sync()
        return self._r.setpoint_js()

    def read_state(self) -> RobotState:
        self._sync()
        st = self._r.read_state()
        st.rejected_commands, st.ignored_commands, st.last_error = (self.rejected_commands, self.ignored_commands,
                                                                    self._last_error)
        return st

    # --- RobotHost's calls ----------------------------------------------------------------------
    def take_texts(self, fault: Optional[str], err: Optional[str]) -> None:
        """Take the child's fault reason and last error (a latched reason stays)."""
        self._r.adopt_texts(self._r.fault_reason if self._latched is not None else fault, err)
        self._last_error = err

    def latch_fault(self, why: str) -> None:
        """Latch a FAULT of the robot process (the first reason stays) and brake the child's arm."""
        if self._latched is not None:
            return
        self._sync()
        self._latched = why
        self._host.set_latched(self._b, True)
        self._r.fault(why)                 # local copy: FAULT, joints stopped; servo_cp sends nothing
        self._push()
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
        setpoint (its message). Returns False, sending nothing, unless the arm is ENABLED.

        A 4x4 float64 array is checked and queued in one compiled call (``RobotHost.servo``);
        anything else, and any pose that fails the check, takes the Python path, which names
        what is wrong."""
        return self.after_servo(self._host.servo(self._b, T), T)

    def after_servo(self, code: int, T) -> bool:
        """``servo_cp``'s answer once the compiled check gave ``code`` for setpoint ``T`` (a
        ``SERVO_*`` code; -1: not checked there): True queued; False ignored (counted);
        InputError for a rejection, or for a pose the Python check refuses (naming what is
        wrong; a pose it accepts is queued)."""
        if code == SERVO_QUEUED:
            return True
        if code == SERVO_IGNORED:
            self._local_ignored += 1
            return False
        if code == SERVO_REJECTED:
            raise InputError(self._last_error or "servo_cp: the robot rejected the previous setpoint")
        host, b = self._host, self._b
        child, seen = host.child_rejections(b)
        if child > seen:
            host.note_rejection_reported(b)
            raise InputError(self._last_error or "servo_cp: the robot rejected the previous setpoint")
        self._sync()
        try:
            self._r.checked_setpoint(T, out=self._pose)   # checks it into the scratch, naming what is wrong
        except InputError as e:
            self._local_rejected += 1
            self._last_error = str(e)
            raise
        if self._latched is not None or self.state is not RobotMode.ENABLED:
            self._local_ignored += 1
            return False
        host.stage_pose(b, self._pose)
        return True

    def measured_jaw(self) -> float:
        """The child's measured jaw angle (rad; NaN: the model has none, or has not reported it)."""
        row, L = self._row, self._L
        return row[L.jaw] if row[L.jaw_known] == 1.0 else math.nan

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
        if self._latched is not None or self.state is not RobotMode.ENABLED:
            self._local_ignored += 1
            return False
        self._host.stage_jaw(self._b, angle)
        return True

    def servo_jp(self, q) -> bool:
        raise InputError("servo_jp is not streamed to a hosted robot; use servo_cp, or run the robots in the "
                         "haptic loop ([service] robot_process = false)")

    def _mode_cmd(self, code: int, local) -> None:
        self._host.send_mode(self._b, code)
        self._sync()
        local()
        self._push()

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
            self._host.set_latched(self._b, False)
        self._mode_cmd(ENABLE, self._r.enable)

    def fault(self, reason: str) -> None:
        self._mode_cmd(FAULT, lambda: self._r.fault(reason))

    def reset(self, q=None) -> None:
        raise InputError("reset places a simulated robot for set-up; a hosted robot starts at its q0 "
                         "(set it in [robot]), or run the robots in the haptic loop ([service] robot_process = false)")

    def close(self) -> None:
        """Nothing: the host owns the process (``RobotHost.close``)."""


__all__ = ["HostedRobot"]
