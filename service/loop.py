"""The 1 kHz haptic loop: absolute-deadline scheduling, per-tick timing, deadline misses.

The schedule is a ``periodic.PeriodicLoop`` (its docstring has the one policy every loop of
pointfence follows): tick k is due at ``t0 + k * period`` (absolute deadlines: no drift however
long the ticks take); the loop sleeps until the deadline (``clock.sleep_until``), runs
``target.tick`` and measures, into preallocated ring buffers, the tick's lateness (start -
deadline) and compute time (end - start). A tick that ends after its period is a deadline miss;
if the loop falls whole periods behind, those periods are skipped (not run in a burst), counted
as misses, and the next tick advances the simulation by the elapsed time (``dt`` = periods x
period). A tick that starts more than ``max_lateness_s`` late is an overrun: the target is told,
and goes into its degraded mode (force ramps to zero, robot holds). This module adds what is the
haptic loop's own: the target's error handling, the tick watchdog, the interpreter lock's switch
interval, the frame threads' gate and the loop thread's scheduling.

A tick that stalls (a hung kernel call) is seen from outside: running in its own thread, the
loop starts a ``watchdog.TickWatchdog`` (limit ``watchdog_s``, default ``max_lateness_s``) that
calls the target's ``on_stall(started, now)`` while the stall goes on (SAFETY.md S9).

The loop never stops silently: an exception escaping ``target.tick`` is counted and kept in
``error``; from then on the loop runs ``target.safe_tick`` (forces ramp down, robots hold)
until ``clear_error()``, so a broken tick cannot leave forces applied or a robot moving. Only
``stop()`` ends the loop.

``target`` provides ``tick(k, t, dt, overrun, now)`` and ``safe_tick(k, t, dt, now)``; ``t`` is
loop time (``k * period``, exact) and ``now`` the clock reading at the tick's start.

The interpreter lock. The service's other threads (frame ingest, camera readers, UDP, control
API) run Python too. Running in its own thread, the loop keeps the lock for a whole tick: the
switch interval is ``tick_switch_s`` (5 ms) while a tick runs, so no other thread can force it
out mid-tick (with 0.1 ms, a 0.6 ms tick was cut into slices and took up to 1.4 ms), and
``switch_interval_s`` (0.1 ms) while it sleeps, so that at its deadline the thread holding the
lock hands it back within 0.1 ms. A tick that blocks (a socket call, a GPU wait) hands the lock
over and may wait up to ``tick_switch_s`` to get it back; PoCL's in-thread proxy launch makes no
blocking call. ``SCHED_FIFO`` (``rt_priority``) makes the thread wake on time;
the loop cannot make a thread that holds the lock run, which is why the service lowers the
priority of the OpenCL worker threads instead (``kernels/opencl/context.lower_pool_priority``).
A thread that was forced out at the loop's wake-up waits for the lock with the 0.1 ms it found
and forces the tick out in turn; so while the loop runs in its own thread it also installs a
``kernels.yielding.Gate`` (``cooperate``): the frame threads' long Python work (self-filter,
build enqueues) checks it between steps and sleeps through the ticks instead.
"""
from __future__ import annotations

import os
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Optional

import numpy as np

from pointfence.kernels import yielding

from .clock import RealClock
from .osthread import name_this_thread
from .periodic import RING, PeriodicLoop


@dataclass(frozen=True)
class LoopTiming:
    """Timing of the ticks so far (the last ``RING`` ticks for the percentiles), microseconds."""

    ticks: int
    periods: int
    misses: int
    overruns: int
    compute_us_p50: float
    compute_us_p99: float
    compute_us_max: float
    late_us_p50: float
    late_us_p99: float
    late_us_max: float
    #: ticks that ended past the end of the period they were due in (they ran long, started
    #: late, or both): each accounts for one or more of ``misses`` (a 100 ms stall of the whole
    #: machine is 100 missed periods but one or two missed ticks)
    missed_ticks: int = 0

    @property
    def miss_ratio(self) -> float:
        return self.misses / self.periods if self.periods else 0.0

    def as_dict(self) -> dict:
        d = {k: (round(v, 2) if isinstance(v, float) else v) for k, v in self.__dict__.items()}
        d["miss_ratio"] = round(self.miss_ratio, 6)
        return d


