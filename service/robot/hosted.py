"""Simulated robots in their own process, stepped on their own 1 kHz clock, as real arms are.

A real arm's controller (the Raven II's RTAI loop, a Franka control box) steps its joints at
its own rate while the haptic service streams setpoints and reads the measured state.
``RobotHost`` does the same for the simulated models of live runs: a child process builds the
arms from the ``[robot]`` table and steps them on absolute 1 kHz deadlines; shared memory
carries the service's commands one way and the measured state the other. In the service each
arm is a ``HostedRobot``: the robot interface the service and the self-filter use, spelt out
(nothing is forwarded implicitly), over a local instance of the same model (kinematics, limits,
workspace, tool geometry) whose state the arm's ``step`` takes from the child, and whose commands
go to the child. A haptic tick then spends about 15 us per arm instead of the
simulation's 70 us (closed-form IK, joint PID, forward kinematics, all in Python), and the
simulation runs on another core, without the interpreter lock of the service's process.

Differences from an in-process robot (offline runs and replays keep that one, which steps in
the tick and is deterministic):

* the state read in a tick is the child's latest, at most one control period old;
* a setpoint the child rejects (out of reach) is reported by a later ``servo_cp`` (a tick or
  two on), which raises InputError with the child's message and sends nothing;
  ``setpoint_cp`` is then the setpoint the child kept (the service falls back to it, as with
  an in-process rejection);
  malformed or non-finite setpoints and workspace violations are refused at once, before they
  reach the child;
* a watchdog runs at every read of the child's record (each tick), whatever the record holds:
  a child that stops stepping, or whose record does not read, for ``timeout_s`` (default 50 ms, at most
  0.25 s: it died, hangs or starves) puts every arm in FAULT ("robot process not answering:
  ..."); an arm whose published state holds a NaN or an infinity is in FAULT ("robot state
  non-finite: q, T_meas (arm 0)") and its state is not taken. Either FAULT is latched in the
  service (the arm sends nothing, ``servo_cp`` returns False, the child is told to brake) and
  ``enable()`` clears it only while the child steps and the arm's state is finite; so the
  service holds (its tick holds an arm whose robot is in FAULT) and says why (``fault_reason``);
* faults can be injected on purpose (tests, ``pointfence bench soak``): ``RobotHost.inject(kind,
  arm)`` with ``"nan"`` (NaN state), ``"stall"`` (SIGSTOP), ``"kill"`` (SIGKILL) or ``"none"``
  (NaN off, SIGCONT); ``RobotHost.restart()`` starts a new process after a death, at the
  arms' last joints; ``close`` ends the child.

Each arm's ``step(dt)`` is its own and right in any call order: it sends every setpoint queued so
far (this arm's among them) and takes this arm's state from the newest read of the child's
record; the record is read again (with the watchdog) whenever an arm steps that has already
taken the last read, so a tick that steps every arm once, in any order, reads it once, and an arm
stepped alone still reads it every time.

The child ticks on a ``periodic.PeriodicLoop`` (absolute 1 kHz deadlines; periods lost are
skipped and the next step covers them: ``dt`` = elapsed periods; its heartbeat counts periods).
State and commands cross through one shared-memory block (robot/hosted_block.py: the layout,
declared once as NumPy dtypes from which both sides take every region and field), each direction
a double-buffered channel (sequence counters and a CRC-32 of the bytes per slot): neither side
ever waits for the other, so the haptic tick never waits for a preempted robot process, nor the
robot for the service. The child is robot/hosted_child.py, started as ``python -m
pointfence.service.robot.hosted_child`` (nothing of the parent's program is imported again); it
ends when its parent does.
"""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from multiprocessing import shared_memory
from typing import Optional, Sequence

import numpy as np

from pointfence.kernels.errors import InputError

from .base import JointState, RobotMode, RobotState
from .factory import robot_from_config
from .hosted_block import ENABLE, FAULT, HOLD, INJECT_NAN, INJECT_NONE, RESUME, RING, TICKS, Block, Commands, get_text

LOST = "robot process not answering"
NONFINITE = "robot state non-finite"
_MODES = tuple(RobotMode)
#: the watchdog: default and ceiling (s) of how long the child may go without stepping. 50 ms:
#: the simulated arms' process shares the machine with the service, and on a loaded 2-core
#: machine a normal process is descheduled for 20 ms now and then (a real arm's controller on
#: its own real-time host can be held to less: ``[service] robot_watchdog_s``)
WATCHDOG_S, WATCHDOG_MAX_S = 0.05, 0.25
#: fault kinds of ``RobotHost.inject``
FAULT_KINDS = ("nan", "stall", "kill", "none")


