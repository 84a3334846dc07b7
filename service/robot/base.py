"""The CRTK-style robot interface shared by every robot model (simulated or real).

Naming follows CRTK (https://crtk-robotics.readthedocs.io), as the dVRK and Raven II stacks do:
``measured_cp`` (measured Cartesian position: a 4x4 pose), ``measured_js`` (measured joint
state), ``setpoint_cp`` / ``setpoint_js`` (what the controller is servoing to), ``servo_cp`` /
``servo_jp`` (stream a new setpoint; meant to be called every tick with small increments).

Units are SI (m, rad, s, N, Nm). The world frame is the robot base frame (SPEC "Frames and
units"); a model may be mounted with ``T_world_base`` (identity by default), and every pose the
interface takes or returns is in the world frame.

State and commands are plain structs (libfranka style): :class:`JointState`, :class:`RobotState`
(a snapshot from :meth:`Robot.read_state`) and :class:`Command` (the last accepted command).

Safety contract
---------------
* A bad command (non-finite numbers, wrong shape, a non-rigid transform, a pose outside the
  workspace or out of reach, joints outside the limits) raises
  :class:`pointfence.kernels.errors.InputError` with a message that names the value, and changes
  nothing: the previous setpoint stays, the robot keeps servoing to it. The service should then
  call :meth:`Robot.hold`.
* :meth:`Robot.hold` freezes the current setpoint (state HOLDING); servo commands are then
  ignored (they return ``False``) until :meth:`Robot.resume`. Resuming does not move the robot.
* FAULT is entered when the simulated state becomes non-finite, when a joint's following error
  exceeds its ``fault_error`` (a robot that cannot follow its setpoint), or on :meth:`Robot.fault`.
  The joints stop (brakes) and commands are ignored until :meth:`Robot.enable`, which re-seats
  the setpoint on the measured position so enabling never jumps.
"""
from __future__ import annotations

import enum
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import NoReturn, Optional, Sequence

import numpy as np

from pointfence.kernels.errors import InputError
from pointfence.native import lib

#: tolerance on R^T R - I and on the last row of a homogeneous transform
RIGID_TOL = 1e-6
#: tolerance on joint limits for values that come out of inverse kinematics
LIMIT_TOL = 1e-9


class RobotMode(enum.IntEnum):
    """Operating state (CRTK's operating_state, reduced to what the service needs)."""

    ENABLED = 0   #: following servo commands
    HOLDING = 1   #: setpoint frozen by hold(); servo commands ignored until resume()
    FAULT = 2     #: stopped; commands ignored until enable()


@dataclass
class JointState:
    """Joint positions (rad or m), velocities (rad/s or m/s) and efforts (Nm or N)."""

    name: tuple
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


@dataclass
class Command:
    """The last accepted command: ``kind`` is 'cp' (Cartesian pose) or 'jp' (joint positions)."""

    kind: str
    t: float
    pose: Optional[np.ndarray] = None      #: 4x4 world pose for 'cp'
    position: Optional[np.ndarray] = None  #: joint positions for 'jp' (and the IK result of 'cp')


@dataclass
class RobotState:
    """A snapshot of everything the robot knows at time ``t`` (libfranka's RobotState)."""

    t: float
    mode: RobotMode
    measured_cp: np.ndarray       #: 4x4, world frame
    setpoint_cp: np.ndarray       #: 4x4, world frame
    measured_js: JointState
    setpoint_jp: np.ndarray
    fault: Optional[str] = None
    rejected_commands: int = 0
    ignored_commands: int = 0
    last_error: Optional[str] = None
    extra: dict = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# validation helpers (shared by every model; each message names the offending value)
# --------------------------------------------------------------------------------------------

def _fmt(v) -> str:
    a = np.asarray(v, dtype=float).ravel()
    return "[" + ", ".join(f"{x:.6g}" for x in a) + "]"


