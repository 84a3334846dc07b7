"""Clocks for the haptic loop: the real monotonic clock and a fake one for deterministic tests.

The loop asks a clock for ``now()`` (seconds, monotonic) and ``sleep_until(t)``, which returns
the reading at which it saw ``t`` pass (the tick's start: service/periodic.py). ``RealClock``
sleeps with ``time.sleep`` until ``spin_s`` before the deadline and spins on
``time.perf_counter`` for the rest. The default is no spin: a spinning Python thread holds the
interpreter lock, every other thread of the service (frame ingest, camera readers, UDP) forces
it to hand the lock over, and the loop then waits to get it back at its deadline (measured:
lateness p99 4.7 ms spinning 0.4 ms, 0.4 ms not spinning, with a frame build running; a
SCHED_FIFO loop thread wakes within tens of microseconds from ``time.sleep``); with
``spin_yield`` the spin calls ``time.sleep(0)`` each turn, handing the lock to any thread that
wants it (the cable controller's choice, ``cable/controller.py``). ``FakeClock``
never sleeps: ``sleep_until`` jumps to the deadline and ``advance(dt)`` lets a test (or a
simulated slow component) make time pass inside a tick, so deadline accounting can be checked
exactly.
"""
from __future__ import annotations

import time


class RealClock:
    """``time.perf_counter``; ``sleep_until`` sleeps, then spins for the last ``spin_s`` seconds
    (yielding the interpreter lock each turn with ``spin_yield``)."""

    simulated = False

    def __init__(self, spin_s: float = 0.00006, spin_yield: bool = False):
        self.spin_s = float(spin_s)
        self.spin_yield = bool(spin_yield)

    @staticmethod
    def now() -> float:
        return time.perf_counter()

    def sleep_until(self, t: float) -> float:
        """Return at ``t`` or later: the clock reading (s) at which the wait saw ``t`` pass."""
        pc = time.perf_counter
        rest = t - pc() - self.spin_s
        if rest > 0:
            time.sleep(rest)
        if self.spin_yield:
            while (now := pc()) < t:
                time.sleep(0)
        else:
            while (now := pc()) < t:
                pass
        return now


class FakeClock:
    """A clock that only moves when told: ``sleep_until`` jumps forward, ``advance`` adds time."""

    simulated = True

    def __init__(self, t0: float = 0.0):
        self.t = float(t0)

    def now(self) -> float:
        return self.t

    def sleep_until(self, t: float) -> float:
        if t > self.t:
            self.t = float(t)
        return self.t

    def advance(self, dt: float) -> None:
        self.t += float(dt)
