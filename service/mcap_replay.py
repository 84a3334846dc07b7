"""Replaying an MCAP recording (``pointfence replay --recording FILE.mcap --out DIR``): the
recorded run's ticks again, from the recorded depth and inputs only (no camera, no haptic
device, no robot process).

Exact replay (no ``--architecture`` / ``--radius``): every tick gets its recorded
``TickInput`` (master samples, timing, frame time and age, control state; the robots' measured
positions and faults through ``RecordedRobot``), and the snapshots are rebuilt from the
recorded frames (``RecordedFrames``: every snapshot the run built, numbered as it was, in the
tick that first saw it; the frames were recorded after the robot self-filter, so the replay
filters nothing). On the same backend the ``TickOutput`` of every tick is the recorded one bit
for bit (its ``kernel_us``, a wall-clock time, aside); the replay checks this tick by tick and
says so in ``summary.json`` (``replay.exact``, ``replay.mismatched_ticks``, the first differing
tick and field). ``--backend`` alone re-runs the same inputs on another backend (still checked:
a difference is then the backends', not an error).

What-if (``--architecture`` I|II|III and/or ``--radius`` m): the same master inputs, timing and
depth under other settings; the robots are then the configured robot model simulated here
(``[robot]`` of the recorded configuration; an ideal robot where none was recorded), since a
recorded robot cannot follow other commands. Nothing is compared.

Not in a recording, so not replayed: changes made between ticks through the control API
(a new radius or selection, clear-faults) and the tick watchdog's stall flag; a replay across
one of them stops being exact there, and ``replay.first_mismatch`` shows where.
"""
from __future__ import annotations

import math
import time
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from .masters import Master
from .recorded_frames import FrameDecoder, RecordedFrames
from .replay_ticks import ReplayTicks
from .robot.base import RobotMode
from .tick_cdr import row_into
from .tick_io import TickInput

_EYE = np.eye(4)


class StartMaster(Master):
    """The master as ``Service.start`` read it in the recorded run; every tick's sample comes
    from the recording (``replay_tick`` reads no master)."""

    name = "recorded"

    def __init__(self, pos, pedal, ok, orientation=(1.0, 0.0, 0.0, 0.0), grasp=0.0):
        super().__init__()
        self._sample = (np.array(pos, float), bool(pedal), bool(ok), np.array(orientation, float), float(grasp))

    def poll(self, t: float) -> None:
        self.position[:] = self._sample[0]
        self.clutch, self.ok = self._sample[1], self._sample[2]
        self.orientation[:] = self._sample[3]
        self.grasp = self._sample[4]


class RecordedRobot:
    """A robot that reports what the recorded one measured (set per tick by the replay) and
    accepts every command (the service's ``Devices`` interface, nothing more)."""

    model = "recorded"
    fault_reason = None
    hosted = False

    def __init__(self, pos, orientation=(1.0, 0.0, 0.0, 0.0), jaw=None, jaw_limits=None):
        self.pos = np.array(pos, float)
        self.quat = np.array(orientation, float)        # w, x, y, z
        self.jaw = math.nan if jaw is None else float(jaw)
        #: the recorded arm's jaw range, where it had a jaw (then ``servo_jaw`` is accepted)
        self.jaw_limits = None if jaw_limits is None else tuple(jaw_limits)
        self.fault = False
        #: the pose (4, 4) of ``pos`` and ``quat`` where the replay set it with them (else None:
        #: ``measured_cp`` makes it)
        self.pose = None

    @property
    def state(self) -> RobotMode:
        return RobotMode.FAULT if self.fault else RobotMode.ENABLED

    def measured_cp(self, out=None):
        T = _EYE.copy() if out is None else out
        if self.pose is not None:
            T[...] = self.pose
            return T
        T[...] = poses(self.pos[None], self.quat[None])[0]
        return T

    def measured_orientation(self) -> np.ndarray:
        """The recorded orientation (w, x, y, z) as recorded (``Devices`` takes it as it is)."""
        return self.quat

    def measured_jaw(self) -> float:
        return self.jaw

    def servo_cp(self, pose) -> bool:
        return True

    def servo_jaw(self, angle) -> bool:
        return True

    def resume(self) -> None:
        pass

    def hold(self) -> None:
        pass

    def enable(self) -> None:
        pass

    def step(self, dt: float) -> None:
        pass


