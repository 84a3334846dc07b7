"""`pointfence replay`: a deterministic offline run of the whole service on a simulated clock.

    pointfence replay --config F --trajectory T.csv --out DIR [--architecture A] [--backend B]
    pointfence replay --config F --recording RUN_DIR --out DIR      # re-run a recorded run
    pointfence replay --config F --recording RUN.pfrec --out DIR    # ... from its streamed recording
    pointfence replay --recording RUN.mcap --out DIR [--architecture A] [--radius R] [--backend B]

With ``--trajectory`` a scripted master plays ``t,x,y,z[,clutch]`` (master frame, m, s) at 1 ms
ticks; camera frames arrive at their own timestamps (synthetic: seq / rate_hz) and are ingested
inside the tick that first sees them. With ``--recording`` the ticks of a recorded run (its
``inputs.npz``: every master sample, each tick's dt, overrun flag and frame age, the control
state, and the camera frames of every snapshot with the tick it became visible at) are played
again exactly; a streamed recording (``.pfrec``, service/record.py: written while the run goes
on, readable after a crash up to its last whole chunk) holds the same, and a folder holding a
``recording.pfrec`` but no ``inputs.npz`` is read from it. Same inputs, same backend: identical ``ticks.csv`` except the ``tick_us``
column (this machine's compute time of each tick).

An MCAP recording (``serve|demo --record FILE.mcap``) holds the depth frames, the
configuration and every tick's input and output: ``mcap_replay`` replays it with no camera,
device or robot, checks that every tick's output is the recorded one (``summary.json``
``replay``), and with ``--architecture`` / ``--radius`` re-runs the same inputs under other
settings (``--config`` is not needed and not used).

Writes ``DIR/ticks.csv`` (``record.TICK_COLUMNS``), ``DIR/summary.json`` (architecture, ticks,
frames, the 6.1 measures, tick_us_p50/p99, deadline_misses = ticks whose compute exceeded the
period, backend, device) and ``DIR/inputs.npz``.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import numpy as np

from . import config as config_mod
from . import measures
from .app import Service
from .clock import FakeClock
from .frames import ScheduledFrames, SimFrames
from .loop import HapticLoop
from .masters import Master, ScriptedMaster
from .record import load_inputs, recording_inputs, tick_input
from .tick_io import TickInput


def add_arguments(p):
    p.add_argument("--config", default=None, help="scene configuration (TOML); default: the embedded defaults")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--trajectory", help="master trajectory CSV: t,x,y,z[,clutch] (master frame, m, s)")
    src.add_argument("--recording", help="a recorded run to play again exactly: its folder (inputs.npz, or recording.pfrec) "
                     "or its streamed .pfrec file")
    p.add_argument("--out", required=True, help="output folder for ticks.csv, summary.json, inputs.npz")
    p.add_argument("--architecture", choices=("I", "II", "III"), default=None,
                   help="override [teleop] architecture (an .mcap recording: a what-if re-run of its inputs)")
    p.add_argument("--radius", type=float, default=None,
                   help="m; an .mcap recording: re-run its inputs with this [fixture] radius (what-if)")
    p.add_argument("--backend", default=None, help="override the configured backend (numpy, opencl, warp)")
    p.add_argument("--device", default=None, help="override the configured device")
    p.add_argument("--duration", type=float, default=None, help="seconds to run (default: the trajectory's end + 0.5 s)")


class PlaybackMaster(Master):
    """Recorded master samples, one row per tick (``row`` set by the replay driver)."""

    name = "playback"

    def __init__(self, samples: np.ndarray):
        super().__init__()
        self.samples = np.asarray(samples, dtype=float)   # (N, 5): x, y, z, pedal, ok
        self.row = 0

    def poll(self, t: float) -> None:
        s = self.samples[min(self.row, len(self.samples) - 1)]
        self.position[:] = s[:3]
        self.clutch = bool(s[3])
        self.ok = bool(s[4])


def simulate(cfg, masters, duration: float, *, architecture: Optional[str] = None, backend: Optional[str] = None,
             device: Optional[str] = None, events: Optional[dict] = None, robots=None, sources=None,
             record: bool = True):
    """Run the service offline for ``duration`` s with ``masters`` (FakeClock, frames at their
    timestamps). ``events`` maps a tick index to a callable(service) run before that tick
    (architecture switches, engage/disengage). Returns (service, loop, sources)."""
    rate = cfg.service.rate_hz
    n_ticks = int(round(duration * rate))
    svc = Service(cfg, masters, robots=robots, backend=backend, device=device, record=n_ticks if record else 0,
                  architecture=architecture)
    sources = sources if sources is not None else cfg.open_sources()
    feeder = SimFrames(svc.pipeline, sources, cfg.service.stale_s, cfg.service.max_frame_age_s)
    svc.attach_frames(feeder)
    feeder.poll(0.0)
    loop = HapticLoop(svc, FakeClock(), rate, cfg.service.max_lateness_s, switch_interval_s=None)
    events = events or {}
    for k in range(n_ticks):
        ev = events.get(k)
        if ev is not None:
            ev(svc)
        loop.run_ticks(1)
    return svc, loop, sources


def load_run(rec) -> dict:
    """The inputs of a recorded run: ``rec`` is a ``.pfrec`` file, or a folder with ``inputs.npz``
    (a clean end) or else ``recording.pfrec`` (streamed: a crash leaves this one)."""
    p = Path(rec)
    if p.is_dir():
        return load_inputs(p / "inputs.npz") if (p / "inputs.npz").is_file() or not (p / "recording.pfrec").is_file() \
            else recording_inputs(p / "recording.pfrec")
    return recording_inputs(p)


def replay_recording(cfg, rec_dir, *, backend=None, device=None):
    """Play a recorded run's ticks again exactly (see the module docstring)."""
    data = load_run(rec_dir)
    inputs, samples = data["inputs"], data["masters"]
    n_ticks, n_arms = samples.shape[0], samples.shape[1]
    masters = [PlaybackMaster(samples[:, b]) for b in range(n_arms)]   # (the first sample places them at start)
    meta = data["meta"]
    svc = Service(cfg, masters, backend=backend or meta.get("backend"), device=device or meta.get("device_spec"),
                  record=n_ticks, architecture=meta.get("architecture"))
    sources = cfg.open_sources()
    schedule = {}
    for seq, tick in data["meta"]["snapshot_ticks"].items():
        frames = data["schedule"].get(int(seq))
        if frames is not None:
            schedule[int(tick)] = frames
    feeder = ScheduledFrames(svc.pipeline, sources, schedule, cfg.service.stale_s, cfg.service.max_frame_age_s)
    svc.attach_frames(feeder)
    if n_ticks:                  # the control state the run started in (start() takes it)
        svc.engage_haptics(bool(inputs[0, 5]))
        svc.engage_teleop(bool(inputs[0, 6]))
    P = 1.0 / cfg.service.rate_hz
    has_frame_time = inputs.shape[1] > 7
    inp = TickInput.zeros(n_arms)
    for i in range(n_ticks):
        tick_input(data, i, inp)
        inp.t = inp.now = inp.k * P
        if not has_frame_time:   # (older recordings: the schedule's clock)
            inp.frame_time = feeder.frame_time(inp.t, inp.now)
        w0 = time.perf_counter()
        svc.replay_tick(inp)
        svc.note_tick_us((time.perf_counter() - w0) * 1e6)
    return svc, sources


