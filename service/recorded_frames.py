"""The frame feeder of a replayed MCAP recording (``mcap_replay``): the recorded snapshots built
again from the recorded frames, each published before the tick that first saw it in the live
run, numbered as it was.

Two things run ahead of the ticks, as in the live service, without changing what a tick sees:

* PNG decoding (``FrameDecoder``): the frames are decoded in the order the schedule needs them,
  up to ``DECODE_AHEAD`` ahead, in a thread pool (``cv2.imdecode`` releases the interpreter
  lock), from before the replay's service is set up;
* snapshot builds, where the pipeline double-buffers its snapshots (``pipeline.buffers``): the
  tick that publishes a snapshot (the tick that first saw it in the live run) then starts the
  next scheduled one (``FramePipeline.ingest_steps``: its frames taken, its device work
  enqueued into the back buffer and submitted), and the ticks go on while the device builds;
  the tick that first saw that one waits for the build to end and publishes it. Everything runs
  in the ticks' thread: a builder thread would wait for the interpreter lock while the ticks
  hold it, and got it only when a tick waited for the build (about a millisecond a snapshot,
  a third of a replay's time, on a 2-core VM). A snapshot build reads only the recorded frames
  and the snapshot before it, so it is the same bit for bit as built in the tick (the live
  service builds beside the ticks the same way). On the NumPy reference the whole build runs
  when it is due.
"""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

from pointfence.kernels.backend import run_steps

from .frames import _FeedBase

#: recorded frames decoded ahead of the snapshot build that needs them
DECODE_AHEAD = 12


class FrameDecoder:
    """Decodes the recorded frames a replay's schedule needs (``build_at``: tick -> snapshot seqs,
    as ``RecordedFrames`` takes it), in the order it needs them, up to ``ahead`` frames ahead,
    in ``workers`` threads (``cv2.imdecode`` releases the interpreter lock). It starts at once:
    made before the replay's service, it decodes while the service sets up. ``get`` hands a
    frame over (decoded ahead, else now); ``close()`` ends the threads."""

    def __init__(self, recording, build_at: dict, ahead: int = DECODE_AHEAD, workers: int = 2):
        self.rec = recording
        self.ahead = int(ahead)
        jobs = [seq for k in sorted(build_at) for seq in build_at[k]]
        self._order = _frames_in_order(recording, jobs)
        self._futures: dict = {}          # (camera, recorded index) -> Future of its DepthFrame
        self._next = 0
        self._pool: Optional[ThreadPoolExecutor] = ThreadPoolExecutor(max_workers=workers,
                                                                      thread_name_prefix="pointfence-png")
        self._top_up()

    def _top_up(self) -> None:
        while self._pool is not None and self._next < len(self._order) and len(self._futures) < self.ahead:
            c, x, fs, st, po = self._order[self._next]
            self._next += 1
            self._futures[(c, x)] = self._pool.submit(self.rec.frame, c, x, fs, st, po)

    def get(self, i: int, idx: int, fseq: int, stamp: float, pose):
        """Camera ``i``'s recorded frame ``idx`` (source seq ``fseq``, capture ``stamp`` s, pose:
        16 numbers) as a ``DepthFrame``."""
        fut = self._futures.pop((i, idx), None)
        self._top_up()
        return fut.result() if fut is not None else self.rec.frame(i, idx, fseq, stamp, pose)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._futures.clear()


def _frames_in_order(rec, seqs) -> list:
    """(camera, recorded index, frame seq, stamp, pose) of every frame that building snapshots
    ``seqs`` (in order) decodes, in that order."""
    order, last = [], [-1] * len(rec.cameras)
    for seq in seqs:
        entry = rec.snapshots.get(seq)
        if entry is None:
            continue
        fseqs, findex, stamps, poses = entry
        for i, (fseq, idx) in enumerate(zip(fseqs, findex)):
            if last[i] != idx:
                order.append((i, idx, fseq, stamps[i], poses[16 * i: 16 * i + 16]))
                last[i] = idx
    return order