def poses(pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) of positions (N, 3) m and unit quaternions (N, 4) (w, x, y, z), each entry
    computed as the recorded arm's ``measured_cp`` was (the same operations in the same order)."""
    w, x, y, z = (quat[:, j] for j in range(4))
    T = np.zeros((len(pos), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    T[:, :3, 3] = pos
    T[:, 3, 3] = 1.0
    return T


def build_schedule(recording) -> dict:
    """Tick k -> snapshot seqs to build before it: every recorded snapshot up to the one tick k
    was the first to see."""
    lay = recording.layout
    rows = recording.rows
    seqs = rows[:, lay.cols[("out", "frame_seq")][0]].astype(np.int64)
    ks = rows[:, lay.cols[("in", "k")][0]].astype(np.int64)
    out, done = {}, 0
    for k, s in zip(ks, seqs):
        if s > done:
            out[int(k)] = [q for q in range(done + 1, int(s) + 1) if q in recording.snapshots or q == s]
            done = int(s)
    return out


def recording_config(recording, radius: Optional[float] = None):
    """The recorded run's ``SceneConfig``: its configuration text with the recorded camera models
    (no source is opened) and the self-filter off (the recorded frames are filtered already);
    ``radius`` (m) overrides ``[fixture] radius``."""
    from .config import parse, tomllib

    meta = recording.meta
    text = meta.get("config")
    if not text:
        raise InputError(f"{recording.path}: the recording holds no configuration (written before the run started?)")
    doc = tomllib.loads(text)
    cams = []
    for c in meta.get("cameras", []):
        if not isinstance(c, dict):      # (a camera's model is recorded with its first frame)
            raise InputError(f"{recording.path}: camera {c!r} has no recorded model (the file ends before its first "
                             "frame); record longer, past the cameras' first frames")
        cams.append({"name": c["name"], "source": c["source"], "rate_hz": c["rate_hz"], "fx": c["fx"], "fy": c["fy"],
                     "cx": c["cx"], "cy": c["cy"], "width": c["width"], "height": c["height"],
                     "depth_scale": c["depth_scale"], "T_world_cam": c["T_world_cam"], "dist": c["dist"],
                     "noise": c["noise"], "z_min": c["z_min"], "z_max": c["z_max"], "max_code": c["max_code"],
                     # (recordings before stop 38 hold neither: their cameras read as read)
                     "depth_step_inv": c.get("depth_step_inv", 0.0), "near_reading": c.get("near_reading", False)})
    if not cams:
        raise InputError(f"{recording.path}: the recording names no cameras")
    doc["camera"] = cams
    doc.setdefault("service", {})["self_filter"] = False
    if radius is not None:
        doc.setdefault("fixture", {})["radius"] = float(radius)
    return parse(doc, f"{recording.path} (recorded configuration)")


def replay(recording, *, backend=None, device=None, architecture=None, radius=None, timing: Optional[dict] = None):
    """Replay ``recording`` (``mcap_read.Recording``); returns (service, check) where ``check``
    is the exactness report (None for a what-if run) and ``service.recorder`` holds every
    replayed tick (``record.Recorder``). ``timing`` (a dict), where given, gets the wall-clock
    seconds of the set-up (``setup_s``: configuration, service, kernels) and of the ticks
    (``ticks_s``)."""
    from .app import Service

    t_start = time.perf_counter()
    meta, lay, rows = recording.meta, recording.layout, recording.rows
    if not len(rows):
        raise InputError(f"{recording.path}: no whole tick recorded (the run ended, or the file was cut, before its "
                         "first flush)")
    what_if = architecture is not None or radius is not None
    cfg = recording_config(recording, radius)
    n = lay.n
    first_in = TickInput.zeros(n)
    row_into(lay, rows[0], first_in)
    start = meta.get("start") or {"master_pos": first_in.master_pos.tolist(), "pedal": first_in.pedal.tolist(),
                                  "master_ok": first_in.master_ok.tolist(), "robot_pos": first_in.robot_pos.tolist(),
                                  "robot_present": first_in.robot_present.tolist(), "haptics": first_in.haptics,
                                  "teleop": first_in.teleop, "architecture": meta.get("architecture")}
    ident, none = [[1.0, 0.0, 0.0, 0.0]] * n, [None] * n      # (recordings made before 6-DOF teleoperation)
    masters = [StartMaster(start["master_pos"][b], start["pedal"][b], start["master_ok"][b],
                           start.get("master_orientation", ident)[b], start.get("grasp", [0.0] * n)[b])
               for b in range(n)]
    present = [bool(x) for x in start["robot_present"]]
    if what_if:
        robots = [Service._make_robot(cfg.robot) if present[b] else None for b in range(n)]
    else:
        robots = [RecordedRobot(start["robot_pos"][b], start.get("robot_orientation", ident)[b],
                                start.get("robot_jaw", none)[b], start.get("jaw_range", none)[b])
                  if present[b] else None for b in range(n)]
    schedule = build_schedule(recording)
    decoder = FrameDecoder(recording, schedule)     # decoding starts now, beside the service's set-up
    try:
        svc = Service(cfg, masters, robots=robots, backend=backend or meta.get("backend"),
                      device=device or (None if backend else meta.get("device_spec")), record=0,
                      architecture=architecture or start.get("architecture") or meta.get("architecture"))
    except BaseException:
        decoder.close()
        raise
    ks, ts = (rows[:, lay.cols[("in", name)][0]] for name in ("k", "t"))
    feeder = RecordedFrames(svc.pipeline, recording, schedule, cfg.service.stale_s, cfg.service.max_frame_age_s,
                            tick_times=dict(zip(ks.astype(np.int64).tolist(), ts.tolist())), decoder=decoder)
    svc.attach_frames(feeder)
    svc.engage_haptics(bool(start["haptics"]))
    svc.engage_teleop(bool(start["teleop"]))
    ticks = ReplayTicks(lay, len(rows))
    inp = TickInput.zeros(n)
    recorded = _Inputs(lay, rows, inp)
    arch_code = svc.teleop.arch if what_if and architecture else None
    arms = [(b, r) for b, r in enumerate(robots) if r is not None and not what_if]
    rpos, rfault, rquat, rjaw = inp.robot_pos, inp.robot_fault, inp.robot_orientation, inp.robot_jaw
    # every recorded pose at once (a tick then only copies its own)
    rec_poses = {b: poses(*(rows[:, lay.cols[("in", f)][0]:][:, b * k: b * k + k] for f, k in
                            (("robot_pos", 3), ("robot_orientation", 4)))) for b, _ in arms}
    clock, take, tick = time.perf_counter, ticks.take, svc.replay_tick
    t_setup = clock()
    try:
        feeder.start()
        for i in range(len(rows)):
            recorded.into(i)
            if arch_code is not None:
                inp.architecture = arch_code
            feeder.too_old = inp.frames_too_old
            for b, r in arms:
                r.pos[:] = rpos[b]
                r.quat[:] = rquat[b]
                r.pose = rec_poses[b][i]
                r.jaw = float(rjaw[b])
                r.fault = bool(rfault[b])
            w0 = clock()
            out = tick(inp)
            take(inp, out, (clock() - w0) * 1e6)
    finally:
        feeder.close()
    svc.recorder = ticks.recorder()          # (what ticks.csv, inputs.npz and summary.json are written from)
    if timing is not None:
        timing.update(setup_s=t_setup - t_start, ticks_s=clock() - t_setup)
    if what_if:
        return svc, None
    report = ticks.compare(rows)
    if feeder.missing:
        report["missing_snapshots"] = sorted(set(feeder.missing))
    return svc, report


class _Inputs:
    """Every recorded ``TickInput``, unpacked once from the ring rows into typed per-field arrays
    and lists, so that a tick's ``into(i)`` only copies into ``inp`` (the same values
    ``tick_cdr.row_into`` gives, without its per-tick conversions)."""

    def __init__(self, lay, rows: np.ndarray, inp: TickInput):
        self.inp = inp
        self.arrays, self.scalars = [], []
        for name, _, dtype, per_arm in lay.fields["in"]:
            c, k = lay.cols[("in", name)]
            if per_arm:
                dst = getattr(inp, name)
                self.arrays.append((dst, rows[:, c: c + k].reshape((len(rows),) + dst.shape).astype(dst.dtype)))
            else:
                kind, col = np.dtype(dtype), rows[:, c]
                vals = (col != 0).tolist() if kind == bool else col.astype(np.int64).tolist() if kind.kind == "i" \
                    else col.tolist()
                self.scalars.append((name, vals))

    def into(self, i: int) -> None:
        inp = self.inp
        for dst, a in self.arrays:
            dst[...] = a[i]
        for name, vals in self.scalars:
            setattr(inp, name, vals[i])


__all__ = ["replay", "recording_config", "build_schedule", "RecordedRobot", "RecordedFrames"]
