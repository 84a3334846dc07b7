"""Snapshot builds that yield to the haptic loop but never starve.

PoCL's worker pool builds the snapshots under SCHED_IDLE by default (``[service] build_idle``):
it then runs only on cores no other thread wants, and never preempts the loop or a thread that
holds the interpreter lock (kernels/opencl/context.py). On a machine whose cores other work keeps
busy (ROS 2 equipment beside the service, a test suite, another guest's load) that pool gets no
time at all: a build that took 15 ms takes seconds, the snapshots age past ``max_frame_age_s``
and the arms hold (S2) for as long as the load lasts (bench/HISTORY.md, the ros2 section: 221 of
297 frames never reached a snapshot).

``BuildWatch`` watches the build in progress from a thread of its own. A build running longer
than ``starve_s`` (in a live run the cameras' frame period, or a quarter of ``max_frame_age_s``
where that is sooner: a longer build loses frames, and the fixtures are then still fresh) puts
the pool back under the normal scheduler (``raise_pool``); after at least ``hold_s``
there, once ``calm_builds`` builds in a row took less than ``calm_s``, the pool goes back to
SCHED_IDLE (``idle_pool``). A pool that starves again soon after (within twice its last hold)
is held twice as long the next time, up to ``max_hold_s``: under lasting load it stays raised,
and the loop gets its idle cores back once the load is gone. Both callables are given (the OpenCL context's functions in the service), so
the policy is tested on its own; ``status()`` says where the pool is and how often it was raised.
"""
from __future__ import annotations

import threading
import time
from typing import Callable, Optional

from .osthread import name_this_thread


class BuildWatch:
    """See the module docstring. ``frames``: the live feed (``build_started``: monotonic time
    the running build began, None between builds; ``ingest_ms``: durations of the builds so
    far, ms). ``raise_pool()`` / ``idle_pool()``: move the pool; each returns whether it took."""

    def __init__(self, frames, raise_pool: Callable[[], bool], idle_pool: Callable[[], bool], starve_s: float,
                 calm_s: Optional[float] = None, calm_builds: int = 10, poll_s: float = 0.02,
                 hold_s: float = 2.0, max_hold_s: float = 60.0):
        if not starve_s > 0:
            raise ValueError(f"starve_s = {starve_s!r}; expected seconds > 0")
        self.frames = frames
        self._raise, self._idle = raise_pool, idle_pool
        self.starve_s = float(starve_s)
        self.calm_s = self.starve_s / 3 if calm_s is None else float(calm_s)
        self.calm_builds = int(calm_builds)
        self.poll_s = float(poll_s)
        self.base_hold_s, self.max_hold_s = float(hold_s), float(max_hold_s)
        self.hold_s = self.base_hold_s   # how long the pool stays raised at least, this time
        self._raised_at = self._lowered_at = -float("inf")
        self.idle = True            # where the pool is (it starts under SCHED_IDLE)
        self.raised = 0             # times it was put back under the normal scheduler
        self.refused = 0            # moves the OS refused
        self._builds_at_raise = 0
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def check(self, now: float) -> None:
        """One look at the builds at monotonic time ``now`` (the thread calls it every ``poll_s``)."""
        started = self.frames.build_started
        if self.idle:
            if started is not None and now - started > self.starve_s:
                if self._raise():
                    again = now - self._lowered_at < 2 * self.hold_s
                    self.hold_s = min(2 * self.hold_s, self.max_hold_s) if again else self.base_hold_s
                    self.idle = False
                    self.raised += 1
                    self._raised_at = now
                    self._builds_at_raise = len(self.frames.ingest_ms)
                else:
                    self.refused += 1
            return
        done = self.frames.ingest_ms
        recent = done[-self.calm_builds:]
        if (now - self._raised_at >= self.hold_s and len(done) - self._builds_at_raise >= self.calm_builds
                and len(recent) == self.calm_builds and max(recent) < 1e3 * self.calm_s
                and (started is None or now - started < self.calm_s)):
            if self._idle():
                self.idle = True
                self._lowered_at = now
            else:
                self.refused += 1

    def start(self) -> "BuildWatch":
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="pointfence-build-watch", daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        name_this_thread("pf-build-watch")
        while not self._stop.wait(self.poll_s):
            self.check(time.monotonic())

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)

    def status(self) -> dict:
        return {"pool": "SCHED_IDLE" if self.idle else "normal (builds were starving)", "raised": self.raised,
                "refused": self.refused, "starve_ms": round(1e3 * self.starve_s, 1), "hold_s": self.hold_s}
