"""Simulated robots in their own process, stepped on their own 1 kHz clock, as real arms are.

A real arm's controller (the Raven II's RTAI loop, a Franka control box) steps its joints at
its own rate while the haptic service streams setpoints and reads the measured state.
``RobotHost`` does the same for the simulated models of live runs: a child process builds the
arms from the ``[robot]`` table and steps them on absolute 1 kHz deadlines; shared memory
carries the service's commands one way and the measured state the other. In the service each
arm is a ``HostedRobot``: the robot interface the service and the self-filter use, spelt out
(nothing is forwarded implicitly), over a local instance of the same model (kinematics, limits,
workspace, tool geometry) whose state the arm's ``step`` takes from the child, and whose commands
go to the child. The simulation (closed-form IK, joint PID, forward kinematics, in Python)
then runs on another core, without the interpreter lock of the service's process, and a haptic
tick only exchanges records with it: per arm one compiled call checks and queues the setpoint
(``pf_host_servo``) and one sends it and takes the newest state (``pf_host_step``, both in
native/shm_exchange.c); Python acts only on what they report.

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

import ctypes
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
from pointfence.native import HOST_LOST, HOST_NONFINITE, HOST_REFUSED, HOST_TEXTS, HostCore, HostLayout, fast, ptr

from ..child_pipe import stop_by_flag
from .base import RIGID_TOL, RobotMode
from .factory import robot_from_config
from .hosted_arm import HostedRobot
from .hosted_block import FAULT, INJECT_NAN, INJECT_NONE, RING, Block, Commands, get_text

#: the flags of a read of the state record (``_after_read``)
_READ_FLAGS = HOST_LOST | HOST_NONFINITE | HOST_TEXTS
LOST = "robot process not answering"
NONFINITE = "robot state non-finite"
__all__ = ["FAULT_KINDS", "HostedRobot", "LOST", "NONFINITE", "RobotHost", "WATCHDOG_MAX_S", "WATCHDOG_S"]
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
        self._L = L = self._blk.layout
        n, S = self.n, self._blk.S
        # the compiled exchange's arrays (native/shm_exchange.c, ``pf_host``), allocated once
        self._buf = np.zeros((n, S))                     # the state record last read
        self._taken = np.zeros((n, S))                   # each arm's row as it last took one
        self._cmds = Commands(n)                         # the commands written so far (this side's copy)
        self._T_d = np.zeros((n, 16))                    # each arm's setpoint (world, row-major)
        self._q_d = np.zeros((n, dof))
        self._mode = np.zeros(n)                         # each arm's RobotMode
        self._versions = np.zeros((n, 2))                # fault and error text versions last seen
        self._rejected_seen = np.zeros(n)                # the child's rejections servo_cp reported
        self._ws = np.zeros((n, 6))                      # each arm's workspace box (min xyz, max xyz)
        self._has_ws = np.array([r.workspace is not None for r in local], bool)
        for b, r in enumerate(local):
            if r.workspace is not None:
                self._ws[b] = np.concatenate(r.workspace)
        self._took = np.zeros(n, np.int64)               # the read each arm took last
        self._latched = np.zeros(n, bool)                # the arm is latched in FAULT (HostedRobot sets it)
        self._finite = np.zeros(n, bool)                 # the arm's row of the last read was finite
        self._fresh = np.zeros(n, bool)                  # the arm took a row its model has not adopted
        C = self._blk.command_layout
        start = lambda f: f if isinstance(f, int) else f.start       # noqa: E731
        layout = HostLayout(*[start(getattr(L, f)) for f in ("t", "mode", "rejected", "ignored", "servo_seq",
                                                             "mode_seq", "fault_ver", "error_ver", "q", "dq", "tau",
                                                             "q_d", "T_meas", "T_d", "jaw", "jaw_known")],
                            dof, C.servo_seq, C.mode_seq, C.pose.start, C.jaw_seq, C.jaw)
        self.core = HostCore(n=n, S=S, C=C.size, state=self._blk.state.core, cmd=self._blk.cmd.core,
                             ticks=ptr(self._blk.heartbeat, np.int64, "heartbeat"),
                             buf=ptr(self._buf, np.float64, "buf"), taken=ptr(self._taken, np.float64, "taken"),
                             cmds=ptr(self._cmds.rec, np.float64, "commands"), T_d=ptr(self._T_d, np.float64, "T_d"),
                             q_d=ptr(self._q_d, np.float64, "q_d"), mode=ptr(self._mode, np.float64, "mode"),
                             versions=ptr(self._versions, np.float64, "versions"),
                             rejected_seen=ptr(self._rejected_seen, np.float64, "rejected_seen"),
                             ws=ptr(self._ws, np.float64, "workspace"), took=ptr(self._took, np.int64, "took"),
                             has_ws=ptr(self._has_ws, bool, "has_ws"), latched=ptr(self._latched, bool, "latched"),
                             finite=ptr(self._finite, bool, "finite"), fresh=ptr(self._fresh, bool, "fresh"),
                             L=layout, timeout_s=self.timeout_s, rigid_tol=RIGID_TOL,
                             enabled_mode=float(RobotMode.ENABLED))
        self._core = ctypes.byref(self.core)
        self._cmds_mv = memoryview(self._cmds.rec)
        self._servo_seq_at = [b * C.size + C.servo_seq for b in range(n)]
        self._jaw_at = [(b * C.size + C.jaw_seq, b * C.size + C.jaw) for b in range(n)]
        self._addresses: dict = {}                       # id -> (pose, its data address): ``_pose_address``
        self._arm64 = [ctypes.c_int64(b) for b in range(n)]   # (the core's arm arguments, made once)
        self._fault_mode = ctypes.c_double(float(RobotMode.FAULT))
        for b, r in enumerate(local):                    # until the first read: the local model's state
            self._taken[b, L.T_meas] = r.measured_cp().reshape(16)
            self._taken[b, L.q] = r.measured_js().position
            self.set_local(b, int(r.state), r.setpoint_cp(), r.setpoint_js().position)
        self._spawn(None)
        self.robots = [HostedRobot(self, b, r) for b, r in enumerate(local)]
        self.sync()

    def _spawn(self, start_q: Optional[list]) -> None:
        """Start the child on a zeroed block and wait until it has built the arms."""
        self._blk.raw[:] = 0                       # no command of a previous child
        self._blk.inject_t[:] = math.nan           # (and no injection that took effect)
        self._cmds.rec[:] = 0                      # (setpoints, mode commands, jaw setpoints sent: 0)
        self._versions[:] = 0.0
        self._rejected_seen[:] = 0.0               # (the new child counts its rejections from 0)
        self._taken[:, self._L.rejected] = 0.0
        self.core.staged = 0
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
        c = self.core
        c.ticks_last, c.ticks_at = -1, time.monotonic()
        c.read_at, c.alive = c.ticks_at, 1

    # --- service side ---------------------------------------------------------------------------
    def sync(self) -> None:
        """Read the child's latest state (after the watchdog) and give every arm its row."""
        if self._blk is not None:
            self._after_read(fast.pf_host_sync(self._core, ctypes.c_double(time.monotonic())))

    def step_arm(self, b: int) -> None:
        """Arm ``b``'s step: send every queued setpoint, read the child's record again if this arm
        has taken the last read (else the read of this tick, by an arm stepped before it), and
        give the arm its row (where the child answers, the row is finite and the arm is not
        latched). Right in any order of the arms' steps (module docstring). The compiled
        exchange does it all (``pf_host_step``); Python acts only on what its flags report."""
        if self._blk is None:              # closed: the arms keep their last state
            return
        flags = fast.pf_host_step(self._core, self._arm64[b], ctypes.c_double(time.monotonic()))
        if flags:
            self._after_read(flags)

    def _after_read(self, flags: int) -> None:
        """What a read of the state record reported: a child that has not stepped, or whose state
        record has not read, for ``timeout_s`` faults every arm; an arm whose state is not
        finite faults; a changed fault reason or error message goes to its arm."""
        c = self.core
        if flags & HOST_LOST and not all(r.latched for r in self.robots):
            self._lost(c.silent, c.unread)
        if flags & HOST_NONFINITE:
            for b in range(self.n):
                if c.nonfinite >> b & 1 and not self.robots[b].latched:
                    self.robots[b].latch_fault(f"{NONFINITE}: {', '.join(self._L.nonfinite_fields(self._buf[b]))} "
                                               f"(arm {b})")
        if flags & HOST_TEXTS:
            text = self._blk.text
            for b in range(self.n):
                if c.texts >> b & 1:
                    self.robots[b].take_texts(get_text(text[b, 0]), get_text(text[b, 1]))

    # --- each arm's exchange (HostedRobot's calls) -------------------------------------------------
    @property
    def layout(self):
        """The state row's layout (``hosted_block.RowLayout``: each field's index or slice)."""
        return self._L

    def taken_row(self, b: int) -> np.ndarray:
        """Arm ``b``'s state row as it last took one (a view, S floats: ``layout`` gives the
        fields), updated in place by every ``step_arm`` that gives the arm a row."""
        return self._taken[b]

    def take_fresh(self, b: int) -> bool:
        """Whether arm ``b`` took a row since the last call (its model adopts it then)."""
        if self._fresh[b]:
            self._fresh[b] = False
            return True
        return False

    def setpoint_of(self, b: int) -> tuple:
        """Arm ``b``'s setpoint as the exchange holds it: (pose (16,) world row-major, joints
        (dof,)), views; and its mode (``RobotMode``)."""
        return self._T_d[b], self._q_d[b], RobotMode(int(self._mode[b]))

    def mode_of_all(self) -> np.ndarray:
        """Every arm's mode as the exchange holds it ((n,) floats, ``RobotMode`` values; a view)."""
        return self._mode

    def set_local(self, b: int, mode: int, T_d, q_d) -> None:
        """Arm ``b``'s mode and setpoint as its model has them after a command of this side
        (hold, resume, enable, fault): pose ``T_d`` (4x4 or 16, world), joints ``q_d``."""
        self._mode[b] = float(mode)
        self._T_d[b] = np.reshape(T_d, 16)
        self._q_d[b] = q_d

    def set_latched(self, b: int, latched: bool) -> None:
        """Whether arm ``b`` is latched in FAULT (then it takes no row)."""
        self._latched[b] = latched

    def command(self, T4, coupled, codes) -> bool:
        """Every arm's tick at once (``Devices.command_robots`` when every robot is an arm of this
        host, arm b on row b): each coupled arm's setpoint checked and queued, then every arm
        stepped, in one compiled call (``pf_host_command``). Pointers (``native.ptr``): ``T4``
        (n, 4, 4) the setpoints (world), ``coupled`` (n) bool, ``codes`` (n) int32 out: each
        arm's ``SERVO_*`` code (-1: not coupled); the arm's ``after_servo`` acts on one that is
        not ``SERVO_QUEUED``. Returns whether an arm's code says so (> 0)."""
        if self._blk is None:              # closed: nothing is sent, the arms keep their last state
            return False
        flags = fast.pf_host_command(self._core, T4, coupled, codes, ctypes.c_double(time.monotonic()))
        if flags & _READ_FLAGS:
            self._after_read(flags & _READ_FLAGS)
        return bool(flags & HOST_REFUSED)

    def read_poses(self, T4, pos, quat, fault, present, jaw, jawed, ideal_jaw) -> None:
        """Every arm's measured pose, tip, orientation, fault, presence and jaw from the rows they
        took, in one compiled call (``pf_host_read_poses``; ``Devices.read_robots`` when every
        robot is an arm of this host, arm b on row b). All pointers (``native.ptr``): T4 (n, 4,
        4), pos (n, 3), quat (n, 4), fault and present (n) bool, jaw (n); ``jawed`` (n) bool:
        the arms with a jaw; ``ideal_jaw`` (n): the jaw of the others (their command)."""
        fast.pf_host_read_poses(self._core, self._fault_mode, T4, pos, quat, fault, present, jaw, jawed, ideal_jaw)

    def _pose_address(self, T) -> Optional[ctypes.c_void_p]:
        """The data address of ``T`` if it is a C-contiguous 4x4 float64 array (else None: the
        caller takes the checked Python path), kept per array."""
        got = self._addresses.get(id(T))
        if got is None or got[0] is not T:
            if type(T) is not np.ndarray or T.shape != (4, 4) or T.dtype != np.float64 or not T.flags.c_contiguous:
                return None
            if len(self._addresses) >= 64:
                self._addresses.clear()
            got = self._addresses[id(T)] = (T, ctypes.c_void_p(T.ctypes.data))
        return got[1]

    def servo(self, b: int, T) -> int:
        """Arm ``b``'s setpoint through the compiled check (``pf_host_servo``): a ``SERVO_*``
        code of ``pointfence.native`` (-1: ``T`` is not a 4x4 array the core reads, or the host
        is closed; the caller checks it in Python)."""
        addr = self._pose_address(T)
        if addr is None or self._blk is None:
            return -1
        return fast.pf_host_servo(self._core, self._arm64[b], addr)

    def child_rejections(self, b: int) -> tuple:
        """(rejections arm ``b``'s child counted, of which ``servo_cp`` reported)."""
        return int(self._taken[b, self._L.rejected]), int(self._rejected_seen[b])

    def note_rejection_reported(self, b: int) -> None:
        self._rejected_seen[b] = self._taken[b, self._L.rejected]

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
        if not self.core.alive:
            return f"{LOST}: no step for {1e3 * (time.monotonic() - self.core.ticks_at):.0f} ms"
        if not self._finite[b]:
            return f"{NONFINITE}: {', '.join(self._L.nonfinite_fields(self._buf[b]))} (arm {b})"
        return None

    def sent(self, b: int) -> tuple:
        """(setpoints, mode commands) sent to arm ``b`` so far."""
        c = self._cmds
        return int(c.servo_seq[b]), int(c.mode_seq[b])

    def applied(self, b: int) -> tuple:
        """(setpoints, mode commands) arm ``b``'s child had applied at the last read of its state
        record (taken or not: also while the arm is latched): a mode command of this side is in
        effect once ``applied(b)[1] == sent(b)[1]``; until then ``state`` reads the mode this
        side asked for."""
        row = self._buf[b]
        return int(row[self._L.servo_seq]), int(row[self._L.mode_seq])

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
                self._blk.inject_t[b] = math.nan
                self._blk.inject[b] = INJECT_NAN if kind == "nan" else INJECT_NONE
        if self._proc.poll() is None:
            sig = {"stall": signal.SIGSTOP, "kill": signal.SIGKILL, "none": signal.SIGCONT}.get(kind)
            if sig is not None:
                os.kill(self._proc.pid, sig)
        if kind == "kill":
            self._proc.wait(timeout=5.0)

    def injected_at(self, arm: int) -> float:
        """When the child first published arm ``arm``'s injected NaN state (``time.perf_counter``
        s, the service's clock); NaN before it did, or without a NaN injection."""
        if self._blk is None:
            raise InputError("injected_at: the robot host is closed")
        return float(self._blk.inject_t[int(arm)])

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
        """Queue arm b's setpoint (4x4 world: an array, or a memoryview of its 16 floats, row-major),
        already checked; ``publish`` sends every queued one at once (``servo`` checks and queues
        in one compiled call)."""
        self._cmds.pose[b] = np.reshape(pose, 16) if type(pose) is not memoryview else np.frombuffer(pose)
        self._cmds.servo_seq[b] += 1.0
        self._T_d[b] = self._cmds.pose[b]
        self.core.staged = 1

    def stage_jaw(self, b: int, angle: float) -> None:
        """Queue arm b's jaw setpoint (rad); ``publish`` sends it with the poses."""
        seq_at, jaw_at = self._jaw_at[b]
        mv = self._cmds_mv
        mv[jaw_at] = float(angle)
        mv[seq_at] = mv[seq_at] + 1.0
        self.core.staged = 1

    def publish(self) -> None:
        """Send the queued setpoints (one sequence-locked write for all arms)."""
        if self._blk is not None:
            fast.pf_host_publish(self._core)

    def send_mode(self, b: int, code: int) -> None:
        """Send a mode command (``HOLD``, ``RESUME``, ``ENABLE``, ``FAULT``) now (with any queued
        setpoints: they come first)."""
        if self._blk is None:
            return
        c = self._cmds
        i = int(c.mode_seq[b])
        c.ring[b, i % RING] = code
        c.mode_seq[b] = i + 1
        self.core.staged = 1
        fast.pf_host_publish(self._core)

    @property
    def alive(self) -> bool:
        """The robot process runs and stepped within the watchdog time (as of the last read)."""
        return bool(self.core.alive) and self._proc is not None and self._proc.poll() is None

    def close(self) -> None:
        """Stop the child (it finishes its period) and free the shared memory. Idempotent."""
        proc = getattr(self, "_proc", None)
        if proc is not None:
            stop_by_flag(proc, self._blk.ctl if self._blk is not None else None)
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
        core = getattr(self, "core", None)
        if core is not None:
            core.alive = 0

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass
