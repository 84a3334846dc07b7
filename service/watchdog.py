"""The tick watchdog: a stalled haptic tick (a hung kernel call, a blocked driver) is seen from
outside the tick within a bounded time, and the target is told while the stall goes on
(SAFETY.md S9).

``TickWatchdog`` runs in its own thread beside a threaded ``loop.HapticLoop``. The loop marks
each tick's start (``HapticLoop.tick_started``, the loop clock's reading; None between ticks).
Every ``poll_s`` (default ``limit_s``) the watchdog looks: a tick that started more than ``limit_s`` ago and has not
ended is a stall; the target's ``on_stall(started, now)`` is called once per stalled tick (the
service zeroes the masters' forces at once and latches a fault that holds every arm when the
tick returns). A stall is therefore seen at most ``limit_s + poll_s`` after the tick started.
The watchdog needs Python's interpreter lock to run: a stall inside a call that keeps the
lock (no I/O, no wait) is seen when that call returns; device waits, sockets and sleeps give it
up. With ``rt_priority`` (the loop's, where the loop runs SCHED_FIFO) it runs SCHED_FIFO too: at
normal priority on a loaded machine it waited for a core for tens of milliseconds, and, preempted
while it held the interpreter lock, kept the loop waiting for as long.
"""
from __future__ import annotations

import threading
from typing import Optional

from .osthread import name_this_thread, set_fifo


class TickWatchdog:
    """Watches ``loop`` (a ``HapticLoop``) and tells ``target.on_stall`` of a stalled tick.

    Args:
        loop: the loop whose ``tick_started`` and ``clock`` are read.
        target: has ``on_stall(started, now)`` (loop clock, s).
        limit_s: a tick running longer than this is a stall (s).
        poll_s: how often the watchdog looks (s; default ``limit_s``: every wake-up takes the
            interpreter lock the loop wants, so the watchdog looks no more often than it must).
        rt_priority: SCHED_FIFO priority of the watchdog's thread where the OS allows it (0:
            normal); ``scheduling`` says what applied once the thread runs.
    """

    def __init__(self, loop, target, limit_s: float, poll_s: Optional[float] = None, rt_priority: int = 0):
        poll_s = limit_s if poll_s is None else poll_s
        if not (limit_s > 0 and poll_s > 0):
            raise ValueError(f"watchdog limit_s = {limit_s!r}, poll_s = {poll_s!r}; expected both > 0 s")
        self.loop = loop
        self.target = target
        self.limit_s = float(limit_s)
        self.poll_s = float(poll_s)
        self.rt_priority = int(rt_priority)
        self.scheduling = "normal"
        self.trips = 0
        self.last_stall_s = 0.0      # how long the last stalled tick had run when it was seen
        self._seen: Optional[float] = None
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def start(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="pointfence-watchdog", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def check(self) -> bool:
        """One look (the thread's body; tests call it directly): True if it saw a new stall."""
        started = self.loop.tick_started
        if started is None or started == self._seen:
            return False
        now = self.loop.clock.now()
        if now - started <= self.limit_s:
            return False
        self._seen = started
        self.trips += 1
        self.last_stall_s = now - started
        self.target.on_stall(started, now)
        return True

    def _run(self) -> None:
        name_this_thread("pf-watchdog")
        self.scheduling = set_fifo(threading.get_native_id(), self.rt_priority)
        while not self._stop.wait(self.poll_s):
            self.check()
