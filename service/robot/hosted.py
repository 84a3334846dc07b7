"""Simulated robots in their own process, stepped on their own 1 kHz clock, as real arms are.

A real arm's controller (the Raven II's RTAI loop, a Franka control box) steps its joints at
its own rate while the haptic service streams setpoints and reads the measured state.
``RobotHost`` does the same for the simulated models of live runs: a child process builds the
arms from the ``[robot]`` table and steps them on absolute 1 kHz deadlines; shared memory
carries the service's commands one way and the measured state the other. In the service each
arm is a ``HostedRobot``: a local instance of the same model (kinematics, limits, workspace,
tool geometry) whose state is copied from the child once per tick (``step``), and whose
commands go to the child. A haptic tick then spends about 15 us per arm instead of the
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
* a watchdog runs in every ``sync`` (each tick), whatever the state record holds: a child that
  stops stepping, or whose record does not read, for ``timeout_s`` (default 20 ms, at most
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

State and commands cross through one shared-memory block (robot/hosted_block.py: the layout,
defined once for both sides), each direction a double-buffered channel (sequence counters and
a CRC-32 of the bytes per slot): neither side ever waits for
the other, so the haptic tick never waits for a preempted robot process, nor the robot for the
service. The child is started as ``python -m pointfence.service.robot.hosted`` (nothing of the
parent's program is imported again) and ends when its parent does.
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

from .base import RobotMode
from .factory import robot_from_config
from .hosted_block import (CTL_PID, CTL_READY, CTL_STOP, CTL_TICKS, ENABLE, FAULT, HOLD, INJECT_NAN, INJECT_NONE,
                           POISONED, RESUME, RING, TEXT, Block, command_views, get_text, put_text)

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


def _write_state(L, row: np.ndarray, text: np.ndarray, r, applied: tuple, texts: list, poison: bool) -> None:
    """Arm ``r``'s state into its state ``row`` (layout ``L``; and ``text``, where a message
    changed); ``poison``: the fields ``POISONED`` as NaN (fault injection)."""
    row[L.t], row[L.mode], row[L.rejected], row[L.ignored] = r.t, int(r.state), r.rejected_commands, r.ignored_commands
    row[L.servo_seq], row[L.mode_seq] = applied
    fault, err = r.fault_reason, r.last_error
    if fault != texts[0]:
        texts[0] = fault
        put_text(text[0], fault)
        row[L.fault_ver] += 1
    if err != texts[1]:
        texts[1] = err
        put_text(text[1], err)
        row[L.error_ver] += 1
    r.copy_state(row[L.q], row[L.dq], row[L.tau], row[L.q_d], row[L.T_meas], row[L.T_d])
    if poison:
        for name in POISONED:
            row[getattr(L, name)] = math.nan


def _child(shm_name: str, tables: list, dof: int, rate_hz: float, rt_priority: int, parent: int,
           start_q: Optional[list] = None) -> None:
    """The child process: build the arms (placed at ``start_q``, one joint list or None per arm,
    after a restart), then step them on absolute deadlines until told to stop (or until the
    parent is gone)."""
    shm = shared_memory.SharedMemory(name=shm_name)
    try:   # the parent owns the block: this process's resource tracker must not unlink it at exit
        from multiprocessing import resource_tracker

        resource_tracker.unregister(shm._name, "shared_memory")
    except Exception:
        pass
    try:
        blk = Block(shm.buf, len(tables), dof)
        L = blk.layout
        robots = [robot_from_config(t) for t in tables]
        for r, q in zip(robots, start_q or []):
            if q is not None:                # (within the limits: a joint read at a limit may lie past it by rounding)
                r.reset(np.clip(q, *r.joint_limits))
        if rt_priority > 0:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(rt_priority)))
            except (AttributeError, OSError):
                pass
        seen = [[0, 0] for _ in robots]        # servo seq and mode commands applied
        texts = [[None, None] for _ in robots]
        period = 1.0 / rate_hz
        n = len(robots)
        state = np.zeros((n, blk.S))
        rec = np.zeros(blk.C)
        cmds, poses, ring = command_views(rec, n)

        def publish():
            for b, r in enumerate(robots):
                _write_state(L, state[b], blk.text[b], r, tuple(seen[b]), texts[b], blk.inject[b] == INJECT_NAN)
            blk.state.write(state.reshape(-1))

        publish()
        blk.ctl[CTL_PID] = os.getpid()
        blk.ctl[CTL_READY] = 1
        t0 = time.monotonic()
        k = 0
        while blk.ctl[CTL_STOP] == 0 and os.getppid() == parent:
            due = t0 + k * period
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            late = time.monotonic() - due
            skip = int(late // period) if late >= period else 0   # periods lost: step them at once
            got = blk.cmd.read(rec)          # else (lapped) this period keeps the last commands
            for b, r in enumerate(robots):
                n_mode = int(cmds[b, 1]) if got else seen[b][1]
                while seen[b][1] < n_mode:
                    code = int(ring[b, seen[b][1] % RING])
                    if code == HOLD:
                        r.hold()
                    elif code == RESUME:
                        r.resume()
                    elif code == ENABLE:
                        r.enable()
                    elif code == FAULT:
                        r.fault("fault requested by the service")
                    seen[b][1] += 1
                if got and cmds[b, 0] != seen[b][0]:
                    seen[b][0] = int(cmds[b, 0])
                    try:
                        r.servo_cp(poses[b].reshape(4, 4))
                    except InputError:
                        pass            # counted in rejected_commands, kept in last_error
                r.step(period * (1 + skip))
            publish()
            blk.ctl[CTL_TICKS] += 1 + skip
            k += 1 + skip
    finally:
        shm.close()


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
    """

    def __init__(self, tables: Sequence[dict], rate_hz: float = 1000.0, rt_priority: int = 0,
                 timeout_s: float = WATCHDOG_S, start_timeout_s: float = 30.0):
        tables = [dict(t) for t in tables]
        if not tables:
            raise InputError("RobotHost: no robot tables; expected one [robot] table per arm")
        if not (isinstance(timeout_s, (int, float)) and 0 < timeout_s <= WATCHDOG_MAX_S):
            raise InputError(f"RobotHost: timeout_s = {timeout_s!r}; expected a watchdog time > 0 and "
                             f"<= {WATCHDOG_MAX_S} s (a robot process silent for longer must read as FAULT)")
        local = [robot_from_config(t) for t in tables]      # validates every table here, first
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
        self._buf = np.zeros((self.n, self._blk.S))
        self._sum = np.zeros(self.n)
        self._finite = [True] * self.n
        self._rec = np.zeros(self._blk.C)          # the commands written so far (this side's copy)
        self._cmd, self._poses, self._ring = command_views(self._rec, self.n)
        self._texts_buf = np.zeros((self.n, 2, TEXT), np.uint8)
        self._spawn(None)
        self.robots = [HostedRobot(self, b, r) for b, r in enumerate(local)]
        self.sync()

    def _spawn(self, start_q: Optional[list]) -> None:
        """Start the child on a zeroed block and wait until it has built the arms."""
        np.ndarray((self._blk.size,), np.uint8, buffer=self._shm.buf)[:] = 0   # no command of a previous child
        self._rec[:] = 0
        self._staged = False
        self._versions = [(0.0, 0.0)] * self.n
        # a fresh interpreter (no fork of a process that runs OpenCL and CUDA threads, and none of
        # the parent's main module imported again, as multiprocessing's spawn would)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "pointfence.service.robot.hosted", self._shm.name,
             json.dumps(self._tables, default=_plain), str(self.dof), repr(self._rate), str(self._prio),
             str(os.getpid()), json.dumps(start_q)], stdin=subprocess.DEVNULL)
        end = time.monotonic() + self._start_timeout
        while self._blk.ctl[CTL_READY] == 0:
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
        """Copy the child's latest state into every arm's local instance (one copy for all arms),
        after the watchdog: a child that has not stepped, or whose state record has not read,
        for ``timeout_s`` faults every arm; an arm whose state is not finite faults."""
        blk, buf, L = self._blk, self._buf, self._L
        if blk is None:                    # closed: the arms keep their last state
            return
        now = time.monotonic()
        ticks = int(blk.ctl[CTL_TICKS])
        if ticks != self._ticks:
            self._ticks, self._ticks_at = ticks, now
        got = blk.state.read(buf.reshape(-1))
        if got:
            self._read_at = now
        silent, unread = now - self._ticks_at, now - self._read_at
        self._alive = silent <= self.timeout_s and unread <= self.timeout_s
        if not self._alive and not all(r.latched for r in self.robots):
            self._lost(silent, unread)
        if not got:            return                         # lapped (this thread was preempted): next tick
        np.sum(buf, axis=1, out=self._sum)
        for b in range(self.n):
            ok = math.isfinite(self._sum[b])
            self._finite[b] = ok
            if not ok:
                if not self.robots[b].latched:
                    self.robots[b]._fail(f"{NONFINITE}: {', '.join(L.nonfinite_fields(buf[b]))} (arm {b})")
                continue
            v = (buf[b, L.fault_ver], buf[b, L.error_ver])
            if v != self._versions[b]:     # a fault reason or an error message changed
                self._versions[b] = v
                self.robots[b]._texts(get_text(blk.text[b, 0]), get_text(blk.text[b, 1]))
        if not self._alive:
            return
        rows, sent = buf.tolist(), self._cmd.tolist()
        for b, r in enumerate(self.robots):
            if self._finite[b]:
                r._load(rows[b], buf[b], sent[b])

    def _lost(self, silent: float, unread: float) -> None:
        """Every arm FAULT: the child has not stepped for ``silent`` s, or its state record has not
        read for ``unread`` s."""
        if silent > self.timeout_s:
            ended = self._proc is None or self._proc.poll() is not None
            why = f"no step for {1e3 * silent:.0f} ms (process {'ended' if ended else 'alive'})"
        else:
            why = f"state record unreadable for {1e3 * unread:.0f} ms"
        for r in self.robots:
            r._fail(f"{LOST}: {why}")

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
                self._blk.ctl[CTL_STOP] = 1
                try:
                    self._proc.wait(timeout=2.0)
                except subprocess.TimeoutExpired:
                    self._proc.kill()
                    self._proc.wait(timeout=2.0)
        start_q = [r.measured_js().position.tolist() for r in self.robots]
        for r in self.robots:
            r._fail(f"{LOST}: the robot process was restarted")
        self._spawn(start_q)
        for b in range(self.n):
            self._send_mode(b, FAULT)      # the new process starts braked, as the arms read here

    def _stage_pose(self, b: int, pose: np.ndarray) -> None:
        """Queue arm b's setpoint; ``publish`` sends every queued one at once."""
        self._poses[b] = pose.ravel()
        self._cmd[b, 0] += 1
        self._staged = True

    def publish(self) -> None:
        """Send the queued setpoints (one sequence-locked write for all arms)."""
        blk = self._blk
        if not self._staged or blk is None:
            return
        blk.cmd.write(self._rec)
        self._staged = False

    def _send_mode(self, b: int, code: int) -> None:
        """Send a mode command now (with any queued setpoints: they come first)."""
        blk = self._blk
        if blk is None:
            return
        i = int(self._cmd[b, 1])
        self._ring[b, i % RING] = code
        self._cmd[b, 1] = i + 1
        blk.cmd.write(self._rec)
        self._staged = False

    @property
    def alive(self) -> bool:
        """The robot process runs and stepped within the watchdog time (as of the last sync)."""
        return self._alive and self._proc is not None and self._proc.poll() is None

    def close(self) -> None:
        """Stop the child (it finishes its period) and free the shared memory. Idempotent."""
        proc = getattr(self, "_proc", None)
        if proc is not None:
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGCONT)    # (a stalled child cannot see the stop request)
            if self._blk is not None:
                self._blk.ctl[CTL_STOP] = 1
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
    """One arm of a ``RobotHost``: the robot interface the service uses (see robot/base.py).

    Reads (``state``, ``measured_cp``, ``setpoint_cp``, ``measured_js``, the joint lists, the
    kinematics) come from a local instance of the model whose state ``step`` copies from the
    child; commands (``servo_cp``, ``hold``, ``resume``, ``enable``, ``fault``) go to the child.
    A FAULT of the robot process itself (silent, dead, non-finite state) is latched here: the
    arm reads FAULT with that reason, sends nothing, and only ``enable()`` clears it, once
    ``RobotHost.ready`` allows.
    """

    def __init__(self, host: RobotHost, index: int, local):
        self._host, self._b, self._r = host, index, local
        self._L = host._L
        self._child_rejected = 0          # setpoints the child rejected (out of reach)
        self._rejected_seen = 0           # ... of which servo_cp has reported
        self._local_rejected = 0          # setpoints refused here (malformed, workspace)
        self._latched: Optional[str] = None   # FAULT of the robot process (reason), until enable()
        self._pose = np.eye(4)
        self.hosted = True

    def __getattr__(self, name):          # everything not overridden: the synced local instance
        return getattr(self._r, name)

    def __repr__(self) -> str:
        proc = self._host._proc
        return f"HostedRobot({self._r.model!r}, arm {self._b}, process {proc.pid if proc else None})"

    # --- state from the child ---------------------------------------------------------------------
    def _load(self, row: list, st: np.ndarray, sent: list) -> None:
        """Take the child's state: ``row`` as floats, ``st`` the same as an array; ``sent``: the
        setpoints and mode commands sent to this arm so far (counts)."""
        r, L = self._r, self._L
        if self._latched is not None:
            return                         # latched until the host answers again and enable() is called
        mode = _MODES[int(row[L.mode])] if row[L.mode_seq] >= sent[1] else None   # our mode commands applied
        r.adopt_state(row[L.t], row[L.q], row[L.dq], row[L.tau], st[L.T_meas], mode)
        self._child_rejected = int(row[L.rejected])
        r.rejected_commands = self._child_rejected + self._local_rejected
        r.ignored_commands = int(row[L.ignored])
        if row[L.servo_seq] >= sent[0]:    # else keep the setpoint just sent
            r.adopt_setpoint(st[L.T_d], row[L.q_d])

    def _texts(self, fault: Optional[str], err: Optional[str]) -> None:
        self._r.adopt_texts(self._r.fault_reason if self._latched is not None else fault, err)

    @property
    def latched(self) -> bool:
        """Whether the arm is in a FAULT of the robot process (cleared only by ``enable()``)."""
        return self._latched is not None

    def _fail(self, why: str) -> None:
        """Latch a FAULT of the robot process (the first reason stays) and brake the child's arm."""
        if self._latched is not None:
            return
        self._latched = why
        self._r.fault(why)                 # local copy: FAULT, joints stopped; servo_cp sends nothing
        self._host._send_mode(self._b, FAULT)

    # --- the robot interface ------------------------------------------------------------------------
    @property
    def state(self) -> RobotMode:
        return self._r.state

    @property
    def fault_reason(self) -> Optional[str]:
        return self._r.fault_reason

    def step(self, dt: float = 1e-3) -> None:
        """The child steps on its own clock. The last arm's call of a tick sends every setpoint
        queued in the tick; the first arm's call reads the child's latest state (all arms)."""
        if not (dt > 0.0) or dt == math.inf:
            raise InputError(f"step: dt = {dt!r}; expected a finite number > 0")
        host = self._host
        if self._b == 0:
            host.publish()                 # anything queued since the last arm's step
            host.sync()
        if self._b == host.n - 1:
            host.publish()

    def servo_cp(self, T) -> bool:
        """Send a Cartesian setpoint (4x4 world pose, or a position (3,) with the setpoint's
        orientation). Raises InputError, sending nothing, on a malformed or non-finite pose, a
        workspace violation, or when the child rejected the previous setpoint (its message).
        Returns False, sending nothing, unless the arm is ENABLED."""
        r = self._r
        if self._child_rejected > self._rejected_seen:
            self._rejected_seen = self._child_rejected
            raise InputError(r.last_error or "servo_cp: the robot rejected the previous setpoint")
        try:
            pose = r._setpoint_pose(T, out=self._pose)     # checks it, as the arm in the tick does
        except InputError:
            self._local_rejected += 1
            r.rejected_commands = self._child_rejected + self._local_rejected
            raise
        if self._latched is not None or r.state is not RobotMode.ENABLED:
            r.ignored_commands += 1
            return False
        self._host._stage_pose(self._b, pose)
        r.adopt_setpoint(pose)
        return True

    def servo_jp(self, q) -> bool:
        raise InputError("servo_jp is not streamed to a hosted robot; use servo_cp, or run the robots in the "
                         "haptic loop ([service] robot_process = false)")

    def _mode_cmd(self, code: int, local) -> None:
        self._host._send_mode(self._b, code)
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
                self._r.last_error = f"enable refused: {why}"
                return
            self._latched = None
        self._mode_cmd(ENABLE, self._r.enable)

    def fault(self, reason: str) -> None:
        self._mode_cmd(FAULT, lambda: self._r.fault(reason))

    def reset(self, q=None) -> None:
        raise InputError("reset places a simulated robot for set-up; a hosted robot starts at its q0 "
                         "(set it in [robot]), or run the robots in the haptic loop ([service] robot_process = false)")

    def close(self) -> None:
        pass                               # the host owns the process


if __name__ == "__main__":
    _shm, _tables, _dof, _rate, _prio, _parent, _q = sys.argv[1:8]
    _child(_shm, json.loads(_tables), int(_dof), float(_rate), int(_prio), int(_parent), json.loads(_q))
