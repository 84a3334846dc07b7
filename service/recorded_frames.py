"""The frame feeder of a replayed MCAP recording (``mcap_replay``): the recorded snapshots built
again from the recorded frames, each published before the tick that first saw it in the live
run, numbered as it was.

Two things run ahead of the ticks, as in the live service, without changing what a tick sees:

* PNG decoding: the frames are decoded in the order the schedule needs them, up to
  ``DECODE_AHEAD`` ahead, in a thread pool (``cv2.imdecode`` releases the interpreter lock);
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


class RecordedFrames(_FeedBase):
    """Re-builds the recorded snapshots: ``build_at`` maps a tick number k to the snapshot seqs
    to build (in order) before that tick's proxy launch; ``tick_times`` maps k to its loop time
    (s; the builder's arrival time of the frames, which ``poll_tick`` otherwise receives).
    ``too_old`` is the recorded ``frames_too_old`` of the tick being replayed. ``ahead``: build
    in a thread where the pipeline double-buffers (see the module). Call ``close()`` after the
    replay."""

    def __init__(self, pipeline, recording, build_at: dict, stale_s: float, max_age_s: float,
                 tick_times: Optional[dict] = None, ahead: bool = True):
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
        self._order = self._frames_in_order()
        self._ahead: dict = {}            # (camera, recorded index) -> Future of its DepthFrame
        self._next = 0
        self._pool: Optional[ThreadPoolExecutor] = None
        self._use_builder = bool(ahead) and tick_times is not None
        self._builder: Optional[threading.Thread] = None
        self._ready: queue.Queue = queue.Queue()      # (k, seq, held-back slot or None, built, error)
        self._published = threading.Semaphore(0)     # one per job the tick has published
        self._held: Optional[int] = None
        self._publish = None
        self._stop = False

    # --- decoding ahead ------------------------------------------------------------------------
    def _frames_in_order(self) -> list:
        """(camera, recorded index, frame seq, stamp, pose) of every frame the replay decodes, in
        the order it needs them."""
        order, last = [], [-1] * len(self.names)
        for _, seq in self._jobs:
            entry = self.rec.snapshots.get(seq)
            if entry is None:
                continue
            fseqs, findex, stamps, poses = entry
            for i, (fseq, idx) in enumerate(zip(fseqs, findex)):
                if last[i] != idx:
                    order.append((i, idx, fseq, stamps[i], poses[16 * i: 16 * i + 16]))
                    last[i] = idx
        return order

    def _frame(self, i: int, idx: int, fseq: int, stamp: float, pose):
        """Camera ``i``'s recorded frame ``idx``: decoded ahead where it was scheduled, else now."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="pointfence-png")
        while self._next < len(self._order) and len(self._ahead) < DECODE_AHEAD:
            c, x, fs, st, po = self._order[self._next]
            self._next += 1
            self._ahead[(c, x)] = self._pool.submit(self.rec.frame, c, x, fs, st, po)
        fut = self._ahead.pop((i, idx), None)
        return fut.result() if fut is not None else self.rec.frame(i, idx, fseq, stamp, pose)

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
                self.latest[i] = self._frame(i, idx, fseq, stamps[i], poses[16 * i: 16 * i + 16])
                self._index[i] = idx
                self.frames_in[i] += 1
            self.arrival[i] = t
        self.pipeline.seq = seq - 1          # numbered as the live run numbered it
        return self._ingest(list(self.latest), t)

    def poll_tick(self, k: int, t: float) -> bool:
        if self._use_builder and self._builder is None:
            self._start_builder()
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
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._ahead.clear()


__all__ = ["RecordedFrames", "DECODE_AHEAD"]
