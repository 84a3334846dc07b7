"""Feeding camera frames into the frame pipeline's double-buffered snapshots.

Every snapshot is built from the latest frame of EVERY camera: a camera that stalls keeps
contributing its last frame, so its fixtures never vanish. Each camera's age (time since its
latest frame arrived) is watched: beyond ``stale_s`` (default 100 ms) the camera is reported
stale. What the service holds on is ``max_age(now)``: the age of the newest *published*
snapshot, counted from the arrival of its oldest frame (SAFETY.md S2). A stalled camera, an
ingest that fails on every frame, or an ingest thread that died all make it grow, and beyond
``max_age_s`` the arms hold; ``frames_too_old`` tells the first case from the other two.
A failed build (any exception, not only a bad frame) is counted and reported and leaves the
previous snapshot current; a dead ingest thread is reported (``status``) and restarted by
``restart_ingest`` (the service's clear-faults).

* ``PublishGate`` makes a snapshot become visible only between haptic ticks, so each tick knows
  exactly which snapshot (``seq``) its one proxy launch used (recorded for replay).
* ``LiveFrames``: one reader thread per camera (blocking ``source.read`` at the camera's pace)
  and one ingest thread that builds a snapshot whenever some camera delivered a new frame.
* ``SimFrames``: the deterministic offline counterpart for replays and tests: at loop time t a
  camera's frames with (timestamp - first timestamp) <= t have arrived; ingest runs inside the
  tick, before the proxy launch.
* ``ScheduledFrames``: re-creates a recorded run's snapshots exactly (which frames of which
  camera formed the snapshot that became visible at which tick).

Two things tie the loop to the frames' own clock (the clock of the frame timestamps):

* ``frame_time(t, now)``: the tick's time on the frames' clock (None while unknown). SimFrames:
  loop time t plus the first frame's timestamp (a frame arrives at its timestamp); LiveFrames:
  the loop clock's ``now`` minus ``clock_minus_stamp`` (loop clock minus camera 0's clock,
  estimated online from every frame's stamp and arrival: camera_clock.py). Every other camera's
  frames are stamped on camera 0's clock through their own camera's estimated offset and drift
  (sources that share a clock say so with a common ``clock_domain`` and are left as they are), so
  a snapshot's timestamps compare across cameras. Motion prediction (``batch.step(hips, now=frame_time)``) and the
  tool pose ring (``toolpose``) use it.
* ``frame_filter``: an optional callable (``toolpose.ToolFilter``, the robot self-filter) that
  every snapshot's frames go through before ``pipeline.ingest``.
"""
from __future__ import annotations

import math
import os
import threading
import time
from dataclasses import replace
from typing import Optional, Sequence

from pointfence.kernels.backend import run_steps
from pointfence.kernels.errors import PointfenceError
from pointfence.kernels.yielding import checkpoint

from .camera_clock import CameraClock
from .osthread import name_this_thread


def camera_clocks(sources) -> list:
    """One ``CameraClock`` per source; sources that name the same ``clock_domain`` (a string;
    None or absent: a clock of its own) share one."""
    by_domain: dict = {}
    out = []
    for src in sources:
        dom = getattr(src, "clock_domain", None)
        if dom is None:
            out.append(CameraClock())
        else:
            out.append(by_domain.setdefault(dom, CameraClock()))
    return out


class PublishGate:
    """Wraps the pipeline's snapshot publication in a lock that the haptic tick holds while it
    reads the front snapshot's number and launches the proxy kernel."""

    def __init__(self, pipeline):
        self.lock = threading.Lock()
        self._pipeline = pipeline
        self._buf = getattr(pipeline, "buffers", None)
        if self._buf is not None and not getattr(self._buf, "_pointfence_gated", False):
            original = self._buf.publish
            lock = self.lock

            def publish(i, _original=original, _lock=lock):
                with _lock:
                    _original(i)

            self._buf.publish = publish
            self._buf._pointfence_gated = True

    def front_seq(self) -> int:
        """Number of the snapshot queries run against now (call while holding ``lock``)."""
        buf = self._buf
        if buf is None:
            return int(self._pipeline.seq)
        return int(getattr(buf.slots[buf.front_index], "seq", 0) or 0)


class _FeedBase:
    """What the service asks of a frame feeder, every tick: ``max_age(now)``, plus status."""

    def __init__(self, pipeline, sources: Sequence, stale_s: float, max_age_s: float):
        self.pipeline = pipeline
        self.sources = list(sources)
        self.names = [s.camera.name for s in self.sources]
        self.stale_s = float(stale_s)
        self.max_age_s = float(max_age_s)
        n = len(self.sources)
        self.latest: list = [None] * n
        self.arrival = [-math.inf] * n     # loop/clock time each camera's latest frame arrived
        #: arrival of the oldest frame of the newest published snapshot (-inf: none yet)
        self.published_arrival = -math.inf
        self.frames_in = [0] * n
        self.snapshots = 0
        self.ingest_errors = 0
        self.last_error: Optional[str] = None
        self.snapshot_frames: dict = {}    # snapshot seq -> tuple of frame seqs (rig order of names)
        self.snapshot_tick: dict = {}      # snapshot seq -> first tick that used it (filled by the service)
        #: ``time.monotonic()`` when the running build began (None between builds: build_watch.py)
        self.build_started: Optional[float] = None
        #: held while a snapshot is built (and while ``swap_pipeline`` moves ingest to another pipeline)
        self.ingest_lock = threading.Lock()
        #: frames -> frames, applied before every ingest (the robot self-filter; None: none)
        self.frame_filter = None
        #: called with (snapshot seq, the frames it was built from) after each build (the MCAP
        #: recorder's ``offer_snapshot``: it must return at once; None: nobody records)
        self.on_snapshot = None

    def frame_time(self, t: float, now: float) -> Optional[float]:
        """The tick's time on the frames' clock (loop time ``t``, clock reading ``now``); None
        while the relation between the two is unknown."""
        return None

    def max_age(self, now: float) -> float:
        """Age (s) of the newest published snapshot: ``now`` minus the arrival of its oldest
        frame; inf until a snapshot was published."""
        return now - self.published_arrival

    def frames_too_old(self, now: float) -> bool:
        """Whether some camera's latest frame is older than ``max_age_s`` (a camera problem);
        False when the frames are fresh and only the snapshots are old (an ingest problem)."""
        return now - min(self.arrival) > self.max_age_s

    def ages(self, now: float) -> dict:
        return {n: (now - a if a > -math.inf else None) for n, a in zip(self.names, self.arrival)}

    def stale(self, now: float) -> list:
        return [n for n, a in zip(self.names, self.arrival) if now - a > self.stale_s]

    def _ingest(self, frames: list, arrival: Optional[float] = None) -> bool:
        """Build a snapshot of ``frames`` whose oldest arrived at ``arrival`` (default: the
        cameras' latest arrivals, for frames that are ``latest``)."""
        checkpoint()
        with self.ingest_lock:
            return self._ingest_locked(frames, min(self.arrival) if arrival is None else arrival)

    def swap_pipeline(self, new) -> bool:
        """Build snapshots in ``new`` from now on (the control API's runtime reconfiguration).
        ``new`` first gets a snapshot of every camera's latest frame, numbered on from the current
        pipeline's snapshots, so it is as current as the old one the moment it takes over; the
        swap happens only if that snapshot was built (returns whether it was)."""
        with self.ingest_lock:
            old = self.pipeline
            new.seq = max(int(new.seq), int(old.seq))
            self.pipeline = new
            if self._ingest_locked(list(self.latest), min(self.arrival)):
                return True
            self.pipeline = old
            return False

    def _ingest_locked(self, frames: list, arrival: float) -> bool:
        return run_steps(self._ingest_steps(frames, arrival))

    def _ingest_steps(self, frames: list, arrival: float):
        """``_ingest_locked`` as a generator over the pipeline's ``ingest_steps`` (it yields while
        the build's device work runs; returns whether a snapshot was built). The caller holds
        ``ingest_lock`` or is the feed's only ingesting thread, until the generator ends."""
        if any(f is None for f in frames):
            return False
        self.build_started = time.monotonic()
        try:
            flt = self.frame_filter
            built = list(frames) if flt is None else flt(frames)
            info = yield from self.pipeline.ingest_steps(built)
        except PointfenceError as e:   # bad frame: the previous snapshot stays current
            self.ingest_errors += 1
            self.last_error = f"ingest: {e}"
            return False
        except Exception as e:   # a failing build (driver, filter, backend): counted, reported, never fatal
            self.ingest_errors += 1
            self.last_error = f"ingest: {type(e).__name__}: {e}"
            return False
        finally:
            self.build_started = None
        self.snapshots += 1
        self.published_arrival = max(self.published_arrival, arrival)
        self.snapshot_frames[info.seq] = tuple(int(f.seq) for f in frames)
        if self.on_snapshot is not None:
            checkpoint()      # (the recorder's copy of the frames, the telemetry's cloud: Python)
            self.on_snapshot(info.seq, built)
        return True

    def status(self, now: float) -> dict:
        return {"cameras": self.names, "frames": dict(zip(self.names, self.frames_in)), "ages_s": self.ages(now),
                "stale": self.stale(now), "snapshots": self.snapshots, "ingest_errors": self.ingest_errors,
                "last_error": self.last_error}

    def close(self) -> None:
        for s in self.sources:
            s.close()


class SimFrames(_FeedBase):
    """Offline frames on the loop clock (see the module docstring). ``poll(t)`` ingests at most
    one snapshot from the frames due by ``t`` and returns True if it did."""

    def __init__(self, pipeline, sources, stale_s: float = 0.1, max_age_s: float = 0.5):
        super().__init__(pipeline, sources, stale_s, max_age_s)
        self._pending = [s.read() for s in self.sources]
        self._t0 = [f.timestamp if f is not None else 0.0 for f in self._pending]

    def frame_time(self, t: float, now: float) -> float:
        return t + self._t0[0]

    def poll(self, t: float) -> bool:
        changed = False
        for i, src in enumerate(self.sources):
            f = self._pending[i]
            while f is not None and f.timestamp - self._t0[i] <= t + 1e-9:
                self.latest[i] = f
                self.arrival[i] = f.timestamp - self._t0[i]
                self.frames_in[i] += 1
                changed = True
                f = src.read()
            self._pending[i] = f
        return self._ingest(self.latest) if changed else False


class ScheduledFrames(_FeedBase):
    """Re-create recorded snapshots: ``schedule`` maps a tick index to the frame seqs (one per
    camera, configuration order) of the snapshot that became visible at that tick."""

    def __init__(self, pipeline, sources, schedule: dict, stale_s: float = 0.1, max_age_s: float = 0.5,
                 t0: float = 0.0):
        super().__init__(pipeline, sources, stale_s, max_age_s)
        self.schedule = {int(k): tuple(v) for k, v in schedule.items()}
        self.t0 = float(t0)   # frames' clock at loop time 0

    def frame_time(self, t: float, now: float) -> float:
        return t + self.t0

    def poll_tick(self, k: int, t: float) -> bool:
        seqs = self.schedule.get(k)
        if seqs is None:
            return False
        for i, (src, seq) in enumerate(zip(self.sources, seqs)):
            f = self.latest[i]
            if f is None or f.seq != seq:
                self.latest[i] = src._frame(int(seq))  # random access: frames depend only on their seq
                self.frames_in[i] += 1
            self.arrival[i] = t
        return self._ingest(self.latest)


class LiveFrames(_FeedBase):
    """Real-time frames: a ``sources.threaded.CameraReader`` per camera (its own thread and
    pace) and an ingest thread that builds a snapshot whenever some camera delivered a new
    frame. ``clock`` must be the loop's clock so that frame ages compare with loop time."""

    def __init__(self, pipeline, sources, clock, stale_s: float = 0.1, max_age_s: float = 0.5):
        super().__init__(pipeline, sources, stale_s, max_age_s)
        from .sources.threaded import CameraReader

        self.clock = clock
        self._new = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.readers = [CameraReader(s, stale_after=self.stale_s, on_frame=self._callback(i), clock=clock.now)
                        for i, s in enumerate(self.sources)]
        self._thread: Optional[threading.Thread] = None
        self.ingest_dead: Optional[str] = None   # why the ingest thread died (None: it did not)
        self.ingest_ms: list = []
        #: the watch that keeps PoCL's pool from starving (build_watch.py; set by LiveRun)
        self.build_watch = None
        #: each camera's clock against the loop's (camera_clock.py); cameras whose sources name
        #: the same ``clock_domain`` share one
        self.clocks = camera_clocks(self.sources)
        #: whether camera i's latest frame is stamped on camera 0's clock yet (a camera of another
        #: clock is mapped once camera 0's clock is known)
        self._on_ref = [c is self.clocks[0] for c in self.clocks]
        self.scheduling = "normal"

    @property
    def clock_minus_stamp(self) -> Optional[float]:
        """Loop clock minus camera 0's clock (s; None before its first frame): the frames' clock."""
        c = self.clocks[0]
        return None if c.samples == 0 else c.offset()

    def frame_time(self, t: float, now: float) -> Optional[float]:
        cms = self.clock_minus_stamp
        return None if cms is None else now - cms

    def _callback(self, i: int):
        def on_frame(frame, _i=i):
            now = self.clock.now()
            clk = self.clocks[_i]
            with self._lock:
                clk.update(frame.timestamp, now)
                same = clk is self.clocks[0]
                self.latest[_i] = frame if same else self._on_frames_clock(_i, frame)
                self.arrival[_i] = now
                self.frames_in[_i] += 1
            self._new.set()
        return on_frame

    def _on_frames_clock(self, i: int, frame):
        """Camera ``i``'s ``frame`` stamped on camera 0's clock (the frames' clock) through both
        cameras' estimated offsets; unchanged (and noted) while camera 0's clock is unknown."""
        ref = self.clocks[0]
        self._on_ref[i] = ref.samples > 0
        if not self._on_ref[i]:
            return frame
        t = self.clocks[i].to_service(frame.timestamp) - ref.offset()
        return replace(frame, timestamp=t)

    def clock_status(self) -> dict:
        """Per camera: its clock's offset to the loop clock (s), drift (ppm) and frames seen."""
        return {n: c.status() for n, c in zip(self.names, self.clocks)}

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        for r in self.readers:
            r.start()
        self._start_ingest()

    def _start_ingest(self) -> None:
        self.ingest_dead = None
        self._thread = threading.Thread(target=self._ingest_thread, name="pointfence-ingest", daemon=True)
        self._thread.start()

    def restart_ingest(self) -> bool:
        """Start the ingest thread again if it died (the service's clear-faults); True if it did."""
        th = self._thread
        if self._stop.is_set() or th is None or th.is_alive():
            return False
        self._start_ingest()
        return True

    def set_rt_priority(self, priority: int) -> str:
        """SCHED_FIFO ``priority`` for the running reader and ingest threads, and the sources' own
        (``DepthSource.threads``: Python threads a source runs itself), where the OS allows it (0: leave them
        normal). They hold Python's interpreter lock between blocking calls, and one preempted by
        lower-priority work would keep the haptic loop waiting for the lock as long as it waits
        for a core. Returns what was applied (for the status)."""
        if priority <= 0:
            self.scheduling = "normal"
            return self.scheduling
        threads = [r._thread for r in self.readers] + [self._thread] + [t for s in self.sources for t in s.threads()]
        try:
            for th in threads:
                if th is not None and th.is_alive():
                    os.sched_setscheduler(th.native_id, os.SCHED_FIFO, os.sched_param(int(priority)))
            self.scheduling = f"SCHED_FIFO {int(priority)}"
        except (AttributeError, OSError) as e:
            self.scheduling = f"normal (SCHED_FIFO refused: {e})"
        return self.scheduling

    def stop(self) -> None:
        self._stop.set()
        self._new.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for r in self.readers:
            r.stop(close=False)

    def wait_first_snapshot(self, timeout: float = 10.0) -> bool:
        end = time.monotonic() + timeout
        while self.snapshots == 0 and time.monotonic() < end:
            time.sleep(0.005)
        return self.snapshots > 0

    def status(self, now: float) -> dict:
        st = super().status(now)
        th = self._thread
        st["ingest"] = ("dead: " + (self.ingest_dead or "thread ended") if th is not None and not th.is_alive()
                        and not self._stop.is_set() else "running" if th is not None else "stopped")
        st["readers"] = {r.name: r.status().reason for r in self.readers}
        st["scheduling"] = self.scheduling
        st["clocks"] = self.clock_status()
        if self.build_watch is not None:
            st["builds"] = self.build_watch.status()
        return st

    def _ingest_thread(self) -> None:
        name_this_thread("pf-ingest")
        try:
            self._ingest_loop()
        except BaseException as e:   # noqa: B036 -- reported: the snapshots' age then holds the arms (S2, S9)
            self.ingest_dead = f"{type(e).__name__}: {e}"
            self.last_error = f"ingest thread died: {self.ingest_dead}"

    def _ingest_loop(self) -> None:
        while not self._stop.is_set():
            if not self._new.wait(0.05):
                continue
            self._new.clear()
            if self._stop.is_set():
                return
            with self._lock:
                for i, ok in enumerate(self._on_ref):
                    if not ok and self.latest[i] is not None:   # arrived before camera 0's first
                        self.latest[i] = self._on_frames_clock(i, self.latest[i])
                frames = list(self.latest)
                arrival = min(self.arrival)
            t0 = time.perf_counter()
            if self._ingest(frames, arrival):
                self.ingest_ms.append((time.perf_counter() - t0) * 1e3)
                if len(self.ingest_ms) > 4096:
                    del self.ingest_ms[:2048]
