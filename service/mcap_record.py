"""Recording a live run to MCAP with ROS 2 message schemas (``pointfence serve|demo --record
FILE.mcap``), streamed to disk while the run goes on (S8).

Three sides, and what each may do:

* the 1 kHz tick (``write``, ``note_tick_us``): copies its ``TickInput`` and ``TickOutput`` into
  a row of the tick ring in shared memory (``mcap_shm.TickBlock``, ``tick_cdr.TickRows``); no
  encoding, no I/O, no allocation, no lock. A tick that finds the ring full (the writer more
  than ``capacity`` ticks behind, or gone) is not recorded and counts in ``ticks_lost``.
* the frame feeder's ingest side (``offer_snapshot``, called by ``frames._FeedBase`` after each
  snapshot is built, with the frames it was built from, after the robot self-filter): copies
  the frames it has not seen into the next entry of the frame ring in shared memory
  (``mcap_shm.FrameBlock``) and returns; a full ring drops the snapshot and counts it
  (``snapshots_dropped``): a replay then says which snapshot is missing.
* the writer **process** (``mcap_writer``, ``python -m pointfence.service.mcap_writer``): every
  ``flush_s`` (<= 0.5 s) it encodes what the others left (every tick's input and output, the
  decimated poses and wrenches, events, depth as a raw 16UC1 ``sensor_msgs/Image`` with its
  ``CameraInfo``, colour (rgb8) and mask (mono8) images, the snapshot table, the fixture cloud at
  ``cloud_hz``; the chunks' zstd compresses it all losslessly),
  ends the MCAP chunk and fsyncs. Being another process, its encoding never takes the service's
  interpreter lock. A ``kill -9`` of the service: the writer sees its control pipe end, writes
  what the rings hold and closes the file (a ``pointfence/end`` metadata record says so). A
  ``kill -9`` of both: every chunk written before it stays readable with
  ``mcap_read.open_recording`` (all but the last ``flush_s`` and the chunk being written). A
  writer that dies is reported by ``status()`` (and ``write_error``); the tick never waits for
  it, its ticks then count in ``ticks_lost`` once the ring is full.

Stamps and log times are the loop clock mapped to wall-clock time: ``epoch_ns`` (in the
``pointfence/recording`` metadata) is the wall clock at loop-clock 0; a frame's capture
timestamp goes through the feeder's loop-clock offset where it has one.

``add_metadata(name, values)`` adds a metadata record of the caller's (end-of-run measures, ...),
read back as ``mcap_read.Recording.metadata[name]``.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from . import mcap_shm
from .child_pipe import end, send
from .tick_cdr import TickLayout, TickRows

FORMAT = "pointfence mcap recording"
VERSION = 1
#: ring rows (16 s at 1 kHz: the writer may fall that far behind, e.g. short of CPU on a loaded
#: machine where the service's SCHED_FIFO threads come first; 7 MB for one arm)
RING = 16384
#: snapshot entries waiting for the writer (2 s of a 30 Hz camera; 1.8 MB of shared memory an
#: entry for a 640x480 camera: depth, colour and mask)
MAX_PENDING = 64
#: metadata names the recorder writes itself
RESERVED = ("pointfence/run", "pointfence/end")
#: seconds ``close`` waits for the writer to write the rest and exit
CLOSE_TIMEOUT_S = 60.0


class McapRecorder:
    """See the module docstring. ``keep`` > 0 also keeps that many ticks in memory
    (``record.Recorder``) for what reads a finished run's arrays (the demo's report). ``nice``:
    the writer process's niceness increment (0: the service's own priority)."""

    streaming = True

    def __init__(self, path, n: int = 1, keep: int = 0, capacity: int = RING, flush_s: float = 0.25,
                 pose_hz: float = 100.0, cloud_hz: float = 2.0, rate_hz: float = 1000.0, nice: int = 0,
                 joint_hz: Optional[float] = None):
        if not 0 < flush_s <= 0.5:
            raise InputError(f"McapRecorder: flush_s = {flush_s!r}; expected 0 < flush_s <= 0.5 s (S8: a crash may "
                             "lose at most the last second)")
        self.path = Path(path)
        self.n, self.capacity, self.flush_s = int(n), int(capacity), float(flush_s)
        self.rate_hz, self.pose_hz, self.cloud_hz = float(rate_hz), float(pose_hz), float(cloud_hz)
        self.joint_hz = self.pose_hz if joint_hz is None else float(joint_hz)
        if not (self.joint_hz >= 0 and math.isfinite(self.joint_hz)):
            raise InputError(f"McapRecorder: joint_hz = {joint_hz!r}; expected a rate >= 0 Hz (0: no joint topics; "
                             f"the tick rate {self.rate_hz:g} Hz or more: every tick)")
        self.layout = TickLayout(self.n)
        from .record import Recorder

        self.memory = Recorder(keep, self.n) if keep else None
        self._next = 0
        self.ticks_recorded = self.ticks_lost = 0
        self.full = False
        self.snapshots_dropped = 0
        self._error: Optional[str] = None
        self.epoch_ns = time.time_ns()
        self._last_frame: list = []        # per camera: the last frame object offered
        self._index: list = []
        self._frames: Optional[mcap_shm.FrameBlock] = None
        self._frame_path: Optional[str] = None
        self._snaps = 0
        self._feeder = None
        self._closed = False
        self._sealed = False
        self._syncs = 0
        self._joints: Optional[mcap_shm.JointBlock] = None    # (note_start: where a robot has joints)
        self._joint_path: Optional[str] = None
        self._joint_fill: list = []       # (arm, the robot's measured_jp_into)
        self._joint_every = 1
        self._joint_stage: Optional[np.ndarray] = None     # (arms, dof): joints taken for tick _joint_staged
        self._joint_staged = -1
        self._grasper = None              # (record_grasper: the GrasperHost, its ring, every how many ticks)
        self._grasper_path: Optional[str] = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            out = self.path.open("wb")
        except OSError as e:
            raise InputError(f"cannot write the recording {str(self.path)!r} ({e.strerror or e}); choose a FILE.mcap "
                             "in a folder you may write to") from None
        self._tick_path, buf = mcap_shm.create(mcap_shm.TickBlock.nbytes(self.capacity, self.layout.width),
                                               "pointfence-ticks-")
        self._ticks = mcap_shm.TickBlock(buf, self.capacity, self.layout.width)
        self._hdr = self._ticks.header
        self.data = self._ticks.rows
        self._fill = TickRows(self.layout, self.data)
        try:
            self._proc = subprocess.Popen([sys.executable, "-m", "pointfence.service.mcap_writer"],
                                          stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                          pass_fds=(out.fileno(),), close_fds=True)
        finally:
            fd = out.fileno()
            out.close()          # (the writer holds its own copy of the descriptor)
        self._send(("init", {"path": str(self.path), "fd": fd, "tick_path": self._tick_path, "n": self.n,
                             "capacity": self.capacity, "flush_s": self.flush_s, "rate_hz": self.rate_hz,
                             "pose_hz": self.pose_hz, "cloud_hz": self.cloud_hz, "epoch_ns": self.epoch_ns,
                             "nice": int(nice)}))
        self.describe({"format": FORMAT, "version": VERSION, "arms": self.n, "rate_hz": self.rate_hz,
                       "pose_hz": self.pose_hz, "cloud_hz": self.cloud_hz, "flush_s": self.flush_s})

    # --- the tick's side ------------------------------------------------------------------------
    def write(self, inp, out) -> None:
        """Record one tick (``Service.publish``): a copy into the shared ring, nothing else."""
        if self.memory is not None:
            self.memory.write(inp, out)
        j = self._next
        if j - self._hdr[mcap_shm.FLUSHED] >= self.capacity:
            self.full = True
            self.ticks_lost += 1
            return
        self.full = False
        slot = j % self.capacity
        self._fill.fill(inp, out, slot)
        js = self._joints
        if js is not None:
            k = inp.k
            if k % self._joint_every == 0:          # the joints this tick read: taken at the end of the one before
                js.rows[slot] = self._joint_stage if self._joint_staged == k else math.nan
            if (k + 1) % self._joint_every == 0:
                stage = self._joint_stage
                for b, fill in self._joint_fill:
                    fill(stage[b])
                self._joint_staged = k + 1
        g = self._grasper
        if g is not None and inp.k % g[2] == 0:    # the grasper's latest estimate (a copy, no allocation)
            g[0].copy_into(g[1].rows[slot, 0])
        self._next = j + 1
        self._hdr[mcap_shm.WRITTEN] = j + 1        # (after the row: the writer reads rows below it)
        self.ticks_recorded += 1

    def note_tick_us(self, us: float) -> None:
        """The loop's compute time of the tick just recorded (us)."""
        if self.memory is not None:
            self.memory.note_tick_us(us)
        if self._next > 0 and not self.full:
            self.data[(self._next - 1) % self.capacity, self._fill.tick_us_col] = us

    # --- set-up (before the run), metadata ------------------------------------------------------------
    def describe(self, meta: dict, snapshot_frames=None) -> None:
        """Run facts for the ``pointfence/run`` metadata (JSON values): architecture, backend,
        cameras, ... (``snapshot_frames`` is the .pfrec recorder's; here the frames come through
        ``offer_snapshot``)."""
        self._send(("meta", "pointfence/run", _jsonable("pointfence/run", meta)))

    def add_metadata(self, name: str, values: dict) -> None:
        """Add a metadata record ``name`` holding ``values`` (str keys, JSON-serialisable values:
        numbers, strings, lists, dicts) to the recording, e.g. the end-of-run measures; call it
        from any thread but the tick's, before ``close()``. It reaches the file at the writer's
        next flush (<= ``flush_s``) and reads back as ``mcap_read.Recording.metadata[name]``
        (the same dict). A second call with the same name adds a second record; the reader keeps
        the newest value of each key. Raises InputError for a reserved or empty name, values that
        are not a dict of JSON values, or a closed recording."""
        if not isinstance(name, str) or not name or name in RESERVED:
            raise InputError(f"add_metadata: name {name!r}; expected a non-empty string other than {RESERVED} "
                             "(e.g. 'pointfence/measures')")
        if not isinstance(values, dict):
            raise InputError(f"add_metadata({name!r}): values is a {type(values).__name__}; expected a dict")
        if self._closed:
            raise InputError(f"add_metadata({name!r}): the recording {self.path} is closed; add metadata before "
                             "close()")
        self._send(("meta", name, _jsonable(name, values)))

    def attach(self, feeder, cfg, clock_now=None, config_text: Optional[str] = None) -> None:
        """Take frames from ``feeder`` (``frames._FeedBase``: its ``on_snapshot``), the camera
        models and pipeline parameters of ``cfg``, and the loop clock (``clock_now()``, s) whose
        0 maps to ``epoch_ns``. Call before the feeder builds its first snapshot."""
        if clock_now is not None:
            self.epoch_ns = time.time_ns() - int(round(clock_now() * 1e9))
            self._send(("epoch", self.epoch_ns))
        self._feeder = feeder
        cameras = [c.camera for c in cfg.cameras]
        self._last_frame = [None] * len(cameras)
        self._index = [-1] * len(cameras)     # running number of each camera's recorded frames
        shapes = [(c.height, c.width) for c in cameras]
        self._frame_path, buf = mcap_shm.create(mcap_shm.FrameBlock.nbytes(shapes, MAX_PENDING), "pointfence-frames-")
        self._frames = mcap_shm.FrameBlock(buf, shapes, MAX_PENDING)
        self._send(("frames", self._frame_path, shapes, MAX_PENDING, cameras, cfg.pipeline))
        cams = [{"name": c.name, "width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                 "depth_scale": c.depth_scale, "T_world_cam": np.asarray(c.T_world_cam, float).ravel().tolist(),
                 "dist": [float(x) for x in c.dist], "noise": {"a": c.noise.a, "b": c.noise.b}, "z_min": c.z_min,
                 "z_max": c.z_max, "max_code": c.max_code, "depth_step_inv": c.depth_step_inv,
                 "near_reading": bool(c.near_reading), "source": cc.source, "rate_hz": cc.rate_hz}
                for c, cc in zip(cameras, cfg.cameras)]
        self.describe({"epoch_ns": self.epoch_ns, "cameras": cams, "config": config_text,
                       "config_path": cfg.path})
        feeder.on_snapshot = self.offer_snapshot

    def note_start(self, service) -> None:
        """The state ``Service.start`` read (masters, robots, control), for a replay's start, and
        the robots whose joints are recorded (``record_joints``). Call before the first tick."""
        inp = service.inp
        jaw = [None if j != j else j for j in inp.robot_jaw.tolist()]          # (NaN: unknown)
        jawed = dict(service.devices.jawed)
        self.describe({"start": {"master_pos": inp.master_pos.tolist(), "pedal": inp.pedal.tolist(),
                                 "master_ok": inp.master_ok.tolist(), "robot_pos": inp.robot_pos.tolist(),
                                 "robot_present": inp.robot_present.tolist(), "haptics": bool(service.haptics_on),
                                 "teleop": bool(service.teleop_on), "architecture": service.architecture,
                                 "master_orientation": inp.master_orientation.tolist(), "grasp": inp.grasp.tolist(),
                                 "robot_orientation": inp.robot_orientation.tolist(), "robot_jaw": jaw,
                                 "jaw_range": [list(jawed[b].jaw_limits) if b in jawed else None
                                               for b in range(service.n)]}})
        self.record_joints(service.robots)
        if getattr(service, "grasper", None) is not None:
            self.record_grasper(service.grasper)

    def record_joints(self, robots) -> None:
        """Record the measured joints of ``robots`` (one per arm, None: an ideal robot) as
        ``sensor_msgs/JointState`` on ``/<arm>/measured_js`` (CRTK) at ``joint_hz``, every
        ``rate_hz / joint_hz``-th tick: the joints the robot reported when that tick read it, so
        that their forward kinematics is the tick's ``/<arm>/measured_cp``. A robot's state moves
        on in its step (in the tick's write), so the tick before takes them at its end
        (``measured_jp_into``, rad or m, into a staging row) and the tick puts them into the joint
        ring beside its own row; a tick whose previous tick ran no recorder write (the first, or
        one after missed periods) has none (NaN: no message). Robots without a joint model
        are left out: an ideal robot, and the point mass, whose three prismatic "joints" are its
        tool position (``measured_cp`` already). Call before the first tick, once."""
        if self._joints is not None or self.joint_hz <= 0 or self._closed:
            return
        arms = [(b, r) for b, r in enumerate(robots) if b < self.n and _has_joints(r)]
        if not arms:
            return
        dof = max(int(r.dof) for _, r in arms)
        names = {b: [str(x) for x in r.joint_names] for b, r in arms}
        self._joint_every = max(1, int(round(self.rate_hz / min(self.joint_hz, self.rate_hz))))
        self._joint_path, buf = mcap_shm.create(mcap_shm.JointBlock.nbytes(self.capacity, self.n, dof),
                                                "pointfence-joints-")
        self._joints = mcap_shm.JointBlock(buf, self.capacity, self.n, dof)
        self._joint_stage = np.full((self.n, dof), math.nan)
        self._joint_fill = [(b, r.measured_jp_into) for b, r in arms]
        self._send(("joints", self._joint_path, dof, {str(b): v for b, v in names.items()}, self._joint_every))

    def record_grasper(self, grasper) -> None:
        """Record the ``[cable]`` grasper's estimate (``cable_grasper.GrasperHost``: jaw, torques,
        tension, faults; ``mcap_topics.GrasperTopics``) at ``joint_hz``: every ``rate_hz /
        joint_hz``-th tick copies its latest values (``copy_into``) into a ring beside its row.
        Call before the first tick, once."""
        from .cable_grasper import RECORD_FIELDS

        if self._grasper is not None or self.joint_hz <= 0 or self._closed:
            return
        every = max(1, int(round(self.rate_hz / min(self.joint_hz, self.rate_hz))))
        self._grasper_path, buf = mcap_shm.create(mcap_shm.JointBlock.nbytes(self.capacity, 1, len(RECORD_FIELDS)),
                                                  "pointfence-grasper-")
        block = mcap_shm.JointBlock(buf, self.capacity, 1, len(RECORD_FIELDS))
        block.rows[:] = math.nan
        self._grasper = (grasper, block, every)
        self._send(("grasper", self._grasper_path, int(grasper.arm), every, tuple(RECORD_FIELDS)))

    # --- the ingest side ------------------------------------------------------------------------------
    def _clock_minus_stamp(self) -> float:
        cms = getattr(self._feeder, "clock_minus_stamp", None)
        if cms is None:
            t0 = getattr(self._feeder, "_t0", None) or [getattr(self._feeder, "t0", 0.0)]
            cms = -float(t0[0])
        return float(cms)

    def offer_snapshot(self, seq: int, frames) -> None:
        """Snapshot ``seq`` was built from ``frames`` (one per camera): the frames not offered
        before are copied into the next frame-ring entry for the writer; never blocks. A full
        ring, or a frame not of its camera's size, drops the snapshot (``snapshots_dropped``)."""
        fb = self._frames
        if self._sealed:                 # (the run's last tick is recorded: a later snapshot served none)
            return
        if fb is None or self._snaps - self._hdr[mcap_shm.SNAPS_CONSUMED] >= fb.slots:
            self.snapshots_dropped += 1
            return
        slot = self._snaps % fb.slots
        for i, f in enumerate(frames):
            if f is not self._last_frame[i] and f.depth.shape != fb.shapes[i]:
                self.snapshots_dropped += 1
                self._error = self._error or (f"camera {f.camera!r}: a frame of {f.depth.shape} while the recording "
                                              f"expects {fb.shapes[i]} (its camera model); such snapshots are dropped")
                return
        cms = self._clock_minus_stamp()
        fb.meta[slot, 0] = seq
        for i, f in enumerate(frames):
            e = fb.cam_meta(slot, i)
            new = f is not self._last_frame[i]
            if new:
                self._last_frame[i] = f
                self._index[i] += 1
                np.copyto(fb.depth[slot][i], f.depth)
                if f.color is not None:
                    np.copyto(fb.color[slot][i], f.color, casting="unsafe")
                if f.mask is not None:
                    np.copyto(fb.mask[slot][i], f.mask, casting="unsafe")
            e[mcap_shm.NEW] = new
            e[mcap_shm.FSEQ], e[mcap_shm.INDEX], e[mcap_shm.STAMP], e[mcap_shm.CMS] = f.seq, self._index[i], f.timestamp, cms
            e[mcap_shm.COLOR], e[mcap_shm.MASK] = f.color is not None, f.mask is not None
            e[mcap_shm.POSE:] = math.nan if f.T_world_cam is None else np.asarray(f.T_world_cam, float).ravel()
        self._snaps += 1
        self._hdr[mcap_shm.SNAPS_WRITTEN] = self._snaps     # (after the entry: the writer reads entries below it)

    # --- the writer process ---------------------------------------------------------------------------
    def _send(self, msg: tuple) -> None:
        """A control message to the writer (never from the tick); a writer gone is reported."""
        if self._closed or self._proc.poll() is not None:
            return
        try:
            send(self._proc.stdin, msg)
            self._hdr[mcap_shm.SENT] += 1       # (after the message: see mcap_shm.SENT)
        except (BrokenPipeError, OSError) as e:
            self._error = self._error or f"recording {self.path}: the writer process is gone ({e})"

    def _writer_error(self) -> Optional[str]:
        rc = self._proc.poll()
        if rc is None or (rc == 0 and self._closed):
            return None
        text = ""
        if self._proc.stderr is not None and not self._proc.stderr.closed:
            text = self._proc.stderr.read().decode(errors="replace").strip()
            self._proc.stderr.close()
            self._stderr_text = text
        text = getattr(self, "_stderr_text", text)
        how = f"signal {-rc}" if rc < 0 else f"exit status {rc}"
        return (f"recording {self.path}: the MCAP writer process (pid {self._proc.pid}) ended ({how})"
                + (f": {text.splitlines()[-1]}" if text else "")
                + "; ticks after its last flush are not recorded (ticks_lost counts them)")

    @property
    def write_error(self) -> Optional[str]:
        """What went wrong with the recording (None: nothing): the writer process ended, a disk
        error, a frame of a size the recording cannot hold."""
        return self._writer_error() or self._error

    @property
    def frames_recorded(self) -> int:
        return int(self._hdr[mcap_shm.FRAMES_RECORDED])

    @property
    def snapshots_recorded(self) -> int:
        return int(self._hdr[mcap_shm.SNAPSHOTS_RECORDED])

    def status(self) -> dict:
        """The recording's counts and health, for the service's status."""
        return {"path": str(self.path), "writer_alive": self._proc.poll() is None, "writer_pid": self._proc.pid,
                "ticks_recorded": self.ticks_recorded, "ticks_written": int(self._hdr[mcap_shm.FLUSHED]),
                "ticks_lost": self.ticks_lost, "snapshots_recorded": self.snapshots_recorded,
                "snapshots_dropped": self.snapshots_dropped, "frames_recorded": self.frames_recorded,
                "flushes": int(self._hdr[mcap_shm.BEAT]), "error": self.write_error,
                # the writer's time (s): encoding ticks, encoding frames, chunk writes and fsync,
                # its longest flush, its CPU time
                "writer_s": {k: round(int(self._hdr[i]) * 1e-6, 3) for k, i in (
                    ("ticks", mcap_shm.US_TICKS), ("frames", mcap_shm.US_FRAMES), ("sync", mcap_shm.US_SYNC),
                    ("flush_max", mcap_shm.US_FLUSH_MAX), ("cpu", mcap_shm.US_CPU))}}

    def seal(self, timeout: float = CLOSE_TIMEOUT_S) -> bool:
        """The run is over (call after its last tick, never from the tick): snapshots offered from
        now on are not recorded, and the writer writes every tick and frame handed over so far in
        whole, fsynced chunks (a flush barrier). Returns True once it has, False if the writer is
        gone or did not within ``timeout`` s. The file then reads whole with
        ``mcap_read.open_recording`` while it is still open (it has no summary yet), so that
        what is computed from it (the run's measures) can go into it with ``add_metadata``
        before ``close()``."""
        if self._closed:
            return False
        self._sealed = True
        self._syncs += 1
        self.describe({"ticks_recorded": self.ticks_recorded, "ticks_lost": self.ticks_lost,
                       "snapshots_dropped": self.snapshots_dropped})
        self._send(("sync", self._syncs))
        end = time.monotonic() + timeout
        while self._hdr[mcap_shm.SYNCED] < self._syncs:
            if self._proc.poll() is not None or time.monotonic() > end:
                return False
            time.sleep(0.002)
        return True

    def close(self) -> None:
        """Write everything recorded, the MCAP summary and footer, and end the writer process
        (idempotent; waits up to ``CLOSE_TIMEOUT_S``)."""
        if self._closed:
            return
        self.describe({"ticks_recorded": self.ticks_recorded, "ticks_lost": self.ticks_lost,
                       "snapshots_dropped": self.snapshots_dropped})
        self._send(("close",))
        self._closed = True
        if end(self._proc, CLOSE_TIMEOUT_S):
            self._error = self._error or (f"recording {self.path}: the writer did not finish within "
                                          f"{CLOSE_TIMEOUT_S} s and was killed; the file ends at its last chunk")
        self._error = self._writer_error() or self._error
        if self._proc.stderr is not None and not self._proc.stderr.closed:
            self._proc.stderr.close()
        for p in (self._tick_path, self._frame_path, self._joint_path, self._grasper_path):
            if p is not None:
                try:
                    os.unlink(p)
                except FileNotFoundError:
                    pass

    # --- reading (what the in-memory recorder gives) -------------------------------------------------
    def __getattr__(self, name):
        if name in ("count", "rows", "inputs", "masters", "robots", "masters_world", "holds", "arrays", "ticks",
                    "column", "write_csv", "save_inputs") and self.__dict__.get("memory") is not None:
            return getattr(self.memory, name)
        raise AttributeError(f"McapRecorder has no {name!r} (a run recorded only to {self.__dict__.get('path')}: "
                             "read it with pointfence.service.mcap_read)")