class RecordedFrames(_FeedBase):
    """Re-builds the recorded snapshots: ``build_at`` maps a tick number k to the snapshot seqs
    to build (in order) before that tick's proxy launch; ``tick_times`` maps k to its loop time
    (s; the arrival time of the frames of a build started ahead, which ``poll_tick``
    otherwise receives). ``too_old`` is the recorded ``frames_too_old`` of the tick being
    replayed. ``ahead``: start each build at the tick before it is due, where the pipeline
    double-buffers (see the module). Call ``close()`` after the replay."""

    def __init__(self, pipeline, recording, build_at: dict, stale_s: float, max_age_s: float,
                 tick_times: Optional[dict] = None, ahead: bool = True, decoder: Optional[FrameDecoder] = None):
        super().__init__(pipeline, [], stale_s, max_age_s)
        self.rec = recording
        self.names = list(recording.cameras)
        n = len(self.names)
        self.latest, self.arrival, self.frames_in = [None] * n, [-math.inf] * n, [0] * n
        self.build_at = build_at
        self.tick_times = tick_times or {}
        self.too_old = False
        self.missing: list = []
        self._index = [-1] * n            # the recorded frame each camera's latest is
        self._jobs = [(k, seq) for k in sorted(build_at) for seq in build_at[k]]
        self.decoder = decoder if decoder is not None else FrameDecoder(recording, build_at)
        self._want_ahead = bool(ahead) and tick_times is not None
        self._ahead: Optional[bool] = None            # decided at start()
        self._next = 0                                # the next job to start
        self._pending = None                          # (k, seq, its steps or None, value, error)

    # --- one snapshot --------------------------------------------------------------------------
    def frames_too_old(self, now: float) -> bool:
        return self.too_old

    def _build_steps(self, seq: int, t: float):
        """Build snapshot ``seq`` from its recorded frames (arrival time ``t``), as a generator of
        ``_ingest_steps``' kind (it returns False if the snapshot is not in the recording or its
        build failed)."""
        entry = self.rec.snapshots.get(seq)
        if entry is None:
            self.missing.append(seq)
            return False
        fseqs, findex, stamps, poses = entry
        for i, (fseq, idx) in enumerate(zip(fseqs, findex)):
            if self._index[i] != idx:
                self.latest[i] = self.decoder.get(i, idx, fseq, stamps[i], poses[16 * i: 16 * i + 16])
                self._index[i] = idx
                self.frames_in[i] += 1
            self.arrival[i] = t
        self.pipeline.seq = seq - 1          # numbered as the live run numbered it
        return (yield from self._ingest_steps(list(self.latest), t))

    def start(self) -> None:
        """Start the first build (where the pipeline double-buffers) before the first tick: call
        after ``Service.attach_frames``; else the first tick starts it."""
        if self._ahead is None:
            self._ahead = self._want_ahead and hasattr(getattr(self.pipeline, "buffers", None), "publish")
            if self._ahead:
                self._start_next()

    def poll_tick(self, k: int, t: float) -> bool:
        self.start()
        built = False
        for seq in self.build_at.get(k, ()):
            if self._ahead:
                built |= self._finish(k, seq)
                self._start_next()
            else:
                built |= run_steps(self._build_steps(seq, t))
        return built

    # --- building ahead ------------------------------------------------------------------------
    def _start_next(self) -> None:
        """Start the next scheduled build: its part before the device works (an error in it is
        raised at the build's own tick)."""
        if self._next >= len(self._jobs):
            return
        k, seq = self._jobs[self._next]
        self._next += 1
        steps = self._build_steps(seq, self.tick_times.get(k, 0.0))
        try:
            next(steps)
            self._pending = (k, seq, steps, None, None)
        except StopIteration as e:           # done before any device work (a missing snapshot)
            self._pending = (k, seq, None, e.value, None)
        except Exception as e:   # noqa: BLE001 (raised at its tick, as a build in the tick would)
            self._pending = (k, seq, None, False, e)

    def _finish(self, k: int, seq: int) -> bool:
        """End the started build, due at tick ``k`` (snapshot ``seq``), and publish it."""
        pending, self._pending = self._pending, None
        if pending is None or pending[:2] != (k, seq):
            raise RuntimeError(f"replay: snapshot {seq} is due at tick {k}, but the build under way is "
                               f"{None if pending is None else pending[:2]} (schedule out of order)")
        _, _, steps, value, err = pending
        if err is not None:
            raise err
        return run_steps(steps) if steps is not None else value

    def close(self) -> None:
        """End a build under way (its device work waited for) and the decoding threads
        (idempotent)."""
        pending, self._pending = self._pending, None
        if pending is not None and pending[2] is not None:
            pending[2].close()
        self.decoder.close()


__all__ = ["RecordedFrames", "FrameDecoder", "DECODE_AHEAD"]
