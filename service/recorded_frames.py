"""The frame feeder of a replayed MCAP recording (``mcap_replay``): the recorded snapshots built
again from the recorded frames, each published before the tick that first saw it in the live
run, numbered as it was.

Two things run ahead of the ticks, as in the live service, without changing what a tick sees:

* PNG decoding (``FrameDecoder``): the frames are decoded in the order the schedule needs them,
  up to ``DECODE_AHEAD`` ahead, in a thread pool (``cv2.imdecode`` releases the interpreter
  lock), from before the replay's service is set up;
* snapshot builds, where the pipeline double-buffers its snapshots (``pipeline.buffers``: the
  OpenCL and Warp backends): a builder thread builds the next scheduled snapshot into the back
  buffer while the ticks before it run, and holds back its publication (``buffers.publish``);
  the tick that first saw it in the live run publishes it, after which the builder may start
  the next build (the back buffer is then the old front, as in a sequential replay). A
  snapshot build reads only the recorded frames and the snapshot before it, so it is the same
  bit for bit as built in the tick (the live service builds beside the ticks the same way).
  The NumPy reference pipeline (a single buffer) builds in the tick.
"""
from __future__ import annotations

import math
import queue
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

from .frames import _FeedBase

#: recorded frames decoded ahead of the snapshot build that needs them
DECODE_AHEAD = 12
#: seconds a tick waits for the builder before calling the replay stuck
BUILD_TIMEOUT_S = 120.0


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
    (s; the builder's arrival time of the frames, which ``poll_tick`` otherwise receives).
    ``too_old`` is the recorded ``frames_too_old`` of the tick being replayed. ``ahead``: build
    in a thread where the pipeline double-buffers (see the module). Call ``close()`` after the
    replay."""

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
        self._use_builder = bool(ahead) and tick_times is not None
        self._builder: Optional[threading.Thread] = None
        self._ready: queue.Queue = queue.Queue()      # (k, seq, held-back slot or None, built, error)
        self._published = threading.Semaphore(0)     # one per job the tick has published
        self._held: Optional[int] = None
        self._publish = None
        self._stop = False

    # --- one snapshot --------------------------------------------------------------------------
    def frames_too_old(self, now: float) -> bool:
        return self.too_old

    def _build(self, seq: int, t: float) -> bool:
        """Build snapshot ``seq`` from its recorded frames (arrival time ``t``); False if it is
        not in the recording or its build failed."""
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
        return self._ingest(list(self.latest), t)

    def start(self) -> None:
        """Start building ahead (where the pipeline double-buffers) before the first tick: call
        after ``Service.attach_frames`` (its publish gate); else the first tick starts it."""
        if self._use_builder and self._builder is None:
            self._start_builder()

    def poll_tick(self, k: int, t: float) -> bool:
        self.start()
        if self._builder is not None:
            return self._publish_due(k)
        built = False
        for seq in self.build_at.get(k, ()):
            built |= self._build(seq, t)
        return built

    # --- building ahead ------------------------------------------------------------------------
    def _start_builder(self) -> None:
        buf = getattr(self.pipeline, "buffers", None)
        if buf is None or not hasattr(buf, "publish"):
            self._use_builder = False
            return
        self._publish = buf.publish        # (the publish gate's, where the service installed one)

        def hold(i: int) -> None:          # the builder's publication, held for its tick
            self._held = i

        buf.publish = hold
        self._buf = buf
        self._builder = threading.Thread(target=self._build_all, name="pointfence-replay-build", daemon=True)
        self._builder.start()

    def _build_all(self) -> None:
        for k, seq in self._jobs:
            if self._stop:
                return
            self._held = None
            try:
                built = self._build(seq, self.tick_times.get(k, 0.0))
                self._ready.put((k, seq, self._held, built, None))
            except BaseException as e:   # noqa: BLE001 (handed to the tick, which raises it)
                self._ready.put((k, seq, None, False, e))
                return
            self._published.acquire()     # the tick published it: the back buffer is free again

    def _publish_due(self, k: int) -> bool:
        built = False
        for _ in self.build_at.get(k, ()):
            try:
                jk, seq, held, ok, err = self._ready.get(timeout=BUILD_TIMEOUT_S)
            except queue.Empty:
                raise RuntimeError(f"replay: the snapshot builder produced nothing for tick {k} within "
                                   f"{BUILD_TIMEOUT_S} s") from None
            if err is not None:
                raise err
            if jk != k:
                raise RuntimeError(f"replay: snapshot {seq} was built for tick {jk}, expected tick {k} (schedule "
                                   "out of order)")
            if held is not None:
                self._publish(held)
            built |= ok
            self._published.release()
        return built

    def close(self) -> None:
        """End the builder and the decoding threads (idempotent) and restore the pipeline's publish."""
        if self._builder is not None:
            self._stop = True
            for _ in range(len(self._jobs) + 1):
                self._published.release()
            self._builder.join(timeout=BUILD_TIMEOUT_S)
            self._builder = None
            self._buf.publish = self._publish
        self.decoder.close()


__all__ = ["RecordedFrames", "FrameDecoder", "DECODE_AHEAD"]
