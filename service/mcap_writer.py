"""The MCAP writer process of a recording (``python -m pointfence.service.mcap_writer``, started by
``mcap_record.McapRecorder``): everything that costs CPU (CDR encoding of the ticks and of the
raw depth, colour and mask images, zstd chunks, the fixture cloud, fsync) runs here, outside the service's
interpreter, so it never holds the service's interpreter lock.

Inputs: the two shared blocks of ``mcap_shm`` (the tick ring, and the frame ring once the
cameras are known), the recording file as an inherited file descriptor, and control messages on
stdin (``child_pipe.send``/``receive``: 4-byte length, then a pickled tuple):

* ``("init", dict)``: first, the recording's parameters (``McapRecorder.__init__``);
* ``("meta", name, dict)``: a metadata record; ``pointfence/run`` accumulates (``describe``),
  any other name is one record (``add_metadata``); written at the next flush;
* ``("frames", path, shapes, slots, cameras, params)``: map the frame block (``attach``);
* ``("epoch", ns)``: the wall clock at loop-clock 0;
* ``("joints", path, dof, {arm: joint names}, every)``: map the joint block; every ``every``-th
  tick's joints go to ``/<arm>/measured_js``;
* ``("grasper", path, arm, every, fields)``: map the grasper block (``[cable]``); every
  ``every``-th tick's grasper row goes to ``mcap_topics.GrasperTopics``;
* ``("sync", token)``: the run is over: write every tick and frame the rings hold now (no fixture
  cloud after it), end the chunk, fsync, then set the header's ``SYNCED`` to ``token``
  (``McapRecorder.seal``, the flush barrier before end-of-run metadata);
* ``("close",)``: write everything, the summary and footer, and exit 0.

Every ``flush_s`` it carries out the control messages sent before the ticks it is about to
write (``mcap_shm.SENT``: a message reaches the file before any tick that followed it, however
late the pipe delivers it), writes the ticks the ring holds (first: they are cheap and the ring must
not fill), then the snapshot entries for at most ``flush_s`` more, the fixture cloud at ``cloud_hz``, ends the chunk and
fsyncs. End of stdin without ``close`` means the service died (``kill -9``, a crash): it writes
what the rings hold, a ``pointfence/end`` metadata record saying so, the summary, and exits 0;
the file is then whole up to the service's last tick. An error (disk full, ...) is one line on
stderr and exit 1: the service reads it (``McapRecorder.status``).
"""
from __future__ import annotations

import json
import os
import queue
import sys
import time

import numpy as np

from .child_pipe import control_inbox, read_init

#: seconds a flush waits for control messages the service sent before the ticks it writes
CATCH_UP_S = 5.0


class _Frame:
    """A recorded frame's images, for the fixture cloud."""

    def __init__(self, depth, color, mask, T_world_cam):
        self.depth, self.color, self.mask, self.T_world_cam = depth, color, mask, T_world_cam