def summary(svc, sources, cfg, frames: int) -> dict:
    rec = svc.recorder.arrays()
    rows = rec["rows"]
    region = measures.region_for(cfg, sources, svc.pipeline)
    teleop = rec["inputs"][:, 6] > 0
    m = measures.compute(rows[:, 0] + svc.scene_time_offset, rec["robots"][:, 0, :3], rec["robots"][:, 0, 3:],
                         rec["masters_world"][:, 0], region, mask=teleop)
    us = rows[:, -1]
    return {
        "architecture": svc.architecture, "ticks": int(len(rows)), "frames": int(frames), **m,
        "tick_us_p50": round(float(np.percentile(us, 50)), 1) if len(us) else None,
        "tick_us_p99": round(float(np.percentile(us, 99)), 1) if len(us) else None,
        "deadline_misses": int((us > 1e6 / svc.rate_hz).sum()),
        "backend": svc.backend.name, "device": svc.backend.device_name,
    }


def write_outputs(svc, sources, cfg, out_dir, frames: int, backend_spec=None) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rec = svc.recorder
    rec.write_csv(out / "ticks.csv")
    fe = svc.feeder
    meta = {"architecture": svc.architecture, "backend": svc.backend.name, "device_spec": svc.cfg.device,
            "rate_hz": svc.rate_hz, "cameras": fe.names,
            "snapshot_ticks": {str(s): int(k) for s, k in svc.snapshot_first_tick.items()}}
    rec.save_inputs(out / "inputs.npz", fe.snapshot_frames, meta)
    s = summary(svc, sources, cfg, frames)
    (out / "summary.json").write_text(json.dumps(s, indent=2) + "\n")
    return s


