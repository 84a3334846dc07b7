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
* a child that stops stepping for ``timeout_s`` (it died, or it starves) puts every arm in
  FAULT ("robot process not answering"), so the service holds; ``close`` ends the child.

State and commands cross through one shared-memory block, each direction a double-buffered
channel (``_Channel``: sequence counters and a checksum per slot): neither side ever waits for
the other, so the haptic tick never waits for a preempted robot process, nor the robot for the
service. The child is started as ``python -m pointfence.service.robot.hosted`` (nothing of the
parent's program is imported again) and ends when its parent does.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from multiprocessing import shared_memory
from typing import Optional, Sequence

import numpy as np

from pointfence.kernels.errors import InputError

from .base import RobotMode
from .factory import robot_from_config

# mode commands (service -> child), in a ring per arm
HOLD, RESUME, ENABLE, FAULT = 1, 2, 3, 4
RING = 64
TEXT = 240
LOST = "robot process not answering"
_MODES = tuple(RobotMode)
#: state floats before the joint arrays: t, mode, rejected, ignored, servo seq applied,
#: mode commands applied, fault text version, error text version
_HDR = 8


class _Channel:
    """One writer, one reader: a record of ``size`` floats in two slots. The writer fills the slot
    the reader was not pointed at (its counter odd while it writes, then its checksum), then points
    the reader at it; the reader copies the slot it is pointed at and keeps the copy if that
    slot's counter was even and unchanged around the copy and the sum matches. Neither side ever
    waits for the other: a reader only retries if the writer lapped it (two whole writes during
    one copy), and a writer preempted mid-write leaves the previous record readable."""

    def __init__(self, take, size: int):
        self.size = size
        self.data = take((2, size), np.float64)
        self.meta = take((4,), np.int64)        # counter of slot 0, of slot 1, slot to read
        self.sums = take((2,), np.float64)

    def write(self, rec: np.ndarray) -> None:
        w = 1 - int(self.meta[2])
        self.meta[w] += 1
        np.copyto(self.data[w], rec)
        self.sums[w] = float(rec.sum())
        self.meta[w] += 1
        self.meta[2] = w

    def read(self, out: np.ndarray, tries: int = 8) -> bool:
        for _ in range(tries):
            i = int(self.meta[2])
            s1 = int(self.meta[i])
            if s1 & 1:
                continue
            np.copyto(out, self.data[i])
            if int(self.meta[i]) == s1 and float(out.sum()) == float(self.sums[i]):
                return True
        return False


class _Block:
    """The shared block for ``n`` arms of ``dof`` joints: control words, the state channel
    (child -> service: ``n`` rows of ``S`` floats), the command channel (service -> child: per arm
    the servo count and the mode-command count, the latest setpoint pose, the mode-command ring)
    and the arms' texts (fault reason, last error; versioned in the state rows)."""

    def __init__(self, buf, n: int, dof: int):
        self.n, self.dof = n, dof
        self.S = _HDR + 4 * dof + 32            # q, dq, tau, q_d; T_meas, T_d
        self.C = n * (2 + 16 + RING)
        off = 0

        def take(shape, dtype):   # buf None: only the layout (nbytes)
            nonlocal off
            a = np.empty(shape, dtype) if buf is None else np.ndarray(shape, dtype, buffer=buf, offset=off)
            off += a.nbytes
            return a

        self.ctl = take((4,), np.int64)         # stop request, child ticks, child pid, child ready
        self.state = _Channel(take, n * self.S)
        self.cmd = _Channel(take, self.C)
        self.text = take((n, 2, TEXT), np.uint8)   # fault reason, last error (UTF-8)
        self.size = off

    @staticmethod
    def nbytes(n: int, dof: int) -> int:
        return _Block(None, n, dof).size


def _command_views(rec: np.ndarray, n: int) -> tuple:
    """(counts (n, 2), poses (n, 16), ring (n, RING)): views of a command record."""
    return (rec[: 2 * n].reshape(n, 2), rec[2 * n: 18 * n].reshape(n, 16), rec[18 * n:].reshape(n, RING))


def _plain(o):
    """JSON for the NumPy values a programmatic ``[robot]`` table may hold."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"[robot] value {o!r} ({type(o).__name__}) cannot be sent to the robot process")


def _put_text(dst: np.ndarray, s: Optional[str]) -> None:
    b = (s or "").encode("utf-8", "replace")[:TEXT]
    dst[:] = 0
    dst[: len(b)] = np.frombuffer(b, np.uint8)


def _get_text(src: np.ndarray) -> Optional[str]:
    b = bytes(src).rstrip(b"\0")
    return b.decode("utf-8", "replace") if b else None


def _write_state(row: np.ndarray, text: np.ndarray, r, applied: tuple, texts: list) -> None:
    """Arm ``r``'s state into its state ``row`` (and ``text``, where a message changed)."""
    d = r.dof
    row[0], row[1], row[2], row[3] = r.t, int(r.state), r.rejected_commands, r.ignored_commands
    row[4], row[5] = applied
    fault, err = r.fault_reason, r.last_error
    if fault != texts[0]:
        texts[0] = fault
        _put_text(text[0], fault)
        row[6] += 1
    if err != texts[1]:
        texts[1] = err
        _put_text(text[1], err)
        row[7] += 1
    h = _HDR
    row[h: h + d] = r._q
    row[h + d: h + 2 * d] = r._dq
    row[h + 2 * d: h + 3 * d] = r._tau
    row[h + 3 * d: h + 4 * d] = r._q_d
    row[h + 4 * d: h + 4 * d + 16] = r.measured_cp().ravel()
    row[h + 4 * d + 16: h + 4 * d + 32] = r._T_d.ravel()


def _child(shm_name: str, tables: list, dof: int, rate_hz: float, rt_priority: int, parent: int) -> None:
    """The child process: build the arms, then step them on absolute deadlines until told to stop
    (or until the parent is gone)."""
    shm = shared_memory.SharedMemory(name=shm_name)
    try:   # the parent owns the block: this process's resource tracker must not unlink it at exit
        from multiprocessing import resource_tracker

        resource_tracker.unregister(shm._name, "shared_memory")
    except Exception:
        pass
    try:
        blk = _Block(shm.buf, len(tables), dof)
        robots = [robot_from_config(t) for t in tables]
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
        cmds, poses, ring = _command_views(rec, n)

        def publish():
            for b, r in enumerate(robots):
                _write_state(state[b], blk.text[b], r, tuple(seen[b]), texts[b])
            blk.state.write(state.reshape(-1))

        publish()
        blk.ctl[2] = os.getpid()
        blk.ctl[3] = 1
        t0 = time.monotonic()
        k = 0
        while blk.ctl[0] == 0 and os.getppid() == parent:
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
            blk.ctl[1] += 1 + skip
            k += 1 + skip
    finally:
        shm.close()


class RobotHost:
    """Robots built from ``tables`` (one ``[robot]`` table per arm) in a child process.

    ``robots``: one ``HostedRobot`` per arm, for the service. ``rt_priority``: SCHED_FIFO
    priority of the child where allowed (0: normal). ``timeout_s``: how long the child may go
    without stepping before the arms read as FAULT. ``start_timeout_s``: how long to wait for
    the child to build the arms. Call ``close()`` when done (the child also ends with its parent).
    """

    def __init__(self, tables: Sequence[dict], rate_hz: float = 1000.0, rt_priority: int = 0,
                 timeout_s: float = 0.5, start_timeout_s: float = 30.0):
        tables = [dict(t) for t in tables]
        if not tables:
            raise InputError("RobotHost: no robot tables; expected one [robot] table per arm")
        local = [robot_from_config(t) for t in tables]      # validates every table here, first
        dof = max(r.dof for r in local)
        if any(r.dof != dof for r in local):
            raise InputError("RobotHost: every hosted arm must have the same number of joints")
        self.n, self.dof = len(tables), dof
        self.timeout_s = float(timeout_s)
        size = _Block.nbytes(self.n, dof)
        self._shm = shared_memory.SharedMemory(create=True, size=size)
        self._blk = _Block(self._shm.buf, self.n, dof)   # a new shared memory object reads as zeros
        # a fresh interpreter (no fork of a process that runs OpenCL and CUDA threads, and none of
        # the parent's main module imported again, as multiprocessing's spawn would)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "pointfence.service.robot.hosted", self._shm.name, json.dumps(tables, default=_plain), str(dof),
             repr(float(rate_hz)), str(int(rt_priority)), str(os.getpid())], stdin=subprocess.DEVNULL)
        end = time.monotonic() + start_timeout_s
        while self._blk.ctl[3] == 0:
            if self._proc.poll() is not None or time.monotonic() > end:
                code = self._proc.poll()
                self.close()
                raise RuntimeError(f"the robot process did not start (exit code {code}); run the robots "
                                   "in the haptic loop instead with [service] robot_process = false")
            time.sleep(0.005)
        self._buf = np.zeros((self.n, self._blk.S))
        self._rec = np.zeros(self._blk.C)          # the commands written so far (this side's copy)
        self._cmd, self._poses, self._ring = _command_views(self._rec, self.n)
        self._texts_buf = np.zeros((self.n, 2, TEXT), np.uint8)
        self._versions = [(0.0, 0.0)] * self.n
        self._staged = False
        self._ticks = -1
        self._ticks_at = time.monotonic()
        self._alive = True
        self.robots = [HostedRobot(self, b, r) for b, r in enumerate(local)]
        self.sync()

    # --- service side ---------------------------------------------------------------------------
    def sync(self) -> None:
        """Copy the child's latest state into every arm's local instance (one copy for all arms)."""
        blk, buf, texts = self._blk, self._buf, self._texts_buf
        if blk is None:                    # closed: the arms keep their last state
            return
        if not blk.state.read(buf.reshape(-1)):
            return                         # lapped (this thread was preempted): next tick
        changed = []
        for b in range(self.n):            # a fault reason or an error message changed
            v = (buf[b, 6], buf[b, 7])
            if v != self._versions[b]:
                self._versions[b] = v
                np.copyto(texts[b], blk.text[b])
                changed.append((b, _get_text(texts[b, 0]), _get_text(texts[b, 1])))
        ticks = int(blk.ctl[1])
        now = time.monotonic()
        if ticks != self._ticks:
            self._ticks, self._ticks_at = ticks, now
            self._alive = True
        elif now - self._ticks_at > self.timeout_s:
            self._lost(f"no step for {1e3 * (now - self._ticks_at):.0f} ms "
                       f"(process {'alive' if self._proc.poll() is None else 'ended'})")
            return
        for b, fault, err in changed:
            self.robots[b]._texts(fault, err)
        rows, sent = buf.tolist(), self._cmd.tolist()
        for b, r in enumerate(self.robots):
            r._load(rows[b], buf[b], sent[b])

    def _lost(self, why: str) -> None:
        self._alive = False
        for r in getattr(self, "robots", []):
            r._fail(f"{LOST}: {why}")

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
        return self._alive and self._proc is not None and self._proc.poll() is None

    def close(self) -> None:
        """Stop the child (it finishes its period) and free the shared memory. Idempotent."""
        proc = getattr(self, "_proc", None)
        if proc is not None:
            if self._blk is not None:
                self._blk.ctl[0] = 1
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
    """

    def __init__(self, host: RobotHost, index: int, local):
        self._host, self._b, self._r = host, index, local
        self._child_rejected = 0          # setpoints the child rejected (out of reach)
        self._rejected_seen = 0           # ... of which servo_cp has reported
        self._local_rejected = 0          # setpoints refused here (malformed, workspace)
        self._lost = False                # FAULT because the robot process stopped answering
        self._T_meas16 = local._T_meas.reshape(16)      # views: the local poses, flat
        self._T_d16 = local._T_d.reshape(16)
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
        r, d = self._r, self._r.dof
        if self._lost:
            return                         # latched until the host answers again and enable() is called
        r.t = row[0]
        if row[5] >= sent[1]:              # the child has applied our mode commands
            r._mode = _MODES[int(row[1])]
        self._child_rejected = int(row[2])
        r.rejected_commands = self._child_rejected + self._local_rejected
        r.ignored_commands = int(row[3])
        h = _HDR
        r._q[:] = row[h: h + d]
        r._dq[:] = row[h + d: h + 2 * d]
        r._tau[:] = row[h + 2 * d: h + 3 * d]
        np.copyto(self._T_meas16, st[h + 4 * d: h + 4 * d + 16])
        r._T_meas_ok = True
        if row[4] >= sent[0]:              # else keep the setpoint just sent
            r._q_d[:] = row[h + 3 * d: h + 4 * d]
            np.copyto(self._T_d16, st[h + 4 * d + 16: h + 4 * d + 32])

    def _texts(self, fault: Optional[str], err: Optional[str]) -> None:
        if not self._lost:
            self._r._fault = fault
        self._r.last_error = err

    def _fail(self, why: str) -> None:
        r = self._r
        self._lost = True
        if r._mode is not RobotMode.FAULT:
            r._mode = RobotMode.FAULT
            r._fault = why
            r._dq[:] = [0.0] * r.dof

    # --- the robot interface ------------------------------------------------------------------------
    @property
    def state(self) -> RobotMode:
        return self._r._mode

    @property
    def fault_reason(self) -> Optional[str]:
        return self._r._fault

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
        workspace violation, or when the child rejected the previous setpoint (its message)."""
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
        if r._mode is not RobotMode.ENABLED:
            r.ignored_commands += 1
            return False
        self._host._stage_pose(self._b, pose)
        r._T_d[...] = pose
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
        r = self._r
        if self._lost:
            if not self._host.alive:
                return                    # nothing to enable: the arm stays in FAULT
            self._lost = False
        self._mode_cmd(ENABLE, r.enable)

    def fault(self, reason: str) -> None:
        self._mode_cmd(FAULT, lambda: self._r.fault(reason))

    def reset(self, q=None) -> None:
        raise InputError("reset places a simulated robot for set-up; a hosted robot starts at its q0 "
                         "(set it in [robot]), or run the robots in the haptic loop ([service] robot_process = false)")

    def close(self) -> None:
        pass                               # the host owns the process


if __name__ == "__main__":
    _shm, _tables, _dof, _rate, _prio, _parent = sys.argv[1:7]
    _child(_shm, json.loads(_tables), int(_dof), float(_rate), int(_prio), int(_parent))