class HapticLoop:
    """Runs ``target``'s ticks at ``rate_hz`` on ``clock`` (see the module docstring).

    The schedule and its accounting are ``periodic`` (a ``PeriodicLoop``); ``period``, ``t0``,
    ``k`` (the next period), ``ticks``, ``misses``, ``overruns`` and the ``late`` and ``compute``
    rings (s) are its. ``tick_us`` (a ring, us) is each tick's wall-clock time
    (``time.perf_counter``, whatever the clock: on a ``FakeClock`` the rings hold simulated time).
    """

    def __init__(self, target, clock=None, rate_hz: float = 1000.0, max_lateness_s: float = 0.003,
                 switch_interval_s: Optional[float] = 0.0001, rt_priority: int = 0,
                 tick_switch_s: float = 0.005, cooperate: bool = True, watchdog_s: Optional[float] = None):
        self.target = target
        self.clock = clock if clock is not None else RealClock()
        self.max_lateness = float(max_lateness_s)
        self.periodic = PeriodicLoop(1.0 / float(rate_hz), self.clock, max_lateness_s=self.max_lateness)
        self.period = self.periodic.period
        self.switch_interval_s = switch_interval_s
        self.tick_switch_s = float(tick_switch_s)
        self.cooperate = bool(cooperate)
        #: the frame threads' gate while the loop runs in its own thread (None otherwise)
        self.gate: Optional[yielding.Gate] = None
        self._threaded = False
        self.tick_us = np.zeros(RING)   # wall-clock compute (perf_counter), whatever the clock
        self.error: Optional[str] = None
        self.errors = 0
        self._thread: Optional[threading.Thread] = None
        #: set when the loop's thread ends (stopped, or died): what another thread waits on
        #: instead of polling ``running`` (each poll takes the interpreter lock the ticks need)
        self.finished = threading.Event()
        self._saved_switch = None
        self._note = getattr(target, "note_tick_us", None)
        self.rt_priority = int(rt_priority)
        self.scheduling = "normal"
        #: loop clock reading at the start of the running tick (None between ticks): the watchdog's view
        self.tick_started: Optional[float] = None
        self.watchdog_s = self.max_lateness if watchdog_s is None else float(watchdog_s)
        self.watchdog = None

    # --- the schedule's accounting (PeriodicLoop's) ---------------------------------------------
    @property
    def t0(self) -> Optional[float]:
        return self.periodic.t0

    @property
    def k(self) -> int:
        """Index of the next period."""
        return self.periodic.k

    @property
    def ticks(self) -> int:
        return self.periodic.ticks

    @property
    def misses(self) -> int:
        return self.periodic.misses

    @property
    def overruns(self) -> int:
        return self.periodic.overruns

    @property
    def compute(self) -> np.ndarray:
        return self.periodic.compute

    @property
    def late(self) -> np.ndarray:
        return self.periodic.late

    # --- one tick ---------------------------------------------------------------------------------
    def run_ticks(self, n: int) -> None:
        """Run ``n`` ticks in the calling thread (tests, replays on a simulated clock)."""
        for _ in range(int(n)):
            self._one()

    def _one(self) -> None:
        sched = self.periodic
        k = sched.begin()
        gate = self.gate
        if gate is not None:
            gate.busy = True
        if self._threaded:
            sys.setswitchinterval(self.tick_switch_s)
        w0 = time.perf_counter()
        start, dt, P = sched.started, sched.dt, self.period
        self.tick_started = start
        try:
            if self.error is None:
                self.target.tick(k, k * P, dt, sched.overrun, start)
            else:
                self.target.safe_tick(k, k * P, dt, start)
        except Exception as e:  # surfaced in status(); the next ticks run safe_tick
            self.errors += 1
            self.error = f"tick {k}: {type(e).__name__}: {e}"
            self.error_trace = traceback.format_exc()
            try:
                self.target.safe_tick(k, k * P, dt, start)
            except Exception as e2:
                self.error += f"; safe_tick failed too: {type(e2).__name__}: {e2}"
        self.tick_started = None
        i = sched.ticks & (RING - 1)
        sched.end()
        if self._threaded:
            sys.setswitchinterval(self.switch_interval_s)
        us = (time.perf_counter() - w0) * 1e6
        self.tick_us[i] = us
        if self._note is not None:
            self._note(us)
        if gate is not None:
            gate.next_due = sched.deadline(sched.k)
            gate.busy = False

    def clear_error(self) -> None:
        self.error = None

    # --- thread -------------------------------------------------------------------------------------
    def start(self) -> None:
        """Run the loop in its own thread until ``stop()``."""
        if self._thread is not None:
            return
        self.periodic.rearm()
        if self.switch_interval_s:
            self._saved_switch = sys.getswitchinterval()
            sys.setswitchinterval(self.switch_interval_s)  # the loop waits less for the GIL
            self._threaded = True
        if self.cooperate:
            self.gate = yielding.Gate(now=self.clock.now)
            yielding.install(self.gate)
        self.finished.clear()
        self._thread = threading.Thread(target=self._run, name="pointfence-haptic-loop", daemon=True)
        self._thread.start()
        if self.watchdog_s > 0 and hasattr(self.target, "on_stall"):
            from .watchdog import TickWatchdog

            self.watchdog = TickWatchdog(self, self.target, self.watchdog_s, rt_priority=self.rt_priority)
            self.watchdog.start()

    def _run(self) -> None:
        name_this_thread("pf-haptic-loop")
        if self.gate is not None:
            self.gate.owner = threading.get_ident()
        if self.rt_priority > 0:   # SCHED_FIFO for this thread only, where the OS allows it
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.rt_priority))
                self.scheduling = f"SCHED_FIFO {self.rt_priority}"
            except (AttributeError, OSError) as e:
                self.scheduling = f"normal (SCHED_FIFO refused: {e})"
        try:
            while not self.periodic.stopping:
                self._one()
        finally:
            self.finished.set()

    def stop(self) -> None:
        if self.watchdog is not None:
            self.watchdog.stop()
            self.watchdog = None
        self.periodic.stop()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._threaded = False
        if self.gate is not None:
            if yielding.installed() is self.gate:
                yielding.install(None)
            self.gate = None
        if self._saved_switch is not None:
            sys.setswitchinterval(self._saved_switch)
            self._saved_switch = None

    @property
    def thread_id(self) -> Optional[int]:
        """The loop thread's id as the kernel knows it (None while no thread runs)."""
        th = self._thread
        return None if th is None else th.native_id

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # --- results ------------------------------------------------------------------------------------
    def mark(self) -> tuple:
        """A point to measure from (``timing(since=mark)``), e.g. after a warm-up."""
        return (self.ticks, self.k, self.misses, self.overruns)

    def timing(self, since: tuple = (0, 0, 0, 0)) -> LoopTiming:
        t0, k0, m0, o0 = since
        late, comp = self.periodic.recent(t0)
        if late.size == 0:
            return LoopTiming(0, 0, 0, 0, *([0.0] * 6))
        missed = int(np.count_nonzero(late + comp > self.period))
        c = comp * 1e6
        lt = late * 1e6
        p = np.percentile
        return LoopTiming(self.ticks - t0, self.k - k0, self.misses - m0, self.overruns - o0,
                          float(p(c, 50)), float(p(c, 99)), float(c.max()),
                          float(p(lt, 50)), float(p(lt, 99)), float(lt.max()), missed)
