"""A periodic loop on absolute deadlines: the schedule every 1 kHz loop of pointfence runs on.

Three loops use it: the haptic loop (``loop.HapticLoop``), the simulated arms' own process
(``robot/hosted.py``) and the cable controller (``cable/controller.py``). Each tick is
``begin()`` (sleep until the deadline, then account for it), the caller's work, ``end()``
(account for the work); ``run(body)`` does that until ``stop()``.

Schedule. Period ``k`` is due at ``t0 + k * period`` on ``clock`` (``t0``: the clock's reading at
the first ``begin()``). Deadlines are absolute, so however long the ticks take the schedule never
drifts.

Missed periods (the one policy). A tick that starts ``late`` seconds after its deadline with
``late >= period`` has lost ``floor(late / period)`` whole periods: they are skipped, not run in
a burst to catch up, and each counts as a miss; the tick runs as period ``k`` = the last one whose
deadline has passed. ``dt`` of a tick is the time its work must account for: the periods since
the previous tick's period (``elapsed`` of them, ``dt = elapsed * period``; one period for the
first tick). A tick whose work ends after its own period ends (``end > t0 + (k + 1) * period``)
is a miss too. ``periods`` (= ``k`` after the last tick) counts the periods so far, run or
skipped: ``misses / periods`` is the miss ratio.

Lateness and overruns. ``late`` is the tick's start minus the deadline of the period it was due
to run (before any skip). The start is the clock reading at which the wait saw the deadline
pass (what ``sleep_until`` returns; a clock that returns None: a reading after it): a wake-up
delayed by the machine, or a wait for the interpreter lock, is lateness; the Python between the
wait's return and the tick's first line is the tick's own time (``compute``). A tick with
``late > max_lateness_s`` is an overrun (``overrun`` is True during it and ``overruns`` counts
them). The last ``ring`` ticks' lateness, compute time (``end - start``) and start, seconds, are
kept in ``late``, ``compute`` and ``starts`` (tick ``i`` at ``i % ring``), preallocated: a tick
allocates nothing.

The clock gives ``now()`` and ``sleep_until(t)`` (``clock.RealClock``, or ``clock.FakeClock``
for deterministic tests: there time moves only by ``advance`` and ``sleep_until``).
"""
from __future__ import annotations

import threading
from typing import Callable, Optional

import numpy as np

from pointfence.kernels.errors import InputError

from .clock import RealClock

#: ticks kept for the lateness and compute percentiles (a power of two)
RING = 1 << 16