def replay_mcap(args) -> dict:
    """``--recording FILE.mcap``: replay (or re-run under other settings) and write the outputs."""
    from . import limits
    from .mcap_read import open_recording
    from .mcap_replay import replay

    if args.radius is not None:
        limits.check("fixture.radius", args.radius, "--radius")
    t0 = time.perf_counter()
    rec = open_recording(args.recording)
    t_open = time.perf_counter()
    timing: dict = {}
    svc, check = replay(rec, backend=args.backend, device=args.device, architecture=args.architecture,
                        radius=args.radius, timing=timing)
    t_ticks = time.perf_counter()
    sources = _ground_truth_sources(svc.cfg)
    try:
        s = write_outputs(svc, sources, svc.cfg, args.out, svc.feeder.snapshots)
    finally:
        for src in sources:
            src.close()
    ticks = len(rec.rows)
    s["recording"] = {"file": str(rec.path), "ticks": ticks, "torn": rec.torn,
                      "ticks_lost_while_recording": rec.meta.get("ticks_lost"),
                      "snapshots_dropped_while_recording": rec.meta.get("snapshots_dropped")}
    s["replay"] = check if check is not None else {"what_if": {"architecture": args.architecture, "radius": args.radius,
                                                               "backend": args.backend}}
    wall = time.perf_counter() - t0
    run_s = ticks / svc.rate_hz
    s["replay_x_realtime"] = round(run_s / wall, 2) if wall > 0 else None
    s["replay_wall_s"] = {"total": round(wall, 3), "open": round(t_open - t0, 3), "setup": round(timing["setup_s"], 3),
                          "ticks": round(timing["ticks_s"], 3), "outputs": round(time.perf_counter() - t_ticks, 3),
                          "run_s": round(run_s, 3)}
    Path(args.out, "summary.json").write_text(json.dumps(s, indent=2) + "\n")
    return s


def _ground_truth_sources(cfg) -> list:
    """Synthetic cameras' sources (their exact scene geometry for the measures; no device)."""
    return [cfg.open_source(c) for c in cfg.cameras if c.source.startswith("synthetic:")]


def run(args) -> int:
    if args.recording and str(args.recording).endswith(".mcap"):
        print(json.dumps(replay_mcap(args), indent=2))
        return 0
    cfg = config_mod.load(args.config)
    if args.recording:
        svc, sources = replay_recording(cfg, args.recording, backend=args.backend, device=args.device)
    else:
        master = ScriptedMaster.from_csv(args.trajectory)
        duration = args.duration if args.duration is not None else master.times[-1] + 0.5
        svc, _, sources = simulate(cfg, [master], duration, architecture=args.architecture, backend=args.backend,
                                   device=args.device)
    try:
        s = write_outputs(svc, sources, cfg, args.out, svc.feeder.snapshots)
    finally:
        for src in sources:
            src.close()
    print(json.dumps(s, indent=2))
    return 0