class Writer:
    """The writer's state: the MCAP writer, the topics, the rings' read side."""

    def __init__(self, init: dict, out_fh, inbox: queue.Queue):
        from mcap.writer import CompressionType
        from mcap.writer import Writer as McapWriter

        from . import mcap_shm
        from .mcap_topics import ArmTopics, EventDetector, TopicWriter
        from .tick_cdr import TickLayout

        self.p = init
        self.layout = TickLayout(int(init["n"]))
        self.ticks = mcap_shm.TickBlock(mcap_shm.attach(init["tick_path"]), init["capacity"], self.layout.width)
        self.hdr = self.ticks.header
        self.frames = None
        self.cameras, self.params = [], None
        self.epoch_ns = int(init["epoch_ns"])
        self.fh = out_fh
        self.w = McapWriter(out_fh, chunk_size=4 << 20, compression=CompressionType.ZSTD)
        self.w.start(profile="ros2", library="pointfence")
        self.tw = TopicWriter(self.w)
        self.arms = ArmTopics(self.layout, self.layout.n)
        self.events = EventDetector(self.layout, self.layout.n)
        self.run_meta: dict = {}
        self.pending_meta: list = []      # (name, {key: JSON text})
        self.latest: list = []
        self.joints = None                # (JointTopics, JointBlock) once the robots are known
        self.grasper = None               # (GrasperTopics, JointBlock) with a [cable] grasper
        self.inbox = inbox                # control messages, in order (main's reader thread)
        self.received = 1                 # (the init message, which main read)
        self.sync = None                  # a sync asked for and not yet carried out
        self.sealed = self.closing = self.service_died = False
        self.next_cloud = 0.0
        self.flushed = int(self.hdr[mcap_shm.FLUSHED])
        self.consumed = int(self.hdr[mcap_shm.SNAPS_CONSUMED])

    # --- control -----------------------------------------------------------------------------------
    def control(self, msg) -> None:
        """Carry out one control message (None: the end of the pipe, the service is gone); a
        ``sync`` or ``close`` is noted (``sync``, ``closing``) for ``main`` to act on."""
        self.received += 1
        if msg is None:
            self.service_died = True
            return
        op = msg[0]
        if op == "meta":
            _, name, values = msg
            enc = {k: json.dumps(v) for k, v in values.items()}
            if name == "pointfence/run":
                self.run_meta.update(enc)
                enc = dict(self.run_meta)
            self.pending_meta.append((name, enc))
        elif op == "frames":
            from . import mcap_shm

            _, path, shapes, slots, self.cameras, self.params = msg
            self.frames = mcap_shm.FrameBlock(mcap_shm.attach(path), shapes, slots)
            self.latest = [None] * len(shapes)
        elif op == "epoch":
            self.epoch_ns = int(msg[1])
        elif op == "joints":
            from . import mcap_shm
            from .mcap_topics import JointTopics

            _, path, dof, names, every = msg
            block = mcap_shm.JointBlock(mcap_shm.attach(path), self.ticks.capacity, self.layout.n, dof)
            self.joints = (JointTopics({int(b): v for b, v in names.items()}, int(every)), block)
        elif op == "grasper":
            from . import mcap_shm
            from .mcap_topics import GrasperTopics

            _, path, arm, every, fields = msg
            block = mcap_shm.JointBlock(mcap_shm.attach(path), self.ticks.capacity, 1, len(fields))
            self.grasper = (GrasperTopics(arm, every, fields), block)
            self.arms.hand_over_jaw(arm)
        elif op == "sync":
            self.sync = int(msg[1])
        elif op == "close":
            self.closing = True

    @property
    def ended(self) -> bool:
        return self.closing or self.service_died

    def catch_up(self, sent: int) -> None:
        """Carry out the control messages up to number ``sent`` (``mcap_shm.SENT`` as read after
        ``WRITTEN``: every message sent before the ticks about to be written), waiting for those
        still in the pipe (at most ``CATCH_UP_S``)."""
        end = time.monotonic() + CATCH_UP_S
        while self.received < sent and not self.service_died:
            try:
                self.control(self.inbox.get(timeout=max(0.0, end - time.monotonic())))
            except queue.Empty:
                return

    @property
    def waiting(self) -> int:
        """Snapshot entries handed over and not yet encoded."""
        from . import mcap_shm

        return 0 if self.frames is None else int(self.hdr[mcap_shm.SNAPS_WRITTEN]) - self.consumed

    @property
    def behind(self) -> bool:
        """Snapshot entries wait in the frame ring (the last flush's time box ended before them)."""
        return self.waiting > 0

    @property
    def pressed(self) -> bool:
        """More than half the frame ring waits: the next flush encodes the frames before the ticks
        (a starved writer then drops fewer snapshots: the tick ring holds seconds more than the
        frame ring, ``mcap_record.RING`` against ``MAX_PENDING``)."""
        return self.waiting > self.frames.slots // 2 if self.frames is not None else False

    def wait_s(self, flush_s: float) -> float:
        """How long to wait for control messages before the next flush: ``flush_s``, or nothing
        while the writer is ``behind`` (it then encodes on at once: waiting a whole ``flush_s``
        between time-boxed flushes halved what it could encode, and the ring filled and dropped
        snapshots while the machine had CPU to spare)."""
        return 0.0 if self.behind else float(flush_s)

    # --- one flush ---------------------------------------------------------------------------------
    def flush(self, final: bool) -> None:
        from . import mcap_shm

        h = self.hdr
        t0 = time.perf_counter()
        written = int(h[mcap_shm.WRITTEN])
        self.catch_up(int(h[mcap_shm.SENT]))      # (read after WRITTEN: see mcap_shm.SENT)
        for name, enc in self.pending_meta:
            self.w.add_metadata(name, enc)
        self.pending_meta = []
        until = None if final else t0 + self.p["flush_s"]
        frames_first = self.pressed
        if frames_first:
            self.write_frames(until)
        ta = time.perf_counter()
        self.write_ticks(final, written)
        tb = time.perf_counter()
        if not frames_first:
            self.write_frames(until)
        self.write_cloud()
        t2 = time.perf_counter()
        self.w.flush()
        os.fsync(self.fh.fileno())
        t3 = time.perf_counter()
        h[mcap_shm.US_TICKS] += int((tb - ta) * 1e6)
        h[mcap_shm.US_FRAMES] += int(((t2 - t0) - (tb - ta)) * 1e6)
        h[mcap_shm.US_SYNC] += int((t3 - t2) * 1e6)
        h[mcap_shm.US_FLUSH_MAX] = max(int(h[mcap_shm.US_FLUSH_MAX]), int((t3 - t0) * 1e6))
        h[mcap_shm.US_CPU] = int(time.process_time() * 1e6)
        h[mcap_shm.BEAT] += 1

    def write_ticks(self, final: bool, written: int) -> None:
        """The tick rows below ``written`` (the newest one too where ``final``)."""
        from . import mcap_shm
        from .ros2_schemas import TICK_INPUT, TICK_OUTPUT

        upto = written if final else written - 1      # (the newest row may still get its tick_us)
        a, cap, lay = self.flushed, self.ticks.capacity, self.layout
        while a < upto:
            i = a % cap
            m = min(upto - a, cap - i)
            rows = self.ticks.rows[i: i + m].copy()
            joints = None if self.joints is None else self.joints[1].rows[i: i + m].copy()
            grasper = None if self.grasper is None else self.grasper[1].rows[i: i + m, 0].copy()
            a += m
            self.flushed = a
            self.hdr[mcap_shm.FLUSHED] = a         # (the ring rows may be reused from here on)
            ns = self.epoch_ns + np.round(rows[:, lay.cols[("in", "now")][0]] * 1e9).astype(np.int64)
            for part, topic, schema in (("in", TICK_INPUT, "pointfence_msgs/TickInput"),
                                        ("out", TICK_OUTPUT, "pointfence_msgs/TickOutput")):
                for msg, t in zip(lay.encode(part, rows, ns), ns.tolist()):
                    self.tw.raw(topic, schema, msg, t)
            k = rows[:, lay.cols[("in", "k")][0]].astype(np.int64)
            every = max(1, int(round(self.p["rate_hz"] / self.p["pose_hz"])))
            sel = k % every == 0
            self.arms.write(self.tw, rows[sel], ns[sel])
            self.events.write(self.tw, rows, ns)
            if joints is not None:
                self.joints[0].write(self.tw, k, joints, ns)
            if grasper is not None:
                self.grasper[0].write(self.tw, k, grasper, ns)

    def _frame_ns(self, ts: float, cms: float) -> int:
        return self.epoch_ns + int(round((ts + cms) * 1e9))

    def write_frames(self, until) -> None:
        """Encode the snapshot entries the ring holds, until the monotonic time ``until`` (s;
        None: all): a writer short of CPU keeps its chunks and fsyncs every ``flush_s`` and
        leaves the rest for its next flush (the ring then fills and drops snapshots, counted)."""
        from . import mcap_shm
        from .cdr import raw_image
        from .mcap_topics import camera_info, stamp
        from .ros2_schemas import SNAPSHOTS, camera_topics

        fb = self.frames
        if fb is None:
            return
        written = int(self.hdr[mcap_shm.SNAPS_WRITTEN])
        tw = self.tw
        while self.consumed < written and (until is None or time.perf_counter() < until):
            slot = self.consumed % fb.slots
            seq = int(fb.meta[slot, 0])
            fseqs, findex, stamps, poses, cmss = [], [], [], [], []
            for i, cam in enumerate(self.cameras):
                e = fb.cam_meta(slot, i)
                fseq, idx, ts, cms = int(e[mcap_shm.FSEQ]), int(e[mcap_shm.INDEX]), float(e[mcap_shm.STAMP]), float(e[mcap_shm.CMS])
                pose = e[mcap_shm.POSE: mcap_shm.POSE + 16].copy()
                fseqs.append(fseq)
                findex.append(idx)
                stamps.append(ts)
                poses.append(pose)
                cmss.append(cms)
                if not e[mcap_shm.NEW]:
                    continue
                ns = self._frame_ns(ts, cms)
                tops = camera_topics(cam.name)
                depth = fb.depth[slot][i]
                # raw images: the chunk's zstd compresses them losslessly, with less CPU than a PNG
                # encoder takes and into fewer bytes (bench/HISTORY.md, stop 32)
                tw.raw(tops["depth"], "sensor_msgs/Image", raw_image(ns, cam.name, depth), ns, idx)
                tw.dyn(tops["info"], "sensor_msgs/CameraInfo", camera_info(cam, ns), ns, idx)
                color = fb.color[slot][i] if e[mcap_shm.COLOR] else None
                mask = fb.mask[slot][i] if e[mcap_shm.MASK] else None
                if color is not None:
                    tw.raw(tops["color"], "sensor_msgs/Image", raw_image(ns, cam.name, color), ns, idx)
                if mask is not None:
                    tw.raw(tops["mask"], "sensor_msgs/Image", raw_image(ns, cam.name, mask), ns, idx)
                self.latest[i] = _Frame(depth.copy(), None if color is None else color.copy(),
                                        None if mask is None else mask.copy(),
                                        None if np.isnan(pose[0]) else pose.reshape(4, 4))
                self.hdr[mcap_shm.FRAMES_RECORDED] += 1
            last = int(np.argmax(stamps)) if stamps else 0
            ns = self._frame_ns(stamps[last], cmss[last]) if stamps else self.epoch_ns
            tw.dyn(SNAPSHOTS, "pointfence_msgs/Snapshot",
                   {"header": stamp(ns, "world"), "seq": seq, "frame_seq": fseqs, "frame_index": findex,
                    "frame_stamp": stamps, "t_world_cam": [float(x) for p in poses for x in p]}, ns)
            self.consumed += 1
            self.hdr[mcap_shm.SNAPS_CONSUMED] = self.consumed
            self.hdr[mcap_shm.SNAPSHOTS_RECORDED] += 1

    def write_cloud(self) -> None:
        from .fixture_cloud import pointcloud2, protected_points
        from .ros2_schemas import FIXTURES

        if self.sealed or self.p["cloud_hz"] <= 0 or self.params is None or all(f is None for f in self.latest):
            return
        now = time.monotonic()
        if now < self.next_cloud:
            return
        self.next_cloud = now + 1.0 / self.p["cloud_hz"]
        pts = protected_points(self.cameras, self.latest, self.params)
        ns = time.time_ns()
        self.tw.dyn(FIXTURES, "sensor_msgs/PointCloud2", pointcloud2(pts, ns), ns)

    def finish(self, service_died: bool) -> None:
        if service_died:
            self.w.add_metadata("pointfence/end", {"reason": json.dumps(
                "the service ended without closing the recording (killed or crashed); the writer process wrote "
                "every tick and frame the service had handed over, then closed the file")})
        self.w.finish()
        self.fh.flush()
        os.fsync(self.fh.fileno())
        self.fh.close()


def main() -> int:
    ctl = sys.stdin.buffer
    p = read_init(ctl, "mcap_writer", "McapRecorder")
    if p is None:
        return 2
    from . import mcap_shm

    inbox = control_inbox(ctl, "mcap-writer-control")
    w = Writer(p, os.fdopen(p["fd"], "wb"), inbox)
    try:
        while True:
            deadline = time.monotonic() + w.wait_s(p["flush_s"])
            while not w.ended and w.sync is None:
                try:
                    w.control(inbox.get(timeout=max(0.0, deadline - time.monotonic())))
                except queue.Empty:
                    break
            final = w.ended or w.sync is not None
            w.flush(final=final)        # (its catch_up may note a sync or the end: acted on next round)
            if final and w.sync is not None:
                w.sealed = True         # (no fixture cloud after the run's end)
                w.hdr[mcap_shm.SYNCED] = w.sync
                w.sync = None
            if final and w.ended:
                break
        w.finish(w.service_died)
    except (OSError, ValueError) as e:
        print(f"recording {p['path']}: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
