"""Recording a live run to MCAP with ROS 2 message schemas (``pointfence serve|demo --record
FILE.mcap``), streamed to disk while the run goes on (S8).

Three sides, and what each may do:

* the 1 kHz tick (``write``, ``note_tick_us``): copies its ``TickInput`` and ``TickOutput`` into
  a preallocated ring row (``tick_cdr.TickRows``); no encoding, no I/O, no allocation. A tick
  that finds the ring full (the writer more than ``capacity`` ticks behind) is not recorded and
  counts in ``ticks_lost``.
* the frame feeder's ingest side (``offer_snapshot``, called by ``frames._FeedBase`` after each
  snapshot is built, with the frames it was built from, after the robot self-filter): keeps
  copies of the frames it has not seen in a bounded queue and returns; a full queue drops the
  snapshot and counts it (``snapshots_dropped``): a replay then says which snapshot is missing.
* the writer thread: every ``flush_s`` (<= 0.5 s) it encodes what the others left (depth as
  lossless ``compressedDepth`` PNG with its ``CameraInfo``, colour and mask PNGs, the snapshot
  table, every tick's input and output, the decimated poses and wrenches, events, the fixture
  cloud at ``cloud_hz``), ends the MCAP chunk and fsyncs. A ``kill -9`` leaves every chunk
  written before it: all but the last ``flush_s`` and the chunk being written, readable with
  ``mcap_read.open_recording`` (the summary section at the end exists only after ``close()``).

Stamps and log times are the loop clock mapped to wall-clock time: ``epoch_ns`` (in the
``pointfence/recording`` metadata) is the wall clock at loop-clock 0; a frame's capture
timestamp goes through the feeder's loop-clock offset where it has one.
"""
from __future__ import annotations

import json
import os
import threading
import time
from collections import deque
from pathlib import Path
from typing import Optional

import numpy as np
from mcap.writer import CompressionType, Writer

from pointfence.kernels.errors import InputError

from . import depth_png
from .cdr import compressed_image
from .fixture_cloud import pointcloud2, protected_points
from .mcap_topics import ArmTopics, EventDetector, TopicWriter, camera_info, stamp
from .ros2_schemas import FIXTURES, SNAPSHOTS, TICK_INPUT, TICK_OUTPUT, camera_topics
from .tick_cdr import TickLayout, TickRows

FORMAT = "pointfence mcap recording"
VERSION = 1
#: ring rows (4 s at 1 kHz: the writer may fall that far behind)
RING = 4096
#: snapshots waiting for the writer (2 s of a 30 Hz camera)
MAX_PENDING = 64


