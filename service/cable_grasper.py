"""The cable-driven grasper controller (chapters 4-5) in the service: ``GrasperHost`` runs it at
1 kHz in its own process and lets the haptic tick command the jaw without waiting.

Why a process: the controller's tick (UKF + iLQG MPC in generated C, plus ~50 us of Python around
them) at 1 kHz in a thread of the service would take the interpreter lock from the haptic loop a
thousand times a second. In a child (``cable_grasper_child``, a fresh interpreter) it runs on its
own clock, as robot/hosted.py runs the simulated arms; one shared-memory block
(``cable_block``) carries the jaw command one way and the estimate the other, each a
double-buffered channel that neither side waits on.

The service's side:

* ``start()``: spawn the process, wait until it has built (and compiled) the controller;
* ``command(jaw_rad)``: once per haptic tick, the jaw angle the master's grasp asks for (rad, link
  side); non-blocking and allocation-free: one write of a 4-float record, then the watchdog (two
  integer reads). A non-finite command is refused (counted in ``rejected``, the last one kept:
  SAFETY.md S6);
* ``faulted`` / ``fault_reason``: whether the grasper is in a latched fault, and why;
* ``snapshot()``: a ``GrasperSnapshot`` (plain values) for the status, the metrics and the
  recording; ``copy_into(row)``: the recorded values into a preallocated row (``RECORD_FIELDS``);
* ``clear_fault()``: the operator cleared faults (a dead process is started again);
* ``close()``.

Faults (each latched, zero grasper torque, reported by name; ``Service`` holds the arm, S3):

* the controller's own (``CableLoop``: a non-finite encoder reading, estimate or torque, an
  estimated parameter out of its physical range), and a grasper tick later than
  ``max_lateness_s``: latched in the child, which applies zero torque from that tick on;
* the process silent for ``watchdog_s`` (dead, stopped, starved: S9): ``"grasper process not
  answering: ..."``, latched here; the child is told to hold (zero torque, latched) so that a
  stopped process that resumes does not drive the jaw. A dead process drives nothing (the
  simulated plant ends with it; a motor driver's own watchdog would cut a real motor).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from multiprocessing import shared_memory
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from .cable_block import ALERT_TEXT, FAULT_TEXT, INJECT_NAN, INJECT_NONE, LOST_CODE, GrasperBlock, get_text
from .cable_settings import CableTable
from .child_pipe import stop_by_flag

LOST = "grasper process not answering"
#: fault kinds of ``inject``
FAULT_KINDS = ("nan", "stall", "kill", "none")
#: the recorded values (``copy_into``), in order: the jaw (rad, rad/s), estimated external link
#: torque (N m), motor torque (N m), setpoint (rad), estimated tension (g), k_e (N/m), the fault's
#: kind (0: none; ``cable_block.FAULT_CODES``), tension alert code, lateness of the child's last tick (s)
RECORD_FIELDS = ("jaw", "jaw_velocity", "link_torque", "motor_torque", "setpoint", "tension_g", "k_e", "fault_code",
                 "tension_alert", "late")


_FAULT_AT = RECORD_FIELDS.index("fault_code")


@dataclasses.dataclass(frozen=True)
class GrasperSnapshot:
    """The grasper's state as of the child's last published tick (SI units; tension in grams)."""

    arm: int
    running: bool               # the process runs and ticks within the watchdog time
    ticks: int                  # control ticks run
    periods: int                # control periods, run or skipped
    deadline_misses: int        # ticks that ended past their period + periods skipped
    commands: int               # jaw commands sent by the service
    rejected: int               # non-finite jaw commands refused
    jaw_command: float          # the last command sent (rad)
    setpoint: float             # the controller's setpoint: clamped, rate-limited (rad)
    jaw: float                  # estimated jaw (link) angle (rad)
    jaw_velocity: float         # (rad/s)
    motor_torque: float         # applied (N m); 0 while faulted
    link_torque: float          # estimated external torque on the jaw (contact) (N m)
    k_e: float                  # cable stiffness used / estimated (N/m)
    tension_g: Optional[float]  # estimated cable tension (g); None: unknown (in contact, too slow, at rest)
    alerts: tuple               # human-readable alerts (tension, misses, degraded)
    fault: Optional[str]        # the latched fault, None if none
    late_ms: float              # lateness of the last tick (ms)
    late_max_ms: float          # largest lateness so far (ms)
    compute_us: float           # the last tick's compute time (us)
    compute_max_us: float
    degraded: bool              # the UKF/MPC run interpreted (no C compiler)
    sim_jaw: Optional[float]    # the simulated plant's true jaw angle (rad); None for a real plant

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


class GrasperHost:
    """The grasper controller of ``table`` (``cable_settings.CableTable``) in a child process; see
    the module docstring. ``rt_priority``: SCHED_FIFO priority of the child where allowed (0:
    normal); ``start_timeout_s``: how long the child may take to build the controller (the first
    run compiles its C code)."""

    def __init__(self, table: CableTable, rt_priority: int = 0, start_timeout_s: float = 120.0):
        if not isinstance(table, CableTable):
            raise InputError(f"GrasperHost: table is a {type(table).__name__}; expected a [cable] CableTable")
        self.table, self.arm = table, table.arm
        self._prio, self._start_timeout = int(rt_priority), float(start_timeout_s)
        self._shm = shared_memory.SharedMemory(create=True, size=GrasperBlock.nbytes())
        self._blk = GrasperBlock(self._shm.buf)
        self._ctl_words = memoryview(self._blk.ctl.reshape(1).view(np.int64))
        names = self._blk.ctl.dtype.names
        self._TICKS, self._FAULTED, self._READY = names.index("ticks"), names.index("faulted"), names.index("ready")
        C = self._blk.command_layout
        self._cmd = np.zeros(C.size)
        self._cmd_mv = memoryview(self._cmd)
        self._SEQ, self._JAW, self._CLEAR, self._HOLD = C.seq, C.jaw, C.clear_seq, C.hold
        S = self._S = self._blk.state_layout
        self._state = np.zeros(S.size)
        self._state_mv = memoryview(self._state)
        self._rec_idx = [getattr(S, f) for f in RECORD_FIELDS]
        self._proc: Optional[subprocess.Popen] = None
        self._latched: Optional[str] = None
        self.commands = self.rejected = 0
        self._jaw = 0.0
        self._alive = False
        self._starting = False

    # --- life -------------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the grasper process and wait until its controller is built (InputError if it
        does not start)."""
        self._spawn()
        end = time.monotonic() + self._start_timeout
        while int(self._blk.ctl["ready"]) == 0:
            code = self._proc.poll()
            if code is not None or time.monotonic() > end:
                self._stop_child()
                raise InputError(f"the grasper process did not start (exit code {code}); see its error above, or "
                                 "remove the [cable] table to run without the grasper controller")
            time.sleep(0.005)
        self._ready()

    def _spawn(self) -> None:
        """Start the child on a zeroed block (without waiting for it: ``_ready`` once it is)."""
        if self._proc is not None and self._proc.poll() is None:
            raise InputError("GrasperHost.start: the grasper process is already running")
        if self._blk is None:
            raise InputError("GrasperHost.start: the grasper host is closed")
        self._blk.raw[:] = 0
        self._cmd[:] = 0.0
        table = json.dumps({f.name: getattr(self.table, f.name) for f in dataclasses.fields(self.table)})
        self._proc = subprocess.Popen([sys.executable, "-m", "pointfence.service.cable_grasper_child", self._shm.name,
                                       table, str(os.getpid()), str(self._prio)], stdin=subprocess.DEVNULL)
        self._starting = True

    def _ready(self) -> None:
        """The child has built its controller: the watchdog starts, the latched fault is gone."""
        self._starting = False
        self._ticks, self._ticks_at = -1, time.monotonic()
        self._alive = True
        self._latched = None

    def close(self) -> None:
        """Stop the child (the motor unpowered) and free the shared memory. Idempotent."""
        self._stop_child()
        if self._shm is not None:
            self._blk = None
            self._ctl_words = None
            try:
                self._shm.close()
                self._shm.unlink()
            except (FileNotFoundError, BufferError):
                pass
            self._shm = None
        self._alive = False

    def _stop_child(self) -> None:
        proc = self._proc
        if proc is None:
            return
        stop_by_flag(proc, self._blk.ctl if self._blk is not None else None)
        self._proc = None

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    # --- the haptic tick's side -------------------------------------------------------------------
    def command(self, jaw_rad: float) -> None:
        """The jaw angle the master asks for (rad); once per haptic tick; never waits, allocates
        no array. Then the watchdog: a child without a tick for ``watchdog_s`` latches a fault."""
        if self._ctl_words is None:
            return
        if math.isfinite(jaw_rad):
            self._jaw = jaw_rad
            self.commands += 1
            cmd = self._cmd
            cmd[self._SEQ] = self.commands
            cmd[self._JAW] = jaw_rad
            self._blk.cmd.write(self._cmd_mv)
        else:
            self.rejected += 1
        self.watch()

    def watch(self) -> None:
        """The watchdog alone (``command`` runs it): latch a fault if the child has not ticked for
        ``watchdog_s`` or has ended."""
        if self._ctl_words is None:
            return
        if self._starting:                          # (a restart after a clear: the fault stays until it is up)
            if self._ctl_words[self._READY]:
                self._ready()
            elif self._proc.poll() is not None:
                self._starting = False
                self._latched = f"{LOST}: the restarted process ended (exit code {self._proc.returncode})"
            return
        if self._latched is not None:
            return
        now = time.monotonic()
        ticks = self._ctl_words[self._TICKS]
        if ticks != self._ticks:
            self._ticks, self._ticks_at = ticks, now
        silent = now - self._ticks_at
        if silent > self.table.watchdog_s:        # (dead, stopped or starved: S9)
            ended = self._proc is None or self._proc.poll() is not None
            self._alive = False
            self._lost(f"no tick for {silent * 1e3:.0f} ms (process {'ended' if ended else 'alive'})")

    def _lost(self, why: str) -> None:
        self._latched = f"{LOST}: {why}"
        self._cmd[self._HOLD] = 1.0                # a stopped child that resumes holds: zero torque
        self._blk.cmd.write(self._cmd_mv)

    @property
    def faulted(self) -> bool:
        """A latched grasper fault (the child's or the watchdog's): zero grasper torque."""
        return self._latched is not None or (self._ctl_words is not None and self._ctl_words[self._FAULTED] != 0)

    @property
    def fault_reason(self) -> Optional[str]:
        if self._latched is not None:
            return self._latched
        if self._blk is not None and self._ctl_words[self._FAULTED]:
            return get_text(self._blk.text[FAULT_TEXT]) or "grasper controller fault"
        return None

    # --- operator -----------------------------------------------------------------------------------
    def clear_fault(self) -> None:
        """Clear the latched fault (``Service.clear_faults``, between two ticks: it never waits).
        A dead grasper process is started again (the fault, "restarting", stays until it is up:
        ``watch``); a live one restarts its estimator on the encoder, the jaw setpoint at the jaw
        (it then ramps to the command: no jump). A cause that persists faults again."""
        if self._blk is None:
            raise InputError("clear_fault: the grasper host is closed")
        if self._starting:
            return
        if self._proc is None or self._proc.poll() is not None:
            self._stop_child()
            self._spawn()
            self._latched = f"{LOST}: restarting the grasper process (faults cleared)"
            return
        self._ticks_at = time.monotonic()
        self._latched = None
        self._alive = True
        self._cmd[self._HOLD] = 0.0
        self._cmd[self._CLEAR] += 1.0
        self._blk.cmd.write(self._cmd_mv)

    def inject(self, kind: str) -> None:
        """Inject a fault (tests, fault-injection runs): ``"nan"``: the encoder reads NaN;
        ``"stall"``: the process is stopped (SIGSTOP); ``"kill"``: killed (SIGKILL); ``"none"``:
        NaN off, a stopped process continues (SIGCONT)."""
        if kind not in FAULT_KINDS:
            raise InputError(f"inject: kind {kind!r}; expected one of {', '.join(FAULT_KINDS)}")
        if self._blk is None or self._proc is None:
            raise InputError("inject: the grasper process is not running (start() it first)")
        if kind in ("nan", "none"):
            self._blk.ctl["inject"] = INJECT_NAN if kind == "nan" else INJECT_NONE
        if self._proc.poll() is None:
            sig = {"stall": signal.SIGSTOP, "kill": signal.SIGKILL, "none": signal.SIGCONT}.get(kind)
            if sig is not None:
                os.kill(self._proc.pid, sig)
        if kind == "kill":
            self._proc.wait(timeout=5.0)

    # --- reading (status, metrics, recording) ---------------------------------------------------------
    def _read(self) -> bool:
        return self._blk is not None and self._blk.state.read(self._state_mv)

    def copy_into(self, row: np.ndarray) -> None:
        """The recorded values (``RECORD_FIELDS``) of the child's latest tick into ``row`` (at
        least ``len(RECORD_FIELDS)`` floats); NaN where the record did not read. No allocation."""
        if self._read():
            s = self._state
            for j, i in enumerate(self._rec_idx):
                row[j] = s[i]
            if self._latched is not None:
                row[_FAULT_AT] = LOST_CODE
        else:
            row[: len(RECORD_FIELDS)] = math.nan

    def snapshot(self) -> GrasperSnapshot:
        """The grasper's state for the status (any thread but the tick's hot path: it allocates)."""
        self._read()
        s, S = self._state, self._S
        fault = self.fault_reason
        alerts = []
        alert = get_text(self._blk.text[ALERT_TEXT]) if self._blk is not None and s[S.tension_alert] else None
        if fault:
            alerts.append(f"FAULT: {fault}; grasper torque is zero until faults are cleared")
        if s[S.degraded]:
            alerts.append("DEGRADED: the grasper's UKF/MPC run in CasADi's interpreter (no C compiler: POINTFENCE_CC)")
        if alert:
            alerts.append(alert)
        if s[S.misses]:
            alerts.append(f"{int(s[S.misses])} of {int(s[S.periods])} grasper control periods missed their 1 ms deadline")
        ended = self._proc is None or self._proc.poll() is not None
        tension = float(s[S.tension_g])
        return GrasperSnapshot(
            arm=self.arm, running=self._alive and not ended, ticks=int(s[S.ticks]), periods=int(s[S.periods]),
            deadline_misses=int(s[S.misses]), commands=self.commands, rejected=self.rejected,
            jaw_command=self._jaw, setpoint=float(s[S.setpoint]), jaw=float(s[S.jaw]),
            jaw_velocity=float(s[S.jaw_velocity]),
            motor_torque=0.0 if ended else float(s[S.motor_torque]),   # (an ended process drives nothing)
            link_torque=float(s[S.link_torque]), k_e=float(s[S.k_e]),
            tension_g=tension if math.isfinite(tension) else None, alerts=tuple(alerts), fault=fault,
            late_ms=float(s[S.late]) * 1e3, late_max_ms=float(s[S.late_max]) * 1e3,
            compute_us=float(s[S.compute]) * 1e6, compute_max_us=float(s[S.compute_max]) * 1e6,
            degraded=bool(s[S.degraded]), sim_jaw=float(s[S.true_jaw]) if self.table.plant == "sim" else None)

    @property
    def pid(self) -> Optional[int]:
        return self._proc.pid if self._proc is not None else None


__all__ = ["GrasperHost", "GrasperSnapshot", "RECORD_FIELDS", "LOST", "FAULT_KINDS"]
