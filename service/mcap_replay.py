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

from .frames import _FeedBase
from .masters import Master
from .robot.base import RobotMode
from .tick_cdr import TickRows, row_into
from .tick_io import TickInput, TickOutput

#: fields of TickOutput that are wall-clock measurements, not results
_TIMING = ("kernel_us", "tick_us")


class StartMaster(Master):
    """The master as ``Service.start`` read it in the recorded run; every tick's sample comes
    from the recording (``replay_tick`` reads no master)."""

    name = "recorded"

    def __init__(self, pos, pedal, ok):
        super().__init__()
        self._sample = (np.array(pos, float), bool(pedal), bool(ok))

    def poll(self, t: float) -> None:
        self.position[:] = self._sample[0]
        self.clutch, self.ok = self._sample[1], self._sample[2]


class RecordedRobot:
    """A robot that reports what the recorded one measured (set per tick by the replay) and
    accepts every command (the service's ``Devices`` interface, nothing more)."""

    model = "recorded"
    fault_reason = None
    hosted = False

    def __init__(self, pos):
        self.pos = np.array(pos, float)
        self.fault = False

    @property
    def state(self) -> RobotMode:
        return RobotMode.FAULT if self.fault else RobotMode.ENABLED

    def measured_cp(self, out=None):
        T = np.eye(4) if out is None else out
        T[...] = np.eye(4)
        T[:3, 3] = self.pos
        return T

    def servo_cp(self, pose) -> bool:
        return True

    def resume(self) -> None:
        pass

    def hold(self) -> None:
        pass

    def enable(self) -> None:
        pass

    def step(self, dt: float) -> None:
        pass


class RecordedFrames(_FeedBase):
    """Re-builds the recorded snapshots: ``build_at`` maps a tick number k to the snapshot seqs
    to build (in order) before that tick's proxy launch. ``too_old`` is the recorded
    ``frames_too_old`` of the tick being replayed."""

    def __init__(self, pipeline, recording, build_at: dict, stale_s: float, max_age_s: float):
        super().__init__(pipeline, [], stale_s, max_age_s)
        self.rec = recording
        self.names = list(recording.cameras)
        n = len(self.names)
        self.latest, self.arrival, self.frames_in = [None] * n, [-math.inf] * n, [0] * n
        self.build_at = build_at
        self.too_old = False
        self.missing: list = []
        self._index = [-1] * n            # the recorded frame each camera's latest is

    def frames_too_old(self, now: float) -> bool:
        return self.too_old

    def poll_tick(self, k: int, t: float) -> bool:
        built = False
        for seq in self.build_at.get(k, ()):
            entry = self.rec.snapshots.get(seq)
            if entry is None:
                self.missing.append(seq)
                continue
            fseqs, findex, stamps, poses = entry
            for i, (fseq, idx) in enumerate(zip(fseqs, findex)):
                if self._index[i] != idx:
                    self.latest[i] = self.rec.frame(i, idx, fseq, stamps[i], poses[16 * i: 16 * i + 16])
                    self._index[i] = idx
                    self.frames_in[i] += 1
                self.arrival[i] = t
            self.pipeline.seq = seq - 1          # numbered as the live run numbered it
            built |= self._ingest(list(self.latest), t)
        return built


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
        cams.append({"name": c["name"], "source": c["source"], "rate_hz": c["rate_hz"], "fx": c["fx"], "fy": c["fy"],
                     "cx": c["cx"], "cy": c["cy"], "width": c["width"], "height": c["height"],
                     "depth_scale": c["depth_scale"], "T_world_cam": c["T_world_cam"], "dist": c["dist"],
                     "noise": c["noise"], "z_min": c["z_min"], "z_max": c["z_max"], "max_code": c["max_code"]})
    if not cams:
        raise InputError(f"{recording.path}: the recording names no cameras")
    doc["camera"] = cams
    doc.setdefault("service", {})["self_filter"] = False
    if radius is not None:
        doc.setdefault("fixture", {})["radius"] = float(radius)
    return parse(doc, f"{recording.path} (recorded configuration)")


def replay(recording, *, backend=None, device=None, architecture=None, radius=None):
    """Replay ``recording`` (``mcap_read.Recording``); returns (service, check) where ``check``
    is the exactness report (None for a what-if run)."""
    from .app import Service

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
    masters = [StartMaster(start["master_pos"][b], start["pedal"][b], start["master_ok"][b]) for b in range(n)]
    present = [bool(x) for x in start["robot_present"]]
    if what_if:
        robots = [Service._make_robot(cfg.robot) if present[b] else None for b in range(n)]
    else:
        robots = [RecordedRobot(start["robot_pos"][b]) if present[b] else None for b in range(n)]
    svc = Service(cfg, masters, robots=robots, backend=backend or meta.get("backend"),
                  device=device or (None if backend else meta.get("device_spec")), record=len(rows),
                  architecture=architecture or start.get("architecture") or meta.get("architecture"))
    feeder = RecordedFrames(svc.pipeline, recording, build_schedule(recording), cfg.service.stale_s,
                            cfg.service.max_frame_age_s)
    svc.attach_frames(feeder)
    svc.engage_haptics(bool(start["haptics"]))
    svc.engage_teleop(bool(start["teleop"]))
    check = None if what_if else _Check(lay)
    inp, rec_out = TickInput.zeros(n), TickOutput.zeros(n)
    arch_code = svc.teleop.arch if what_if and architecture else None
    for row in rows:
        row_into(lay, row, inp)
        if arch_code is not None:
            inp.architecture = arch_code
        feeder.too_old = inp.frames_too_old
        if not what_if:
            for b, r in enumerate(robots):
                if r is not None:
                    r.pos[:] = inp.robot_pos[b]
                    r.fault = bool(inp.robot_fault[b])
        w0 = time.perf_counter()
        out = svc.replay_tick(inp)
        svc.note_tick_us((time.perf_counter() - w0) * 1e6)
        if check is not None:
            check.compare(inp, out, row)
    if feeder.missing:
        if check is not None:
            check.report["missing_snapshots"] = sorted(set(feeder.missing))
    return svc, (None if check is None else check.report)


class _Check:
    """Compares each replayed tick's output with the recorded one (timing fields aside)."""

    def __init__(self, lay):
        self.lay = lay
        self.rows = TickRows(lay)
        self.scratch = np.zeros(lay.width)
        self.cols = np.concatenate([np.arange(c, c + k) for (part, name), (c, k) in lay.cols.items()
                                    if part == "out" and name not in _TIMING])
        self.report = {"exact": True, "ticks_compared": 0, "mismatched_ticks": 0, "first_mismatch": None}

    def compare(self, inp, out, row) -> None:
        self.rows.fill(inp, out, self.scratch)
        a, b = self.scratch[self.cols], row[self.cols]
        self.report["ticks_compared"] += 1
        same = (a == b) | (np.isnan(a) & np.isnan(b))
        if not same.all():
            self.report["exact"] = False
            self.report["mismatched_ticks"] += 1
            if self.report["first_mismatch"] is None:
                col = int(self.cols[np.flatnonzero(~same)[0]])
                name = next(nm for (part, nm), (c, k) in self.lay.cols.items() if part == "out" and c <= col < c + k)
                self.report["first_mismatch"] = {"tick": int(out.k), "field": name, "recorded": float(row[col]),
                                                 "replayed": float(self.scratch[col])}


__all__ = ["replay", "recording_config", "build_schedule", "RecordedRobot", "RecordedFrames"]