def _has_joints(robot) -> bool:
    """Whether ``robot``'s joints are recorded (see ``McapRecorder.record_joints``)."""
    return (robot is not None and getattr(robot, "model", None) != "point-mass" and hasattr(robot, "measured_jp_into")
            and bool(getattr(robot, "joint_names", ())) and int(getattr(robot, "dof", 0)) > 0)


def _jsonable(name: str, values: dict) -> dict:
    """``values`` checked to be a dict of JSON values (the writer stores each key's JSON text)."""
    for k, v in values.items():
        if not isinstance(k, str):
            raise InputError(f"metadata {name!r}: key {k!r} is a {type(k).__name__}; expected str keys")
        try:
            json.dumps(v)
        except (TypeError, ValueError) as e:
            raise InputError(f"metadata {name!r}: the value of {k!r} is not JSON ({e}); give numbers, strings, "
                             "lists or dicts (e.g. arr.tolist())") from None
    return dict(values)


def config_text(cfg) -> str:
    """The TOML text ``cfg`` was read from (its file, or the embedded defaults), kept in the
    recording so that a replay needs no configuration file."""
    from .config import embedded_defaults

    p = Path(cfg.path) if cfg.path else None
    return p.read_text() if p is not None and p.is_file() else embedded_defaults()


__all__ = ["McapRecorder", "config_text", "FORMAT", "VERSION"]
