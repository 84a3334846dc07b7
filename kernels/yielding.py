"""Background Python work that steps aside for a real-time thread of the same process.

Python runs one thread at a time (the interpreter lock). When the haptic loop wakes up, or
gives the lock up for an instant during its tick, a frame thread in the middle of Python work
(the robot self-filter, the enqueues of a snapshot build) takes it, and the loop waits until the
interpreter forces a switch: up to the switch interval, and a tick waits for the interval set
at the start of the other thread's wait. On a 2-core VM with four Raven II tools, 92-99 % of the
loop's deadline misses fell while a frame was being ingested (bench/HISTORY.md, issue 5).

Long Python work on a frame thread therefore calls ``checkpoint()`` between its steps (every
capsule of the self-filter, every stage of a build). While a ``Gate`` is installed (the live
haptic loop installs its own), a checkpoint reached while a tick runs, or less than
``guard_s`` before the next one is due (0.3 ms: time for one step to finish first; 0.15 ms
left the loop's lateness p99 at 120-150 us instead of 10-60), sleeps (without the lock) until
the tick is over, for at most ``max_wait_s``: the frame thread then spends its Python time in
the loop's idle part of each period instead of inside the ticks. A checkpoint in the loop's own thread, or with no
gate installed (offline runs, tests, other programs), returns at once.
"""
from __future__ import annotations

import threading
import time

_gate = None


class Gate:
    """When background work may run: ``busy`` while a tick runs, ``next_due`` the next tick's
    start (seconds on ``now``'s clock), ``owner`` the real-time thread's ident (its own
    checkpoints never wait). Counts the waits (``waits``) and their total time (``waited_s``)."""

    def __init__(self, now=time.perf_counter, guard_s: float = 300e-6, max_wait_s: float = 0.002,
                 poll_s: float = 50e-6):
        self.now = now
        self.guard_s = float(guard_s)
        self.max_wait_s = float(max_wait_s)
        self.poll_s = float(poll_s)
        self.busy = False
        self.next_due = float("inf")   # no tick scheduled yet
        self.owner = None
        self.waits = 0
        self.waited_s = 0.0

    def blocked(self) -> bool:
        return self.busy or self.next_due - self.now() < self.guard_s

    def wait(self) -> None:
        if threading.get_ident() == self.owner or not self.blocked():
            return
        t0 = time.perf_counter()
        end = t0 + self.max_wait_s
        while self.blocked() and time.perf_counter() < end:
            time.sleep(self.poll_s)
        self.waits += 1
        self.waited_s += time.perf_counter() - t0


def install(gate: Gate | None) -> None:
    """Make ``gate`` the process's gate (None: checkpoints never wait)."""
    global _gate
    _gate = gate


def installed() -> Gate | None:
    return _gate


def checkpoint() -> None:
    """A point where background work may step aside for the real-time thread (see the module)."""
    g = _gate
    if g is not None:
        g.wait()