def as_vector(v, n: int, what: str) -> np.ndarray:
    """``v`` as a finite float vector of length ``n``, or InputError naming it."""
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{what} = {v!r}; expected {n} numbers") from None
    if a.shape != (n,):
        raise InputError(f"{what} has shape {a.shape}; expected ({n},)")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{what} = {_fmt(a)} is not finite")
    return a


def as_pose(T, what: str = "pose", out: Optional[np.ndarray] = None) -> np.ndarray:
    """``T`` as a finite rigid 4x4 transform (proper rotation), or InputError naming it: a copy,
    or written into ``out`` (4x4 float64, C-contiguous; no allocation: a robot's setpoint check
    in the tick). The check is the compiled core's (``pf_pose_check``); what is wrong is named by
    ``_pose_error`` only when it fails."""
    try:
        a = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{what} = {T!r}; expected a 4x4 transform") from None
    if a.shape != (4, 4):
        raise InputError(f"{what} has shape {a.shape}; expected (4, 4) or a position (3,)")
    if out is None:
        out = np.array(a, order="C")
        address = out.ctypes.data
    else:
        if out is not a:
            np.copyto(out, a)
        address = _address(out)
    if lib.pf_pose_check(address, RIGID_TOL):
        _pose_error(out, what)
    return out


#: id -> (array, data address) of the ``out`` arrays ``as_pose`` wrote into (a robot's setpoint
#: scratch: a handful; ``ndarray.ctypes`` costs microseconds, the tick asks every tick)
_ADDRESSES: dict = {}


def _address(a: np.ndarray) -> int:
    """The data address of 4x4 float64 C-contiguous ``a``, kept per array (the entry holds ``a``,
    so its id is not reused while cached)."""
    got = _ADDRESSES.get(id(a))
    if got is None or got[0] is not a:
        if a.dtype != np.float64 or a.shape != (4, 4) or not a.flags.c_contiguous:
            raise TypeError(f"as_pose: out must be a C-contiguous 4x4 float64 array, got {a.dtype} {a.shape}")
        if len(_ADDRESSES) >= 256:
            _ADDRESSES.clear()
        got = _ADDRESSES[id(a)] = (a, a.ctypes.data)
    return got[1]


def _pose_error(a: np.ndarray, what: str) -> NoReturn:
    """Raise the InputError naming why 4x4 ``a`` is not a finite rigid transform (the checks of
    ``pf_pose_check``, in Python, for the message)."""
    (r00, r01, r02, x), (r10, r11, r12, y), (r20, r21, r22, z), last = a.tolist()
    if not math.isfinite(r00 + r01 + r02 + x + r10 + r11 + r12 + y + r20 + r21 + r22 + z + sum(last)):
        raise InputError(f"{what} is not finite: {a.tolist()}")
    if max(abs(last[0]), abs(last[1]), abs(last[2]), abs(last[3] - 1.0)) > RIGID_TOL:
        raise InputError(f"{what} last row = {_fmt(a[3])}; expected [0, 0, 0, 1]")
    err = max(abs(r00 * r00 + r10 * r10 + r20 * r20 - 1.0), abs(r01 * r01 + r11 * r11 + r21 * r21 - 1.0),
              abs(r02 * r02 + r12 * r12 + r22 * r22 - 1.0), abs(r00 * r01 + r10 * r11 + r20 * r21),
              abs(r00 * r02 + r10 * r12 + r20 * r22), abs(r01 * r02 + r11 * r12 + r21 * r22))
    if err > RIGID_TOL:
        raise InputError(f"{what} rotation is not orthonormal (max |R^T R - I| = {err:.3g}): {a[:3, :3].tolist()}")
    det = (r00 * (r11 * r22 - r12 * r21) - r01 * (r10 * r22 - r12 * r20) + r02 * (r10 * r21 - r11 * r20))
    if det < 0:
        raise InputError(f"{what} rotation has determinant {det:.6g}; expected +1 (a reflection is not a pose)")
    raise InputError(f"{what} is not a rigid transform: {a.tolist()}")