class McapRecorder:
    """See the module docstring. ``keep`` > 0 also keeps that many ticks in memory
    (``record.Recorder``) for what reads a finished run's arrays (the demo's report)."""

    streaming = True

    def __init__(self, path, n: int = 1, keep: int = 0, capacity: int = RING, flush_s: float = 0.25,
                 pose_hz: float = 100.0, cloud_hz: float = 2.0, rate_hz: float = 1000.0):
        if not 0 < flush_s <= 0.5:
            raise InputError(f"McapRecorder: flush_s = {flush_s!r}; expected 0 < flush_s <= 0.5 s (S8: a crash may "
                             "lose at most the last second)")
        self.path = Path(path)
        self.n, self.capacity, self.flush_s = int(n), int(capacity), float(flush_s)
        self.rate_hz, self.pose_hz, self.cloud_hz = float(rate_hz), float(pose_hz), float(cloud_hz)
        self.layout = TickLayout(self.n)
        self._fill = TickRows(self.layout)
        self.data = np.zeros((self.capacity, self.layout.width))
        from .record import Recorder

        self.memory = Recorder(keep, self.n) if keep else None
        self._next = 0
        self._flushed = 0
        self.ticks_recorded = self.ticks_lost = 0
        self.full = False
        self.snapshots_recorded = self.snapshots_dropped = self.frames_recorded = 0
        self.write_error: Optional[str] = None
        self.epoch_ns = time.time_ns()
        self._pending: deque = deque()
        self._last_frame: list = []        # per camera: the last frame object offered
        self._index: list = []
        self._latest: list = []            # per camera: the latest recorded frame (for the fixture cloud)
        self._cameras: list = []
        self._params = None
        self._feeder = None
        self._meta: dict = {}
        self._meta_dirty = False
        self._next_cloud = 0.0
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = self.path.open("wb")
        except OSError as e:
            raise InputError(f"cannot write the recording {str(self.path)!r} ({e.strerror or e}); choose a FILE.mcap "
                             "in a folder you may write to") from None
        self._w = Writer(self._fh, chunk_size=4 << 20, compression=CompressionType.ZSTD)
        self._w.start(profile="ros2", library="pointfence")
        self._tw = TopicWriter(self._w)
        self._arms = ArmTopics(self.layout, self.n)
        self._events = EventDetector(self.layout, self.n)
        self.describe({"format": FORMAT, "version": VERSION, "arms": self.n, "rate_hz": self.rate_hz,
                       "pose_hz": self.pose_hz, "cloud_hz": self.cloud_hz, "flush_s": self.flush_s})
        self._stop = threading.Event()
        self._lock = threading.Lock()      # the writer's own state against close()
        self._thread = threading.Thread(target=self._writer, name="pointfence-mcap", daemon=True)
        self._thread.start()

    # --- the tick's side ------------------------------------------------------------------------
    def write(self, inp, out) -> None:
        """Record one tick (``Service.publish``): a copy into the ring, nothing else."""
        if self.memory is not None:
            self.memory.write(inp, out)
        j = self._next
        if j - self._flushed >= self.capacity:
            self.full = True
            self.ticks_lost += 1
            return
        self.full = False
        self._fill.fill(inp, out, self.data[j % self.capacity])
        self._next = j + 1
        self.ticks_recorded += 1

    def note_tick_us(self, us: float) -> None:
        """The loop's compute time of the tick just recorded (us)."""
        if self.memory is not None:
            self.memory.note_tick_us(us)
        if self._next > self._flushed and not self.full:
            self.data[(self._next - 1) % self.capacity, self._fill.tick_us_col] = us

    # --- set-up (before the run) ---------------------------------------------------------------------
    def describe(self, meta: dict, snapshot_frames=None) -> None:
        """Run facts for the ``pointfence/run`` metadata (JSON values): architecture, backend,
        cameras, ... (``snapshot_frames`` is the .pfrec recorder's; here the frames come through
        ``offer_snapshot``)."""
        self._meta.update(meta)
        self._meta_dirty = True

    def attach(self, feeder, cfg, clock_now=None, config_text: Optional[str] = None) -> None:
        """Take frames from ``feeder`` (``frames._FeedBase``: its ``on_snapshot``), the camera
        models and pipeline parameters of ``cfg``, and the loop clock (``clock_now()``, s) whose
        0 maps to ``epoch_ns``. Call before the feeder builds its first snapshot."""
        if clock_now is not None:
            self.epoch_ns = time.time_ns() - int(round(clock_now() * 1e9))
        self._feeder = feeder
        self._cameras = [c.camera for c in cfg.cameras]
        self._params = cfg.pipeline
        self._last_frame = [None] * len(self._cameras)
        self._index = [-1] * len(self._cameras)     # running number of each camera's recorded frames
        self._latest = [None] * len(self._cameras)
        cams = [{"name": c.name, "width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                 "depth_scale": c.depth_scale, "T_world_cam": np.asarray(c.T_world_cam, float).ravel().tolist(),
                 "dist": [float(x) for x in c.dist], "noise": {"a": c.noise.a, "b": c.noise.b}, "z_min": c.z_min,
                 "z_max": c.z_max, "max_code": c.max_code, "source": cc.source, "rate_hz": cc.rate_hz}
                for c, cc in zip(self._cameras, cfg.cameras)]
        self.describe({"epoch_ns": self.epoch_ns, "cameras": cams, "config": config_text,
                       "config_path": cfg.path})
        feeder.on_snapshot = self.offer_snapshot

    def note_start(self, service) -> None:
        """The state ``Service.start`` read (masters, robots, control), for a replay's start."""
        inp = service.inp
        self.describe({"start": {"master_pos": inp.master_pos.tolist(), "pedal": inp.pedal.tolist(),
                                 "master_ok": inp.master_ok.tolist(), "robot_pos": inp.robot_pos.tolist(),
                                 "robot_present": inp.robot_present.tolist(), "haptics": bool(service.haptics_on),
                                 "teleop": bool(service.teleop_on), "architecture": service.architecture}})

    # --- the ingest side ------------------------------------------------------------------------------
    def offer_snapshot(self, seq: int, frames) -> None:
        """Snapshot ``seq`` was built from ``frames`` (one per camera): copies of the frames not
        offered before go to the writer; never blocks."""
        if len(self._pending) >= MAX_PENDING:
            self.snapshots_dropped += 1
            return
        new, index = [], self._index
        for i, f in enumerate(frames):
            if f is self._last_frame[i]:
                new.append(None)
                continue
            self._last_frame[i] = f
            index[i] += 1
            new.append((index[i], f.timestamp, f.depth.copy(), None if f.color is None else f.color.copy(),
                        None if f.mask is None else f.mask.copy(), None if f.T_world_cam is None
                        else np.asarray(f.T_world_cam, float).copy(), f.camera))
        self._pending.append((int(seq), [int(f.seq) for f in frames], list(index), [float(f.timestamp) for f in frames],
                              [None if f.T_world_cam is None else np.asarray(f.T_world_cam, float).ravel()
                               for f in frames], new))

    # --- the writer thread ---------------------------------------------------------------------------
    def _writer(self) -> None:
        while not self._stop.wait(self.flush_s):
            self._flush(final=False)
        self._flush(final=True)

    def _frame_ns(self, ts: float) -> int:
        cms = getattr(self._feeder, "clock_minus_stamp", None)
        if cms is None:
            t0 = getattr(self._feeder, "_t0", None) or [getattr(self._feeder, "t0", 0.0)]
            cms = -float(t0[0])
        return self.epoch_ns + int(round((ts + cms) * 1e9))

    def _flush(self, final: bool) -> None:
        with self._lock:
            if self._fh.closed:
                return
            try:
                if self._meta_dirty:
                    self._meta_dirty = False
                    self._w.add_metadata("pointfence/run", {k: json.dumps(v) for k, v in self._meta.items()})
                self._write_frames()
                self._write_ticks(final)
                self._write_cloud()
                self._w.flush()
                self._fh.flush()
                os.fsync(self._fh.fileno())
            except (OSError, ValueError) as e:
                self.write_error = f"recording {self.path}: {e}"
                self._stop.set()

    def _write_frames(self) -> None:
        tw = self._tw
        while self._pending:
            seq, fseqs, findex, stamps, poses, new = self._pending.popleft()
            for i, fr in enumerate(new):
                if fr is None:
                    continue
                fseq, ts, depth, color, mask, _, name = fr       # (fseq: the running number)
                ns = self._frame_ns(ts)
                tops = camera_topics(name)
                tw.raw(tops["depth"], "sensor_msgs/CompressedImage",
                       compressed_image(ns, name, depth_png.DEPTH_FORMAT, depth_png.encode_depth(depth)), ns, fseq)
                tw.dyn(tops["info"], "sensor_msgs/CameraInfo", camera_info(self._cameras[i], ns), ns, fseq)
                if color is not None:
                    tw.raw(tops["color"], "sensor_msgs/CompressedImage",
                           compressed_image(ns, name, "rgb8; png compressed bgr8", depth_png.encode_color(color)), ns, fseq)
                if mask is not None:
                    tw.raw(tops["mask"], "sensor_msgs/CompressedImage",
                           compressed_image(ns, name, "mono8; png compressed mono8", depth_png.encode_mask(mask)), ns, fseq)
                self._latest[i] = _Frame(depth, color, mask, fr[5])
                self.frames_recorded += 1
            ns = self._frame_ns(max(stamps)) if stamps else self.epoch_ns
            tw.dyn(SNAPSHOTS, "pointfence_msgs/Snapshot",
                   {"header": stamp(ns, "world"), "seq": seq, "frame_seq": fseqs, "frame_index": findex, "frame_stamp": stamps,
                    "t_world_cam": [x for p in poses for x in (p.tolist() if p is not None else [float("nan")] * 16)]},
                   ns)
            self.snapshots_recorded += 1

    def _write_ticks(self, final: bool) -> None:
        upto = self._next if final else self._next - 1   # (the newest row may still get its tick_us)
        a = self._flushed
        while a < upto:
            i = a % self.capacity
            m = min(upto - a, self.capacity - i)
            rows = self.data[i: i + m].copy()
            self._flushed = a + m     # (the ring rows may be reused from here on)
            lay = self.layout
            now = rows[:, lay.cols[("in", "now")][0]]
            ns = self.epoch_ns + np.round(now * 1e9).astype(np.int64)
            for part, topic, schema in (("in", TICK_INPUT, "pointfence_msgs/TickInput"),
                                        ("out", TICK_OUTPUT, "pointfence_msgs/TickOutput")):
                for msg, t in zip(lay.encode(part, rows, ns), ns):
                    self._tw.raw(topic, schema, msg, t)
            k = rows[:, lay.cols[("in", "k")][0]].astype(np.int64)
            every = max(1, int(round(self.rate_hz / self.pose_hz)))
            sel = k % every == 0
            self._arms.write(self._tw, rows[sel], ns[sel])
            self._events.write(self._tw, rows, ns)
            a += m

    def _write_cloud(self) -> None:
        if self.cloud_hz <= 0 or self._params is None or all(f is None for f in self._latest):
            return
        now = time.monotonic()
        if now < self._next_cloud:
            return
        self._next_cloud = now + 1.0 / self.cloud_hz
        pts = protected_points(self._cameras, self._latest, self._params)
        ns = time.time_ns()
        self._tw.dyn(FIXTURES, "sensor_msgs/PointCloud2", pointcloud2(pts, ns), ns)

    def close(self) -> None:
        """Write everything recorded, the MCAP summary and footer, and end the writer (idempotent)."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None
            with self._lock:
                if not self._fh.closed:
                    self.describe({"ticks_recorded": self.ticks_recorded, "ticks_lost": self.ticks_lost,
                                   "snapshots_dropped": self.snapshots_dropped})
                    try:
                        self._w.add_metadata("pointfence/run", {k: json.dumps(v) for k, v in self._meta.items()})
                        self._w.finish()
                    except (OSError, ValueError) as e:
                        self.write_error = f"recording {self.path}: {e}"
                    self._fh.close()

    # --- reading (what the in-memory recorder gives) -------------------------------------------------
    def __getattr__(self, name):
        if name in ("count", "rows", "inputs", "masters", "robots", "masters_world", "holds", "arrays", "ticks",
                    "column", "write_csv", "save_inputs") and self.__dict__.get("memory") is not None:
            return getattr(self.memory, name)
        raise AttributeError(f"McapRecorder has no {name!r} (a run recorded only to {self.__dict__.get('path')}: "
                             "read it with pointfence.service.mcap_read)")


def config_text(cfg) -> str:
    """The TOML text ``cfg`` was read from (its file, or the embedded defaults), kept in the
    recording so that a replay needs no configuration file."""
    from .config import embedded_defaults

    p = Path(cfg.path) if cfg.path else None
    return p.read_text() if p is not None and p.is_file() else embedded_defaults()


class _Frame:
    """A recorded frame's images, for the fixture cloud."""

    def __init__(self, depth, color, mask, T_world_cam):
        self.depth, self.color, self.mask, self.T_world_cam = depth, color, mask, T_world_cam


__all__ = ["McapRecorder", "config_text", "FORMAT", "VERSION"]