def _plain(o):
    """JSON for the NumPy values a programmatic ``[robot]`` table may hold."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"[robot] value {o!r} ({type(o).__name__}) cannot be sent to the robot process")


class RobotHost:
    """Robots built from ``tables`` (one ``[robot]`` table per arm) in a child process.

    ``robots``: one ``HostedRobot`` per arm, for the service. ``rt_priority``: SCHED_FIFO
    priority of the child where allowed (0: normal). ``timeout_s``: the watchdog, how long the
    child may go without stepping (or its state record without reading) before every arm reads
    as FAULT (default ``WATCHDOG_S``, at most ``WATCHDOG_MAX_S``). ``start_timeout_s``: how long to
    wait for the child to build the arms. Call ``close()`` when done (the child also ends with
    its parent).

    Faults, for tests and fault-injection benchmarks: ``inject(kind, arm)``; after a ``kill``,
    ``restart()`` starts a new robot process at the arms' last joints (they stay in FAULT until
    ``enable()``).

    The arms' side (``HostedRobot`` calls these): ``step_arm(b)``, ``stage_pose(b, pose)``,
    ``send_mode(b, code)``, ``ready(b)``.
    """

    def __init__(self, tables: Sequence[dict], rate_hz: float = 1000.0, rt_priority: int = 0,
                 timeout_s: float = WATCHDOG_S, start_timeout_s: float = 30.0):
        tables = [dict(t) for t in tables]
        if not tables:
            raise InputError("RobotHost: no robot tables; expected one [robot] table per arm")
        if not (isinstance(timeout_s, (int, float)) and 0 < timeout_s <= WATCHDOG_MAX_S):
            raise InputError(f"RobotHost: timeout_s = {timeout_s!r}; expected a watchdog time > 0 and "
                             f"<= {WATCHDOG_MAX_S} s (a robot process silent for longer must read as FAULT)")
        # validates every table here, first; an arm behind a connection (crtk) connects in the child only
        local = [robot_from_config(t, connect=False) for t in tables]
        dof = max(r.dof for r in local)
        if any(r.dof != dof for r in local):
            raise InputError("RobotHost: every hosted arm must have the same number of joints")
        self._tables, self._rate, self._prio, self._start_timeout = tables, float(rate_hz), int(rt_priority), start_timeout_s
        self.n, self.dof = len(tables), dof
        self.timeout_s = float(timeout_s)
        self._proc = None
        self._shm = shared_memory.SharedMemory(create=True, size=Block.nbytes(self.n, dof))
        self._blk = Block(self._shm.buf, self.n, dof)   # a new shared memory object reads as zeros
        self._L = self._blk.layout
        L, n = self._L, self.n
        self._buf = np.zeros((n, self._blk.S))           # the last state record read
        self._buf_mv = memoryview(self._buf.reshape(-1))  # (made once: Channel.read copies into it)
        self._row_arrays = [self._buf[b] for b in range(n)]
        # each arm's poses in it, as memoryviews (16 floats: the arm copies them)
        self._T_meas = [memoryview(self._buf[b, L.T_meas]) for b in range(n)]
        self._T_d = [memoryview(self._buf[b, L.T_d]) for b in range(n)]
        self._rows: list = [None] * n                    # each arm's row of the last read, as floats
        self._finite = [True] * n
        self._got = False                                # whether the last read succeeded
        self._reads = 0                                  # reads of the record so far
        self._took = [0] * n                             # the read arm b took last (== _reads: the last)
        self._cmds = Commands(n)                         # the commands written so far (this side's copy)
        self._cmds_mv = memoryview(self._cmds.rec)
        self._pose_rows = [memoryview(self._cmds.pose[b]) for b in range(n)]   # (16 floats each)
        self._servo_seq_at = [b * self._blk.C + self._blk.command_layout.servo_seq for b in range(n)]
        self._spawn(None)
        self.robots = [HostedRobot(self, b, r) for b, r in enumerate(local)]
        self.sync()

    def _spawn(self, start_q: Optional[list]) -> None:
        """Start the child on a zeroed block and wait until it has built the arms."""
        self._blk.raw[:] = 0                       # no command of a previous child
        self._cmds.rec[:] = 0
        self._servo_sent = [0] * self.n            # setpoints and mode commands sent (the record's counts)
        self._modes_sent = [0] * self.n
        self._staged = False
        self._versions = [(0.0, 0.0)] * self.n
        # a fresh interpreter (no fork of a process that runs OpenCL and CUDA threads, and none of
        # the parent's main module imported again, as multiprocessing's spawn would)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "pointfence.service.robot.hosted_child", self._shm.name,
             json.dumps(self._tables, default=_plain), str(self.dof), repr(self._rate), str(self._prio),
             str(os.getpid()), json.dumps(start_q)], stdin=subprocess.DEVNULL)
        end = time.monotonic() + self._start_timeout
        while int(self._blk.ctl["ready"]) == 0:
            if self._proc.poll() is not None or time.monotonic() > end:
                code = self._proc.poll()
                self.close()
                raise RuntimeError(f"the robot process did not start (exit code {code}); run the robots "
                                   "in the haptic loop instead with [service] robot_process = false")
            time.sleep(0.005)
        self._ticks, self._ticks_at = -1, time.monotonic()
        self._read_at = self._ticks_at
        self._alive = True

    # --- service side ---------------------------------------------------------------------------
    def sync(self) -> None:
        """Read the child's latest state (after the watchdog) and give every arm its row."""
        self._read()
        for b in range(self.n):
            self._give(b)

    def step_arm(self, b: int) -> None:
        """Arm ``b``'s step: send every queued setpoint, read the child's record again if this arm
        has taken the last read (else the read of this tick, by an arm stepped before it), and
        give the arm its row. Right in any order of the arms' steps (module docstring)."""
        if self._staged:
            self.publish()
        if self._took[b] == self._reads:
            self._read()
        self._give(b)

    def _read(self) -> None:
        """Read the state record, after the watchdog: a child that has not stepped, or whose state
        record has not read, for ``timeout_s`` faults every arm; an arm whose state is not finite
        faults. Every arm may take this read once (``_give``)."""
        blk = self._blk
        self._reads += 1
        if blk is None:                    # closed: the arms keep their last state
            self._got = False
            return
        now = time.monotonic()
        ticks = blk.ctl_words[TICKS]
        if ticks != self._ticks:
            self._ticks, self._ticks_at = ticks, now
        got = self._got = blk.state.read(self._buf_mv)
        if got:
            self._read_at = now
        silent, unread = now - self._ticks_at, now - self._read_at
        self._alive = silent <= self.timeout_s and unread <= self.timeout_s
        if not self._alive and not all(r.latched for r in self.robots):
            self._lost(silent, unread)
        if not got:                        # lapped (this thread was preempted): the next read
            return
        L, rows, finite, versions = self._L, self._rows, self._finite, self._versions
        fault_ver, error_ver = L.fault_ver, L.error_ver
        for b, arr in enumerate(self._row_arrays):
            row = rows[b] = arr.tolist()
            # (a NaN or an infinity anywhere makes the sum non-finite)
            ok = finite[b] = math.isfinite(sum(row))
            if not ok:
                if not self.robots[b].latched:
                    self.robots[b].latch_fault(f"{NONFINITE}: {', '.join(L.nonfinite_fields(arr))} (arm {b})")
                continue
            v = (row[fault_ver], row[error_ver])
            if v != versions[b]:           # a fault reason or an error message changed
                versions[b] = v
                self.robots[b].take_texts(get_text(blk.text[b, 0]), get_text(blk.text[b, 1]))

    def _give(self, b: int) -> None:
        """Arm ``b`` takes its row of the last read (where it read, the child answers and the row
        is finite)."""
        self._took[b] = self._reads
        if self._got and self._alive and self._finite[b]:
            self.robots[b].take_state(self._rows[b], self._T_meas[b], self._T_d[b], self._servo_sent[b],
                                      self._modes_sent[b])

    def _lost(self, silent: float, unread: float) -> None:
        """Every arm FAULT: the child has not stepped for ``silent`` s, or its state record has not
        read for ``unread`` s."""
        if silent > self.timeout_s:
            ended = self._proc is None or self._proc.poll() is not None
            why = f"no step for {1e3 * silent:.0f} ms (process {'ended' if ended else 'alive'})"
        else:
            why = f"state record unreadable for {1e3 * unread:.0f} ms"
        for r in self.robots:
            r.latch_fault(f"{LOST}: {why}")

    def ready(self, b: int) -> Optional[str]:
        """Why arm ``b`` cannot be enabled now (None: it can): the robot process must be running
        and stepping, and the arm's latest state finite."""
        if self._blk is None or self._proc is None or self._proc.poll() is not None:
            return f"{LOST}: the robot process has ended (restart() starts a new one)"
        if not self._alive:
            return f"{LOST}: no step for {1e3 * (time.monotonic() - self._ticks_at):.0f} ms"
        if not self._finite[b]:
            return f"{NONFINITE}: {', '.join(self._L.nonfinite_fields(self._buf[b]))} (arm {b})"
        return None

    def sent(self, b: int) -> tuple:
        """(setpoints, mode commands) sent to arm ``b`` so far."""
        return self._servo_sent[b], self._modes_sent[b]

    @property
    def pid(self) -> Optional[int]:
        """The robot process's id (None: none runs)."""
        return self._proc.pid if self._proc is not None else None

    def inject(self, kind: str, arm: Optional[int] = None) -> None:
        """Inject a robot fault (tests, ``pointfence bench soak``): ``"nan"``: the child publishes
        NaN joints and pose for ``arm`` (None: every arm) from its next period on; ``"stall"``:
        the child is stopped (SIGSTOP), as a starved or hung controller; ``"kill"``: the child is
        killed (SIGKILL), as a crashed one (``restart()`` starts a new one); ``"none"``: the NaN
        injection ends and a stalled child continues (SIGCONT). The arms read FAULT within the
        watchdog time (``timeout_s``) and stay so until ``enable()``."""
        if kind not in FAULT_KINDS:
            raise InputError(f"inject: kind {kind!r}; expected one of {', '.join(FAULT_KINDS)}")
        arms = range(self.n) if arm is None else [int(arm)]
        if any(not 0 <= b < self.n for b in arms):
            raise InputError(f"inject: arm {arm!r}; expected 0..{self.n - 1} or None (every arm)")
        if self._blk is None or self._proc is None:
            raise InputError("inject: the robot host is closed")
        if kind in ("nan", "none"):
            for b in arms:
                self._blk.inject[b] = INJECT_NAN if kind == "nan" else INJECT_NONE
        if self._proc.poll() is None:
            sig = {"stall": signal.SIGSTOP, "kill": signal.SIGKILL, "none": signal.SIGCONT}.get(kind)
            if sig is not None:
                os.kill(self._proc.pid, sig)
        if kind == "kill":
            self._proc.wait(timeout=5.0)

    def restart(self) -> None:
        """Start a new robot process after the last one ended (a ``kill``, a crash), its arms at
        the joints last read from the old one; every arm stays in FAULT until ``enable()``. A
        running process is ended first."""
        if self._blk is None:
            raise InputError("restart: the robot host is closed")
        if self._proc is not None:
            if self._proc.poll() is None:
                os.kill(self._proc.pid, signal.SIGCONT)
                self._blk.ctl["stop"] = 1
                try:
                    self._proc.wait(timeout=2.0)
                except subprocess.TimeoutExpired:
                    self._proc.kill()
                    self._proc.wait(timeout=2.0)
        start_q = [r.measured_js().position.tolist() for r in self.robots]
        for r in self.robots:
            r.latch_fault(f"{LOST}: the robot process was restarted")
        self._spawn(start_q)
        for b in range(self.n):
            self.send_mode(b, FAULT)       # the new process starts braked, as the arms read here

    def stage_pose(self, b: int, pose) -> None:
        """Queue arm b's setpoint (4x4 world: an array, or a memoryview of its 16 floats, row-major);
        ``publish`` sends every queued one at once."""
        self._pose_rows[b][:] = pose if type(pose) is memoryview else memoryview(np.ascontiguousarray(pose).reshape(16))
        k = self._servo_sent[b] = self._servo_sent[b] + 1
        self._cmds_mv[self._servo_seq_at[b]] = float(k)
        self._staged = True

    def publish(self) -> None:
        """Send the queued setpoints (one sequence-locked write for all arms)."""
        blk = self._blk
        if not self._staged or blk is None:
            return
        blk.cmd.write(self._cmds_mv)
        self._staged = False

    def send_mode(self, b: int, code: int) -> None:
        """Send a mode command (``HOLD``, ``RESUME``, ``ENABLE``, ``FAULT``) now (with any queued
        setpoints: they come first)."""
        blk = self._blk
        if blk is None:
            return
        c = self._cmds
        i = self._modes_sent[b]
        c.ring[b, i % RING] = code
        c.mode_seq[b] = self._modes_sent[b] = i + 1
        blk.cmd.write(self._cmds_mv)
        self._staged = False

    @property
    def alive(self) -> bool:
        """The robot process runs and stepped within the watchdog time (as of the last read)."""
        return self._alive and self._proc is not None and self._proc.poll() is None

    def close(self) -> None:
        """Stop the child (it finishes its period) and free the shared memory. Idempotent."""
        proc = getattr(self, "_proc", None)
        if proc is not None:
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGCONT)    # (a stalled child cannot see the stop request)
            if self._blk is not None:
                self._blk.ctl["stop"] = 1
            try:
                proc.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=2.0)
            self._proc = None
        shm = getattr(self, "_shm", None)
        if shm is not None:
            self._blk = None
            try:
                shm.close()
                shm.unlink()
            except (FileNotFoundError, BufferError):
                pass
            self._shm = None
        self._alive = False

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


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

    def __init__(self, host: RobotHost, index: int, local):
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
            pose = r.checked_setpoint(T, out=self._pose)    # checks it, as the arm in the tick does
        except InputError as e:
            self._local_rejected += 1
            self._last_error = str(e)
            raise
        if self._latched is not None or r.state is not RobotMode.ENABLED:
            self._local_ignored += 1
            return False
        if pose is not self._pose:         # (a 4x4 pose was given: checked into a new array)
            np.copyto(self._pose, pose)
        self._host.stage_pose(self._b, self._pose16)
        r.adopt_setpoint(self._pose16)
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
