"""ROS 2 telemetry for RViz and Foxglove (``[ros2] telemetry``, ``serve|demo --ros2-telemetry``):
the service's side. The ROS side is a child process (``telemetry_node``, ``python -m
pointfence.service.ros2.telemetry_node``) that runs rclpy and publishes; this module hands it
the ticks and the frames through shared memory, as the MCAP recorder hands its writer process
(``mcap_record``, ``mcap_shm``), so the service's process does no per-message Python and never
waits on ROS.

Three sides, and what each may do:

* the 1 kHz tick (``write``, from ``Service.publish``): on one tick in ``every`` (the loop rate
  over ``telemetry_rate_hz``: ticks with ``k % every == 0``, the same ticks the recording's
  decimated pose topics hold when the rates match) it copies the few fields telemetry needs
  (``FIELDS``) into a row of the telemetry ring (``mcap_shm.TickBlock``: the tick writes row j,
  then ``WRITTEN`` = j + 1; the child reads rows below it and sets ``CONSUMED``). Preallocated
  views, no encoding, no lock, no allocation. A full ring (the child more than ``RING_S`` seconds of rows
  behind, or gone) drops the row and counts it (``rows_lost``); the tick never waits.
* the frame feeder's ingest side (``offer_snapshot``, chained after the recorder's on
  ``frames._FeedBase.on_snapshot``): at most ``cloud_rate_hz`` times a second, every
  ``CLOUD_STRIDE``-th pixel of each frame the snapshot was built from (after the robot
  self-filter) into the next entry of the frame ring (``mcap_shm.FrameBlock`` of the strided
  shapes); a full ring drops the offer (``clouds_dropped``). Never blocks.
* the child: publishes the newest row at ``telemetry_rate_hz`` and the newest frame entry's
  fixture cloud (``fixture_cloud.protected_points``, as the recording's) at ``cloud_rate_hz``;
  see ``telemetry_node`` for the topics.

A child that dies (killed, a DDS failure) stops telemetry and nothing else: ``status()`` says
``lost`` with the reason, the rows it no longer reads count in ``rows_lost``, and the loop runs
on. Stamps are the loop clock mapped to wall-clock time through ``epoch_ns`` (the recording's
when there is one), as the recording's: a live run and its recording carry the same stamps.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
from typing import Optional

import numpy as np

from pointfence.kernels.errors import BackendUnavailable, InputError

from .. import mcap_shm
from ..child_pipe import end, send

#: seconds of sampled ticks the ring holds (the child publishes the newest, so depth only covers
#: its hiccups on a loaded machine)
RING_S = 2.0
#: pixels between two sampled pixels of a frame, both ways (the recording's fixture cloud's)
CLOUD_STRIDE = 4
#: frame-ring entries (the child wants the newest; two let the ingest side fill one while the
#: child reads the other)
CLOUD_SLOTS = 2
#: the child's counters in the tick block's header (after mcap_shm's WRITTEN .. SNAPS_CONSUMED):
#: rows it read, rows it published, clouds published, points of the last cloud, its heartbeat
CONSUMED = mcap_shm.FLUSHED
ROWS_READ, PUBLISHED, CLOUDS, CLOUD_POINTS, BEAT = 7, 8, 9, 10, 11
#: the service's: the wall clock (ns) at loop-clock 0, set before any row that uses it
EPOCH = 12
#: seconds ``close`` waits for the child to end
CLOSE_TIMEOUT_S = 5.0
#: niceness increment of the child (it yields to the service's threads on a busy machine)
CHILD_NICE = 5

#: (struct, field, values per arm; 0: a scalar) of a telemetry row, in column order: positions (3,
#: m), orientations (4, w x y z), angles (1, rad; NaN: none this tick)
FIELDS = (("in", "k", 0), ("in", "now", 0), ("in", "architecture", 0), ("in", "haptics", 0), ("in", "teleop", 0),
          ("in", "pedal", 1), ("in", "master_ok", 1), ("in", "robot_fault", 1), ("in", "robot_pos", 3),
          ("in", "robot_orientation", 4), ("in", "robot_jaw", 1), ("in", "master_pos", 3),
          ("in", "master_orientation", 4), ("in", "grasp", 1),
          ("out", "xm", 3), ("out", "hip", 3), ("out", "proxy", 3), ("out", "force", 3), ("out", "command", 3),
          ("out", "orientation", 4), ("out", "jaw", 1),
          ("out", "state", 1), ("out", "gain", 1), ("out", "coupled", 1), ("out", "hold", 0), ("out", "arm_hold", 1))


class TelemetryLayout:
    """Columns of a telemetry row for ``n`` arms: ``cols[name]`` = (first column, values); every
    value is a float64 (exact for bools, hold bits and tick numbers below 2^53)."""

    def __init__(self, n: int):
        self.n = int(n)
        self.cols: dict = {}
        self._per_arm: dict = {}
        c = 0
        for _, name, per_arm in FIELDS:
            k = per_arm * self.n if per_arm else 1
            self.cols[name] = (c, k)
            self._per_arm[name] = per_arm
            c += k
        self.width = c

    def get(self, row: np.ndarray, name: str):
        """Field ``name`` of ``row``: a float (scalars), an (n,), (n, 3) or (n, 4) view."""
        c, k = self.cols[name]
        per_arm = self._per_arm[name]
        if per_arm == 0:
            return float(row[c])
        return row[c: c + k].reshape(self.n, per_arm) if per_arm > 1 else row[c: c + k]


def strided_shape(height: int, width: int, stride: int = CLOUD_STRIDE) -> tuple:
    """The shape of ``image[::stride, ::stride]`` for an image of ``height`` x ``width``."""
    return (-(-int(height) // stride), -(-int(width) // stride))


class Telemetry:
    """The service's side of ROS 2 telemetry for ``n`` arms (see the module docstring).

    ``table``: the ``[ros2]`` settings (``settings.Ros2Table``); ``loop_rate_hz``: the haptic
    loop's rate; ``radius``: the fixture radius (m, the proxy markers' size); ``workspace``: the
    world box (``kernels.params.Workspace``, its marker); ``env``: the child's environment
    (default: this process's, whose ROS 2 variables choose the DDS domain and discovery range).
    Starts the child at once; ``attach`` gives it the cameras and frames; ``close()`` ends it."""

    def __init__(self, table, n: int, loop_rate_hz: float, radius: float, workspace, env: Optional[dict] = None,
                 capacity: Optional[int] = None):
        rate = float(table.telemetry_rate_hz)
        if not 0 < rate <= loop_rate_hz:
            raise InputError(f"[ros2] telemetry_rate_hz = {rate:g}; expected 0 < rate <= the loop rate "
                             f"{loop_rate_hz:g} Hz (telemetry samples ticks)")
        self.table = table
        self.n = int(n)
        self.capacity = int(capacity) if capacity is not None else max(16, math.ceil(rate * RING_S))
        self.every = max(1, int(round(loop_rate_hz / rate)))
        self.layout = TelemetryLayout(self.n)
        self.epoch_ns = time.time_ns()
        self.rows_sent = self.rows_lost = 0
        self.clouds_offered = self.clouds_dropped = 0
        self._next = 0
        self._closed = False
        self._cloud_next = 0.0
        self._cloud_period = 1.0 / float(table.cloud_rate_hz)
        self._frames: Optional[mcap_shm.FrameBlock] = None
        self._frame_path: Optional[str] = None
        self._snaps = 0
        self._chained = None
        self._beat_seen = (-1, time.monotonic())
        self._tick_path, buf = mcap_shm.create(mcap_shm.TickBlock.nbytes(self.capacity, self.layout.width),
                                               "pointfence-telemetry-")
        self._block = mcap_shm.TickBlock(buf, self.capacity, self.layout.width)
        self._hdr = self._block.header
        # a staging row the tick fills through preallocated views (arrays) and columns (scalars),
        # then copies whole into the ring slot (as tick_cdr.TickRows: cheaper than a view per field)
        self._stage = np.zeros(self.layout.width)
        self._arrays, self._scalars = {"in": [], "out": []}, {"in": [], "out": []}
        for part, name, per_arm in FIELDS:
            c, k = self.layout.cols[name]
            if per_arm:
                v = self._stage[c: c + k]
                self._arrays[part].append((name, v.reshape(self.n, per_arm) if per_arm > 1 else v))
            else:
                self._scalars[part].append((name, c))
        self._rows = [self._block.rows[s] for s in range(self.capacity)]
        self._hdr[EPOCH] = self.epoch_ns
        self._log = tempfile.TemporaryFile(prefix="pointfence-telemetry-log-")
        try:
            self._proc = subprocess.Popen([sys.executable, "-m", "pointfence.service.ros2.telemetry_node"],
                                          stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=self._log,
                                          close_fds=True, env=None if env is None else {**os.environ, **env})
        except OSError as e:
            self._log.close()
            os.unlink(self._tick_path)
            raise InputError(f"cannot start the ROS 2 telemetry process ({e}); check that {sys.executable} runs") \
                from None
        self._error: Optional[str] = None
        ws = workspace
        self._send(("init", {"tick_path": self._tick_path, "n": self.n, "capacity": self.capacity,
                             "cols": self.layout.cols, "width": self.layout.width, "rate_hz": rate,
                             "cloud_rate_hz": float(table.cloud_rate_hz),
                             "cloud_max_points": int(table.cloud_max_points), "frame_id": table.frame_id,
                             "namespace": table.namespace, "radius": float(radius),
                             "arrow_m_per_n": float(table.force_arrow_m_per_n),
                             "workspace": (tuple(map(float, ws.min)), tuple(map(float, ws.max))),
                             "nice": CHILD_NICE, "parent_pid": os.getpid()}))

    # --- the tick's side --------------------------------------------------------------------------
    def write(self, inp, out) -> None:
        """One tick (``Service.publish``): on sampled ticks a copy into the shared ring, else nothing."""
        if inp.k % self.every:
            return
        j = self._next
        if j - self._hdr[CONSUMED] >= self.capacity:
            self.rows_lost += 1
            return
        st = self._stage
        for obj, part in ((inp, "in"), (out, "out")):
            for name, view in self._arrays[part]:
                view[...] = getattr(obj, name)
            for name, c in self._scalars[part]:
                st[c] = getattr(obj, name)
        self._rows[j % self.capacity][:] = st
        self._next = j + 1
        self._hdr[mcap_shm.WRITTEN] = j + 1     # (after the row: the child reads rows below it)
        self.rows_sent += 1

    # --- set-up, the ingest side ------------------------------------------------------------------
    def attach(self, feeder, cfg, clock_now=None, epoch_ns: Optional[int] = None) -> None:
        """Take frames from ``feeder`` (``frames._FeedBase``; chained after a callback already on
        its ``on_snapshot``, the recorder's), the cameras and pipeline parameters of ``cfg``, and
        the loop clock (``clock_now()``, s) whose 0 maps to ``epoch_ns`` (default: now minus
        ``clock_now()``; pass the recording's to share its stamps). Call before the feeder builds
        its first snapshot."""
        if epoch_ns is not None:
            self.epoch_ns = int(epoch_ns)
        elif clock_now is not None:
            self.epoch_ns = time.time_ns() - int(round(clock_now() * 1e9))
        self._hdr[EPOCH] = self.epoch_ns       # (before the loop's first row: the child stamps rows with it)
        from dataclasses import replace

        s = CLOUD_STRIDE
        cameras = [c.camera for c in cfg.cameras]
        # the strided image is the image of a camera whose pixels are s times larger
        small = [replace(c, width=w, height=h, fx=c.fx / s, fy=c.fy / s, cx=c.cx / s, cy=c.cy / s)
                 for c, (h, w) in zip(cameras, [strided_shape(c.height, c.width) for c in cameras])]
        shapes = [(c.height, c.width) for c in small]
        self._frame_path, buf = mcap_shm.create(mcap_shm.FrameBlock.nbytes(shapes, CLOUD_SLOTS),
                                                "pointfence-telemetry-frames-")
        self._frames = mcap_shm.FrameBlock(buf, shapes, CLOUD_SLOTS)
        self._full_shapes = [(c.height, c.width) for c in cameras]
        self._send(("frames", self._frame_path, shapes, CLOUD_SLOTS, small, cfg.pipeline))
        self._chained = feeder.on_snapshot
        feeder.on_snapshot = self.offer_snapshot

    def offer_snapshot(self, seq: int, frames) -> None:
        """Snapshot ``seq`` was built from ``frames``: the callback chained before this one
        first (the recorder's), then, at most ``cloud_rate_hz`` times a second, the frames'
        strided images into the next frame-ring entry. Never blocks; a full ring drops it."""
        if self._chained is not None:
            self._chained(seq, frames)
        now = time.monotonic()
        fb = self._frames
        if fb is None or now < self._cloud_next:
            return
        self._cloud_next = now + self._cloud_period
        self.clouds_offered += 1
        if self._snaps - self._hdr[mcap_shm.SNAPS_CONSUMED] >= fb.slots or any(
                f.depth.shape != shape for f, shape in zip(frames, self._full_shapes)):
            self.clouds_dropped += 1
            return
        slot, s = self._snaps % fb.slots, CLOUD_STRIDE
        fb.meta[slot, 0] = seq
        for i, f in enumerate(frames):
            e = fb.cam_meta(slot, i)
            np.copyto(fb.depth[slot][i], f.depth[::s, ::s])
            if f.color is not None:
                np.copyto(fb.color[slot][i], f.color[::s, ::s], casting="unsafe")
            if f.mask is not None:
                np.copyto(fb.mask[slot][i], f.mask[::s, ::s], casting="unsafe")
            e[mcap_shm.NEW], e[mcap_shm.FSEQ], e[mcap_shm.STAMP] = 1, f.seq, f.timestamp
            e[mcap_shm.COLOR], e[mcap_shm.MASK] = f.color is not None, f.mask is not None
            e[mcap_shm.POSE:] = math.nan if f.T_world_cam is None else np.asarray(f.T_world_cam, float).ravel()
        self._snaps += 1
        self._hdr[mcap_shm.SNAPS_WRITTEN] = self._snaps     # (after the entry)

    # --- the child --------------------------------------------------------------------------------
    def _send(self, msg: tuple) -> None:
        """A control message to the child (never from the tick); a child gone is reported."""
        if self._closed or self._proc.poll() is not None:
            return
        try:
            send(self._proc.stdin, msg)
        except (BrokenPipeError, OSError) as e:
            self._error = self._error or f"ROS 2 telemetry: the publisher process is gone ({e})"

    def _log_tail(self) -> str:
        try:
            self._log.seek(0)
            lines = [ln for ln in self._log.read().decode(errors="replace").splitlines() if ln.strip()]
        except (OSError, ValueError):
            return ""
        return lines[-1].strip() if lines else ""

    @property
    def pid(self) -> int:
        """The publisher process's id."""
        return self._proc.pid

    @property
    def alive(self) -> bool:
        return self._proc.poll() is None

    @property
    def error(self) -> Optional[str]:
        """Why telemetry stopped (None: it runs, or it was closed)."""
        rc = self._proc.poll()
        if rc is None or (self._closed and rc == 0):
            return self._error
        how = f"signal {-rc}" if rc < 0 else f"exit status {rc}"
        tail = self._log_tail()
        return (f"ROS 2 telemetry lost: its publisher process (pid {self._proc.pid}) ended ({how})"
                + (f": {tail}" if tail else "") + "; the haptic loop runs on without telemetry (restart the service "
                "to get it back)")

    def wait_ready(self, timeout: float = 20.0) -> bool:
        """Wait until the publisher process runs (its node made, its first cycle done) or has
        ended, at most ``timeout`` s; whether it runs. The service never needs to (the tick
        samples into the ring from its first tick on); benches and tests use it to keep rclpy's
        start-up out of the seconds they measure."""
        end = time.monotonic() + timeout
        while self._hdr[BEAT] == 0 and self.alive and time.monotonic() < end:
            time.sleep(0.01)
        return self.alive and self._hdr[BEAT] > 0

    def status(self) -> dict:
        """Telemetry's health and counts for the service's status: ``lost`` (the publisher
        process ended while the service runs), ``stalled_s`` (seconds since its last heartbeat
        was seen to move), rows sampled, lost and published, clouds."""
        beat, now = int(self._hdr[BEAT]), time.monotonic()
        if beat != self._beat_seen[0]:
            self._beat_seen = (beat, now)
        alive = self.alive
        return {"lost": not alive and not self._closed, "publisher_alive": alive, "publisher_pid": self._proc.pid,
                "error": self.error, "every_ticks": self.every, "rows_sent": self.rows_sent,
                "rows_lost": self.rows_lost, "rows_read": int(self._hdr[ROWS_READ]),
                "messages_published": int(self._hdr[PUBLISHED]), "clouds_published": int(self._hdr[CLOUDS]),
                "cloud_points": int(self._hdr[CLOUD_POINTS]), "clouds_dropped": self.clouds_dropped,
                "stalled_s": round(now - self._beat_seen[1], 3)}

    def close(self) -> None:
        """End the publisher process (idempotent; waits up to ``CLOSE_TIMEOUT_S``, then kills it)
        and remove the shared memory."""
        if self._closed:
            return
        self._send(("close",))
        self._closed = True
        end(self._proc, CLOSE_TIMEOUT_S)
        self._log.close()
        for p in (self._tick_path, self._frame_path):
            if p is not None:
                try:
                    os.unlink(p)
                except FileNotFoundError:
                    pass


def start_telemetry(cfg, n: int, workspace=None) -> Telemetry:
    """The ``Telemetry`` of a live run of ``cfg`` (its ``[ros2]`` table) with ``n`` arms; a
    ``BackendUnavailable`` that says how to install ROS 2 where rclpy or the message packages
    are missing (looked up, not imported: the service's process never loads rclpy)."""
    import importlib.util

    from . import dds

    missing = [m for m in ("rclpy", "geometry_msgs", "sensor_msgs", "std_msgs", "visualization_msgs")
               if importlib.util.find_spec(m) is None]
    if missing:
        raise BackendUnavailable(f"ROS 2 telemetry needs {', '.join(missing)}, not installed here; {dds.INSTALL_HINT}")
    return Telemetry(cfg.ros2, n, cfg.service.rate_hz, cfg.pipeline.radius.r_base,
                     workspace if workspace is not None else cfg.pipeline.workspace)


__all__ = ["Telemetry", "TelemetryLayout", "start_telemetry", "strided_shape", "FIELDS", "RING_S", "CLOUD_STRIDE"]