class PeriodicLoop:
    """Ticks every ``period_s`` seconds on ``clock`` (see the module docstring).

    Args:
        period_s: the period (s), finite and > 0.
        clock: ``now()`` and ``sleep_until(t)`` (s); default ``RealClock()``.
        max_lateness_s: a tick starting later than this after its deadline is an overrun (s;
            None: never).
        ring: how many ticks' lateness and compute time are kept (a power of two).

    After ``begin()`` returns, these describe the running tick: ``tick_k`` (its period index),
    ``dt`` (s), ``elapsed`` (periods since the previous tick), ``started`` (clock, s), ``late``
    (s), ``overrun``.
    """

    def __init__(self, period_s: float, clock=None, max_lateness_s: Optional[float] = None, ring: int = RING):
        period_s = float(period_s)
        if not (0.0 < period_s < float("inf")):
            raise InputError(f"PeriodicLoop: period_s = {period_s!r}; expected a finite period > 0 s")
        if ring < 1 or ring & (ring - 1):
            raise InputError(f"PeriodicLoop: ring = {ring!r}; expected a power of two >= 1")
        self.period = period_s
        self.clock = clock if clock is not None else RealClock()
        self.max_lateness = float("inf") if max_lateness_s is None else float(max_lateness_s)
        self.ring = int(ring)
        self.compute = np.zeros(self.ring)   # s, end - start of each tick
        self.late = np.zeros(self.ring)      # s, start - deadline of each tick
        self.starts = np.zeros(self.ring)    # s, each tick's start (clock reading)
        self.t0: Optional[float] = None      # clock reading of period 0's deadline
        self.k = 0                           # index of the next period
        self.ticks = 0                       # ticks run
        self.misses = 0                      # periods skipped + ticks that ended past their period
        self.overruns = 0                    # ticks that started more than max_lateness_s late
        # the running tick (set by begin())
        self.tick_k = 0
        self.dt = self.period
        self.elapsed = 1
        self.started = 0.0
        self.late_s = 0.0
        self.overrun = False
        self._k_prev = -1
        self._stop = threading.Event()

    @property
    def periods(self) -> int:
        """Periods so far, run or skipped."""
        return self.k

    def deadline(self, k: int) -> float:
        """Clock time (s) period ``k`` is due (``t0 + k * period``; the first ``begin()`` sets t0)."""
        return (self.t0 if self.t0 is not None else self.clock.now()) + k * self.period

    # --- one tick -------------------------------------------------------------------------------
    def begin(self) -> int:
        """Sleep until the next period's deadline and start its tick: returns the tick's period
        index ``k`` (after skipping the periods already lost); sets ``dt``, ``elapsed``,
        ``started``, ``late_s``, ``overrun``."""
        clock, P = self.clock, self.period
        if self.t0 is None:
            self.t0 = clock.now()
        due = self.t0 + self.k * P
        woke = clock.sleep_until(due)
        start = clock.now() if woke is None else woke
        late = start - due
        if late >= P:                        # whole periods lost: skipped, each a miss
            skip = int(late // P)
            self.misses += skip
            self.k += skip
        k = self.k
        self.elapsed = 1 if self._k_prev < 0 else k - self._k_prev
        self.dt = self.elapsed * P
        self.overrun = late > self.max_lateness
        if self.overrun:
            self.overruns += 1
        self.tick_k, self.started, self.late_s = k, start, late
        return k

    def end(self) -> float:
        """End the tick ``begin()`` started: record its lateness and compute time, count a miss if
        it ended past its period, move on to the next period. Returns the clock reading (s)."""
        end = self.clock.now()
        k = self.tick_k
        i = self.ticks & (self.ring - 1)
        self.compute[i] = end - self.started
        self.late[i] = self.late_s
        self.starts[i] = self.started
        if end > self.t0 + (k + 1) * self.period:
            self.misses += 1
        self.ticks += 1
        self._k_prev = k
        self.k = k + 1
        return end

    # --- a loop -------------------------------------------------------------------------------
    def run(self, body: Callable[[int], None], keep_going: Optional[Callable[[], bool]] = None) -> None:
        """Tick ``body(k)`` (``dt`` etc. on this object) until ``stop()`` is called or
        ``keep_going()`` (checked before each tick) returns False. An exception from ``body``
        ends the tick's accounting and is raised. After a ``stop()``, ``rearm()`` first."""
        stop = self._stop
        while not stop.is_set() and (keep_going is None or keep_going()):
            k = self.begin()
            try:
                body(k)
            finally:
                self.end()

    def stop(self) -> None:
        """End ``run`` after the tick in progress (any thread; also before ``run`` starts)."""
        self._stop.set()

    def rearm(self) -> None:
        """Let ``run`` tick again after a ``stop()`` (call it before starting the thread that runs
        it, so that a ``stop()`` right after the start is never lost)."""
        self._stop.clear()

    @property
    def stopping(self) -> bool:
        """Whether ``stop()`` was called (and not ``rearm()`` since)."""
        return self._stop.is_set()

    # --- results ------------------------------------------------------------------------------
    def recent(self, since_tick: int = 0) -> tuple:
        """(lateness, compute) of the ticks run since tick ``since_tick`` that the rings still
        hold, seconds, oldest first (copies)."""
        lo = max(int(since_tick), self.ticks - self.ring)
        if self.ticks <= lo:
            return np.zeros(0), np.zeros(0)
        idx = np.arange(lo, self.ticks) & (self.ring - 1)
        return self.late[idx], self.compute[idx]

    def recent_starts(self, since_tick: int = 0) -> tuple:
        """(start, lateness) of the same ticks as ``recent``, seconds, oldest first (copies)."""
        lo = max(int(since_tick), self.ticks - self.ring)
        idx = np.arange(lo, max(lo, self.ticks)) & (self.ring - 1)
        return self.starts[idx], self.late[idx]