def as_limits(lower, upper, n: int, what: str) -> tuple:
    lo = as_vector(lower, n, f"{what} lower")
    hi = as_vector(upper, n, f"{what} upper")
    bad = np.nonzero(lo >= hi)[0]
    if bad.size:
        i = int(bad[0])
        raise InputError(f"{what}: lower[{i}] = {lo[i]:.6g} is not below upper[{i}] = {hi[i]:.6g}")
    return lo, hi


# --------------------------------------------------------------------------------------------
# the abstract robot
# --------------------------------------------------------------------------------------------

class Robot(ABC):
    """A robot arm behind a CRTK-style interface.

    Subclasses provide the kinematics and the simulation (or the real device) through five hooks:
    :meth:`_fk` (joint positions to a base-frame pose), :meth:`_ik` (base-frame pose to joint
    positions near a seed; raises InputError when out of reach), :meth:`_advance` (simulate
    ``dt`` seconds towards ``self._q_d``), :meth:`_stop` (brakes, for FAULT) and
    :meth:`_reset_controller` (clear integrators after a setpoint re-seat).

    The per-tick state lives in lists of Python floats allocated once and mutated in place:
    ``self._q`` (measured joints), ``self._dq``, ``self._tau`` (applied effort) and ``self._q_d``
    (joint setpoint). For 3-6 joints scalar arithmetic is an order of magnitude cheaper than
    NumPy calls on tiny arrays (2-5 us against 30-40 us per tick); readers get NumPy copies.
    """

    #: model name used by make_robot
    model: str = ""
    #: (lo, hi) the jaw's range (rad) for a model with a jaw (``servo_jaw``, ``measured_jaw``); None: no jaw
    jaw_limits: Optional[tuple] = None

    def __init__(self, joint_names: Sequence[str], lower, upper, *, T_world_base=None,
                 workspace_min=None, workspace_max=None, fault_error=None, control_rate_hz: float = 1000.0):
        n = len(joint_names)
        self.joint_names = tuple(joint_names)
        self.dof = n
        self._lower, self._upper = as_limits(lower, upper, n, "joint limits")
        if T_world_base is None:
            T_world_base = np.eye(4)
        self._T_world_base = as_pose(np.asarray(T_world_base, dtype=float).reshape(4, 4), "T_world_base")
        self._T_base_world = np.linalg.inv(self._T_world_base)
        if (workspace_min is None) != (workspace_max is None):
            raise InputError("workspace: give both workspace_min and workspace_max, or neither")
        self._ws = None if workspace_min is None else as_limits(workspace_min, workspace_max, 3, "workspace")
        #: the workspace as six floats (x, y, z min, x, y, z max): the per-tick check compares scalars
        self._ws_box = None if self._ws is None else tuple(self._ws[0].tolist() + self._ws[1].tolist())
        if not (isinstance(control_rate_hz, (int, float)) and math.isfinite(control_rate_hz) and control_rate_hz > 0):
            raise InputError(f"control_rate_hz = {control_rate_hz!r}; expected a number > 0")
        self.control_period = 1.0 / float(control_rate_hz)
        self._fault_error = None if fault_error is None else as_vector(fault_error, n, "fault_error")
        if self._fault_error is not None and np.any(self._fault_error <= 0):
            raise InputError(f"fault_error = {_fmt(self._fault_error)}; expected positive values")

        self._q = [0.0] * n
        self._dq = [0.0] * n
        self._tau = [0.0] * n
        self._q_d = [0.0] * n
        self._lo = self._lower.tolist()
        self._hi = self._upper.tolist()
        self._fe = None if self._fault_error is None else self._fault_error.tolist()
        self._identity_mount = bool(np.array_equal(self._T_world_base, np.eye(4)))
        self._T_d = np.eye(4)            # commanded pose (world)
        self._T_meas = np.eye(4)         # cached measured pose (world)
        self._T_meas_ok = False
        self._scratch4 = np.eye(4)
        self._T_meas16 = self._T_meas.reshape(16)   # flat views of the poses (adopt_*)
        self._T_d16 = self._T_d.reshape(16)
        self._T_meas_mv, self._T_d_mv = memoryview(self._T_meas16), memoryview(self._T_d16)
        self.t = 0.0
        self._mode = RobotMode.ENABLED
        self._fault: Optional[str] = None
        self.rejected_commands = 0
        self.ignored_commands = 0
        self.last_error: Optional[str] = None
        self.last_command: Optional[Command] = None

    # ---------------------------------------------------------------- hooks for subclasses
    @abstractmethod
    def _fk(self, q, out: np.ndarray) -> np.ndarray:
        """Write the base-frame 4x4 pose of the tool tip at joints ``q`` into ``out``."""

    @abstractmethod
    def _ik(self, T_base: np.ndarray, seed) -> np.ndarray:
        """Joint positions (an array) within the limits reaching base-frame pose ``T_base``, nearest
        ``seed`` (a sequence).

        Raises InputError naming the pose and the violated limit when out of reach."""

    @abstractmethod
    def _advance(self, dt: float) -> None:
        """Simulate ``dt`` seconds (one or more control periods) towards ``self._q_d``."""

    def _stop(self) -> None:
        n = self.dof
        self._dq[:] = [0.0] * n
        self._tau[:] = [0.0] * n

    def _reset_controller(self) -> None:
        """Clear controller memory (integrators) after the setpoint is re-seated."""

    # ---------------------------------------------------------------- read side
    @property
    def state(self) -> RobotMode:
        return self._mode

    @property
    def fault_reason(self) -> Optional[str]:
        return self._fault

    @property
    def joint_limits(self) -> tuple:
        """(lower, upper) joint limits, copies (rad or m)."""
        return self._lower.copy(), self._upper.copy()

    @property
    def workspace(self) -> Optional[tuple]:
        """(min, max) corners of the Cartesian workspace box in the world frame, or None."""
        return None if self._ws is None else (self._ws[0].copy(), self._ws[1].copy())

    @property
    def T_world_base(self) -> np.ndarray:
        return self._T_world_base.copy()

    def measured_cp(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        """4x4 world pose of the tool tip from the measured joints (a copy, or written to ``out``)."""
        if not self._T_meas_ok:
            if self._identity_mount:
                self._fk(self._q, self._T_meas)
            else:
                self._fk(self._q, self._scratch4)
                np.matmul(self._T_world_base, self._scratch4, out=self._T_meas)
            self._T_meas_ok = True
        if out is None:
            return self._T_meas.copy()
        out[...] = self._T_meas
        return out

    def measured_cp_position(self) -> np.ndarray:
        """The tool-tip position (3,) of :meth:`measured_cp`."""
        return self.measured_cp()[:3, 3].copy()

    def measured_jp_into(self, out: np.ndarray) -> None:
        """Write the measured joint positions (rad or m) into ``out[:dof]`` (allocates nothing:
        the self-filter's tool pose ring reads them every tick)."""
        out[: self.dof] = self._q

    def measured_js(self) -> JointState:
        return JointState(self.joint_names, np.array(self._q), np.array(self._dq), np.array(self._tau))

    def setpoint_cp(self, out: Optional[np.ndarray] = None) -> np.ndarray:
        """4x4 world pose the robot is servoing to (the last accepted command)."""
        if out is None:
            return self._T_d.copy()
        out[...] = self._T_d
        return out

    def setpoint_js(self) -> JointState:
        n = self.dof
        return JointState(self.joint_names, np.array(self._q_d), np.zeros(n), np.zeros(n))

    def read_state(self) -> RobotState:
        return RobotState(t=self.t, mode=self._mode, measured_cp=self.measured_cp(),
                          setpoint_cp=self.setpoint_cp(), measured_js=self.measured_js(),
                          setpoint_jp=np.array(self._q_d), fault=self._fault,
                          rejected_commands=self.rejected_commands, ignored_commands=self.ignored_commands,
                          last_error=self.last_error)

    # ---------------------------------------------------------------- forward/inverse kinematics (world frame)
    def forward_kinematics(self, q) -> np.ndarray:
        """4x4 world pose of the tool tip at joint positions ``q`` (no limit check)."""
        q = as_vector(q, self.dof, "q")
        out = np.empty((4, 4))
        self._fk(q.tolist(), out)
        return self._T_world_base @ out

    def inverse_kinematics(self, T, seed=None) -> np.ndarray:
        """Joint positions within the limits that reach world pose ``T`` (4x4), nearest ``seed``
        (default: the current setpoint). Raises InputError when out of reach."""
        T = as_pose(T, "T")
        seed = self._q_d if seed is None else as_vector(seed, self.dof, "seed").tolist()
        return self._ik(self._T_base_world @ T, seed).copy()

    # ---------------------------------------------------------------- commands
    def _reject(self, msg: str) -> NoReturn:
        self.rejected_commands += 1
        self.last_error = msg
        raise InputError(msg)

    def _check_workspace(self, p: np.ndarray, what: str) -> None:
        if self._ws is None:
            return
        lo, hi = self._ws
        x, y, z = float(p[0]), float(p[1]), float(p[2])
        if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]:
            return                        # (scalar compares: the common case costs no array op)
        if np.any(p < lo) or np.any(p > hi):
            axis = int(np.argmax(np.maximum(lo - p, p - hi)))
            self._reject(f"{what}: position {_fmt(p)} m is outside the workspace "
                         f"[{_fmt(lo)}, {_fmt(hi)}] (axis {'xyz'[axis]})")

    def _check_joints(self, q: np.ndarray, what: str) -> None:
        lo, hi = self._lo, self._hi
        for i, v in enumerate(q.tolist()):
            if lo[i] - LIMIT_TOL <= v <= hi[i] + LIMIT_TOL:
                continue
            self._reject(f"{what}: joint {self.joint_names[i]!r} = {q[i]:.6g} is outside its limits "
                         f"[{self._lower[i]:.6g}, {self._upper[i]:.6g}] (q = {_fmt(q)})")

    def checked_setpoint(self, T, out: Optional[np.ndarray] = None) -> np.ndarray:
        """The world pose a ``servo_cp`` argument asks for (what a robot in another process checks
        before it sends a setpoint, robot/hosted.py): ``T`` itself (4x4), or the setpoint
        pose moved to the position ``T`` (3,), written into ``out`` (4x4) when given. Raises
        InputError, counted as a rejected command, on a malformed or non-finite value or a
        position outside the workspace."""
        try:
            a = np.asarray(T, dtype=float)
        except (TypeError, ValueError):
            self._reject(f"servo_cp: {T!r} is not a 4x4 pose or a 3-vector")
        try:
            if a.shape == (3,):
                x, y, z = a.tolist()
                if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
                    as_vector(a, 3, "servo_cp position")      # raises, naming the value
                if out is None:
                    pose = self._T_d.copy()
                else:
                    pose = out
                    np.copyto(pose, self._T_d)
                pose[0, 3], pose[1, 3], pose[2, 3] = x, y, z
            else:
                pose = as_pose(a, "servo_cp pose", out)
                x, y, z = pose[0, 3], pose[1, 3], pose[2, 3]
        except InputError as e:
            self._reject(str(e))
        box = self._ws_box
        if box is not None and not (box[0] <= x <= box[3] and box[1] <= y <= box[4] and box[2] <= z <= box[5]):
            self._check_workspace(pose[:3, 3], "servo_cp")    # (outside: raises, naming the axis)
        return pose

    def servo_cp(self, T) -> bool:
        """Stream a Cartesian setpoint: a 4x4 world pose, or a position (3,) keeping the current
        setpoint orientation. Returns True when applied, False when ignored (HOLDING or FAULT).
        Raises InputError (and changes nothing) on a bad or unreachable pose."""
        pose = self.checked_setpoint(T)
        try:
            q = self._ik(pose if self._identity_mount else self._T_base_world @ pose, self._q_d)
        except InputError as e:
            self._reject(f"servo_cp: {e}")
        self._check_joints(q, "servo_cp")  # belt and braces: _ik only returns in-limit solutions
        if self._mode is not RobotMode.ENABLED:
            self.ignored_commands += 1
            return False
        self._q_d[:] = q.tolist()
        self._T_d[...] = pose
        self.last_command = Command("cp", self.t, pose=pose, position=q)
        return True

    def measured_jaw(self) -> float:
        """The jaw's measured angle (rad; NaN while unknown). Only for a model with ``jaw_limits``."""
        return math.nan

    def servo_jaw(self, angle: float) -> bool:
        """Stream a jaw setpoint (rad, within ``jaw_limits``). A model without a jaw refuses it."""
        self._reject(f"servo_jaw: a {self.model or type(self).__name__} robot has no jaw")

    def servo_jp(self, q) -> bool:
        """Stream a joint-position setpoint. Returns True when applied, False when ignored
        (HOLDING or FAULT). Raises InputError (and changes nothing) on bad values or limits."""
        try:
            qv = as_vector(q, self.dof, "servo_jp q")
        except InputError as e:
            self._reject(str(e))
        self._check_joints(qv, "servo_jp")
        pose = np.empty((4, 4))
        self._fk(qv.tolist(), pose)
        if not self._identity_mount:
            pose = self._T_world_base @ pose
        self._check_workspace(pose[:3, 3], "servo_jp")
        if self._mode is not RobotMode.ENABLED:
            self.ignored_commands += 1
            return False
        self._q_d[:] = qv.tolist()
        self._T_d[...] = pose
        self.last_command = Command("jp", self.t, pose=pose, position=qv)
        return True

    # ---------------------------------------------------------------- operating state
    def hold(self) -> None:
        """Stop where the arm is: the setpoint moves onto the measured joints (a stop, not the
        end of the last command: an arm that lags its setpoint does not go on moving while it is
        held, SAFETY.md S3), and servo commands are ignored until resume(). Safe to call
        repeatedly and in any state (FAULT stays FAULT)."""
        if self._mode is RobotMode.ENABLED:
            self._q_d[:] = self._q
            self._fk(self._q_d, self._scratch4)
            np.matmul(self._T_world_base, self._scratch4, out=self._T_d)
            self._mode = RobotMode.HOLDING

    def resume(self) -> None:
        """Leave HOLDING (the setpoint is unchanged, so nothing moves). No effect in FAULT."""
        if self._mode is RobotMode.HOLDING:
            self._mode = RobotMode.ENABLED

    def enable(self) -> None:
        """Clear a FAULT (or leave HOLDING): the setpoint is re-seated on the measured joints when
        leaving FAULT, so enabling never moves the robot."""
        if self._mode is RobotMode.FAULT:
            self._q_d[:] = self._q
            self._fk(self._q_d, self._scratch4)
            np.matmul(self._T_world_base, self._scratch4, out=self._T_d)
            self._T_meas_ok = False
            self._reset_controller()
            self._fault = None
        self._mode = RobotMode.ENABLED

    def fault(self, reason: str) -> None:
        """Enter FAULT (e.g. an e-stop from the service): the joints stop where they are."""
        self._mode = RobotMode.FAULT
        self._fault = str(reason)
        self._stop()

    # ---------------------------------------------------------------- a controller running elsewhere
    def copy_state(self, q, dq, tau, q_d, T_meas, T_d) -> None:
        """Write the state into the given arrays (what a robot process publishes): joints ``q``,
        ``dq``, ``tau``, setpoint ``q_d`` (``dof`` values each); measured and setpoint poses
        ``T_meas``, ``T_d`` (16 values each: 4x4 world, row-major)."""
        q[:] = self._q
        dq[:] = self._dq
        tau[:] = self._tau
        q_d[:] = self._q_d
        T_meas[:] = self.measured_cp().ravel()
        T_d[:] = self._T_d.ravel()

    def adopt_state(self, t: float, q, dq, tau, T_meas, mode: Optional[RobotMode] = None) -> None:
        """Take the measured state of this model's controller running in another process (the
        service's copy of a hosted arm, robot/hosted.py): time ``t`` (s), joints ``q``, ``dq``,
        ``tau`` (``dof`` values each), measured pose ``T_meas`` (16 values, world, row-major) and,
        where given, the operating ``mode``. Nothing is checked: the caller checked it. (A memoryview
        of 16 floats is the cheapest ``T_meas``: a plain copy.)"""
        self.t = t
        if mode is not None:
            self._mode = mode
        self._q[:] = q
        self._dq[:] = dq
        self._tau[:] = tau
        if type(T_meas) is memoryview:
            self._T_meas_mv[:] = T_meas
        else:
            np.copyto(self._T_meas16, T_meas)
        self._T_meas_ok = True

    def adopt_setpoint(self, T_d, q_d=None) -> None:
        """Take the setpoint (pose ``T_d``: 16 values or 4x4, world; joints ``q_d`` where given) of
        this model's controller running in another process (a memoryview of 16 floats: a plain copy)."""
        if type(T_d) is memoryview:
            self._T_d_mv[:] = T_d
        else:
            np.copyto(self._T_d16, T_d.reshape(16) if type(T_d) is np.ndarray else np.reshape(T_d, 16))
        if q_d is not None:
            self._q_d[:] = q_d

    def adopt_texts(self, fault: Optional[str], last_error: Optional[str]) -> None:
        """Take the fault reason and last error of this model's controller in another process."""
        self._fault = fault
        self.last_error = last_error

    # ---------------------------------------------------------------- simulation
    def reset(self, q=None) -> None:
        """Place the robot at joints ``q`` (default: its home), at rest, setpoint on it, ENABLED.
        For simulation set-up only: a real robot cannot teleport."""
        qv = self.home if q is None else as_vector(q, self.dof, "reset q")
        self._check_joints(qv, "reset")
        self._q[:] = qv.tolist()
        self._q_d[:] = qv.tolist()
        self._stop()
        self._fk(self._q, self._scratch4)
        np.matmul(self._T_world_base, self._scratch4, out=self._T_d)
        self._T_meas_ok = False
        self._reset_controller()
        self._mode = RobotMode.ENABLED
        self._fault = None

    @property
    def home(self) -> np.ndarray:
        return np.clip(0.5 * (self._lower + self._upper), self._lower, self._upper)

    def step(self, dt: float = 1e-3) -> None:
        """Advance the simulation by ``dt`` seconds (the controller runs at ``control_rate_hz``;
        a longer dt runs several control periods). Allocation-free for dt = one period."""
        if not (dt > 0.0) or dt == math.inf:
            raise InputError(f"step: dt = {dt!r}; expected a finite number > 0")
        if self._mode is RobotMode.FAULT:
            self.t += dt
            return
        self._advance(dt)
        self.t += dt
        self._T_meas_ok = False
        q = self._q
        if not (math.isfinite(sum(q)) and math.isfinite(sum(self._dq))):
            self.fault("simulation state is not finite")
            return
        fe = self._fe
        if fe is not None:
            qd = self._q_d
            for i in range(self.dof):
                if abs(qd[i] - q[i]) > fe[i]:
                    self.fault(f"following error on joint {self.joint_names[i]!r}: "
                               f"|{qd[i]:.6g} - {q[i]:.6g}| > {fe[i]:.6g}")
                    return
