"""`pointfence demo`: the main job on the embedded defaults (or a configuration file).

Runs the dissertation's chapter-3 experiments (``scenarios``) live: the 1 kHz haptic loop in
its own thread on the real clock, camera reader threads feeding the frame pipeline on the
configured backend (PoCL by default), a scripted master and the simulated robot (Raven II by
default): the inclined plane approached horizontally (fig. 3.8) and the balloon pushed ever
deeper (fig. 3.9) under architectures I, II and III, and the rocking platform (fig. 3.10)
under III. For every run it prints the 6.1 measures against the scenes' exact geometry
(safety: max penetration of the fixture; submittance: closest approach while held off;
tracking: r.m.s. |X_r - X_r*| with the master outside the region) and the loop's timing
(compute and lateness p50/p99, deadline misses; a tick later than ``--max-lateness``, 20 ms by
default here and held to ``[service] max_lateness_s``'s hard limit, holds the robot as in the
service). ``--offline`` runs the same on the simulated clock (deterministic; no loop timing).
``--out DIR`` keeps each run's ticks.csv, summary.json and inputs.npz (replayable with
``pointfence replay --recording``).

It then runs the chapter-2 surface probes in haptic rendering mode (``probes``: push into a
plane, concave/convex/corner, the 5 mm ledge, and the rising plane's pop-through speed, figs.
2.12-2.15) and writes the report folder (``--report DIR``, default ``out/demo``; ``report``):
PNG plots of every figure and the table (with the pop-through column) as table.md and table.json.

Then the chapter-6 section (``dynamic_demo``; ``--no-dynamic`` skips it): the whole service on a
plane rising at 0.5 m/s without and with motion prediction (live, or on the simulated clock with
``--offline``), the translating plane's pop-through speed without and with prediction (also with
100 ms camera latency), the tool's shadow with one and two cameras, and the robot self-filter;
its figures are a second table in table.md and ``dynamic`` in table.json.

``--ros2`` runs the whole ROS 2 path instead (``ros2/demo_ros2.py``): the scene's camera, master
and arm as ROS 2 equipment in processes of their own, the service between them.

``--viewer`` (spawn a rerun viewer, or connect to a URL) and ``--viewer-save FILE.rrd`` log every
chapter-3 experiment after it ends, from its recording and its last snapshot: point cloud,
proxy, HIP, force arrows, robot path (``viewer``; needs ``pip install 'pointfence[viewer]'``).
"""
from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

from pointfence.kernels import get_backend
from pointfence.service import config as config_mod

from . import limits, replay, report, scenarios, viewer as viewer_mod
from .canned import canned_sources
from .runner import LiveRun

_CACHE: dict = {}

RUNS = [("inclined_plane", "I"), ("inclined_plane", "II"), ("inclined_plane", "III"),
        ("balloon", "I"), ("balloon", "II"), ("balloon", "III"), ("rocking_platform", "III")]


def add_arguments(p):
    p.add_argument("--config", default=None, help="scene configuration (TOML); default: the embedded defaults")
    p.add_argument("--backend", default=None, help="override the configured backend (numpy, opencl, warp)")
    p.add_argument("--device", default=None, help="override the configured device")
    p.add_argument("--offline", action="store_true", help="simulated clock: deterministic, no loop timing")
    p.add_argument("--only", default=None, help="comma-separated scenarios (inclined_plane, balloon, rocking_platform)")
    p.add_argument("--render-live", action="store_true",
                   help="render the synthetic cameras while the loop runs (default: pre-render one period "
                        "of frames and serve them in real time, as a real camera's C driver would)")
    p.add_argument("--max-lateness", type=float, default=0.02,
                   help="s; a tick later than this holds the robot (default 0.02 for the demo on a shared or "
                        "loaded machine; the configuration's [service] max_lateness_s otherwise applies)")
    p.add_argument("--out", default=None, help="folder to keep every run's ticks.csv, summary.json, inputs.npz")
    p.add_argument("--record", default=None, metavar="FILE.mcap",
                   help="record every live chapter-3 run to FILE-<scene>_<arch>.mcap (ROS 2 schemas; "
                        "`pointfence replay --recording` replays each exactly)")
    p.add_argument("--ros2-telemetry", action="store_true",
                   help="publish ROS 2 telemetry of every live run for RViz and Foxglove ([ros2] table; needs "
                        "pointfence[ros2])")
    p.add_argument("--ros2", action="store_true",
                   help="the whole ROS 2 path instead of the chapter-3 runs: camera, master and arm as ROS 2 "
                        "equipment in their own processes on this machine (ros2/demo_ros2.py; needs pointfence[ros2])")
    p.add_argument("--ros2-seconds", type=float, default=15.0, help="seconds of the --ros2 run (default 15)")
    p.add_argument("--report", default="out/demo", help="report folder: PNG plots and table.md/table.json "
                                                        "(default out/demo; '' for none)")
    p.add_argument("--no-probes", action="store_true", help="skip the chapter-2 surface probes (figs. 2.12-2.15)")
    p.add_argument("--no-dynamic", action="store_true",
                   help="skip the chapter-6 dynamic scenes (moving plane with and without motion prediction, the "
                        "tool's shadow with one and two cameras, the robot self-filter)")
    viewer_mod.add_arguments(p)


def _mm(v):
    return "    -" if v is None else f"{v * 1000:5.2f}"


def _one(cfg, scene, arch, args, viewer=None):
    master = scenarios.scenario_master(scene)
    duration = float(master.times[-1])
    if args.offline:
        svc, loop, sources = replay.simulate(cfg, [master], duration, architecture=arch, backend=args.backend,
                                             device=args.device)
        timing = None
    else:
        n = 90 if scene == "rocking_platform" else 30     # one rocking period, or 1 s of noise
        sources = None if args.render_live else canned_sources(cfg, n, _CACHE)
        out_dir = Path(args.out) / f"{scene}_{arch}" if args.out else None
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
        # a live run streams its recording to disk as it goes (S8); without --out it stays in memory
        record_path = None if out_dir is None else out_dir / "recording.pfrec"
        if args.record:     # MCAP (keeps the ticks in memory too: the report reads them)
            base = Path(args.record)
            record_path = base.with_name(f"{base.stem}-{scene}_{arch}.mcap")
            print(f"recording {scene} {arch} to {record_path}")
        run = LiveRun(cfg, [master], architecture=arch, backend=args.backend, device=args.device,
                      record_s=duration + 1.0, sources=sources, record_path=record_path,
                      ros2_telemetry=getattr(args, "ros2_telemetry", False) or None)
        run.start()
        try:
            run.wait(duration)
        finally:
            run.stop()
        svc, loop, sources, timing = run.service, run.loop, run.sources, run.timing()
    out_dir = Path(args.out) / f"{scene}_{arch}" if args.out else None
    if out_dir is not None:
        summary = replay.write_outputs(svc, sources, cfg, out_dir, svc.feeder.snapshots)
    else:
        summary = replay.summary(svc, sources, cfg, svc.feeder.snapshots)
    for s in sources:
        s.close()
    if loop.error:
        summary["loop_error"] = loop.error
    summary["hold"] = svc.status()["hold"]
    summary["_trace"] = report.trace_of(svc, sources, cfg) if args.report else None
    if viewer is not None:
        viewer.log_run(f"{scene}_{arch}", svc, summary)
    return summary, timing


def run(args) -> int:
    lateness = None   # checked first, against the configuration's own hard limit (S7): fails before any run
    if args.max_lateness is not None:
        lateness = limits.check("service.max_lateness_s", args.max_lateness, "--max-lateness")
    cfg = config_mod.load(args.config)
    if lateness is not None:
        cfg = replace(cfg, service=replace(cfg.service, max_lateness_s=lateness))
    if args.ros2:
        from .ros2 import demo_ros2

        return demo_ros2.run(args, cfg)
    backend = get_backend(args.backend or cfg.backend, args.device or cfg.device)
    viewer = viewer_mod.from_args(args)   # before the runs: a missing rerun-sdk fails at once
    done = False
    try:
        rc = _run(args, cfg, backend, viewer)
        done = True
    finally:
        if viewer is not None:
            viewer.close(check=done)   # a run's own error is not masked by the viewer's
    if viewer is not None and viewer.save is not None:
        print(f"viewer recording: {viewer.save} (open it with `rerun {viewer.save}`)")
    return rc


def _run(args, cfg, backend, viewer) -> int:
    print(f"pointfence demo: {cfg.path}, backend {backend.name} on {backend.device_name}, robot "
          f"{cfg.robot.model}, fixture {cfg.pipeline.radius.r_base * 1000:.0f} mm, k_s "
          f"{cfg.haptics.k_s:.0f} N/m, scale {cfg.teleop.scale}, max robot speed {cfg.teleop.max_robot_speed} m/s, "
          f"{'simulated clock' if args.offline else 'live 1 kHz loop'}")
    only = set(args.only.split(",")) if args.only else None
    head = (f"{'scenario':17s} {'arch':4s} {'safety':>6s} {'submit':>6s} {'track':>6s} {'popthr':>6s}   "
            f"{'tick p50':>8s} {'p99':>6s} {'late p50':>8s} {'p99':>6s} {'misses':>7s}  frames")
    print("\nmeasures in mm (safety: max penetration; submit: closest approach held off; track: rms |X_r - X_r*|);"
          " times in us")
    print(head)
    print("-" * len(head))
    results, rows, experiments = [], [], {}
    t_start = time.monotonic()
    for scene, arch in RUNS:
        if only is not None and scene not in only:
            continue
        scfg = scenarios.scenario_config(cfg, scene)
        s, timing = _one(scfg, scene, arch, args, viewer)
        if timing is not None:
            tm = (f"{timing.compute_us_p50:8.0f} {timing.compute_us_p99:6.0f} {timing.late_us_p50:8.0f} "
                  f"{timing.late_us_p99:6.0f} {timing.misses:4d}/{timing.periods}")
            s["loop"] = timing.as_dict()
        else:
            tm = f"{s['tick_us_p50']:8.0f} {s['tick_us_p99']:6.0f} {'-':>8s} {'-':>6s} {'-':>7s}"
        flag = f"  HOLD: {', '.join(s['hold'])}" if s["hold"] else ""
        print(f"{scene:17s} {arch:4s} {_mm(s['safety_max_penetration_m'])} {_mm(s['submittance_min_distance_m'])} "
              f"{_mm(s['tracking_rms_m'])} {'-':>6s}   {tm}  {s['frames']}{flag}")
        experiments.setdefault(scene, []).append((arch, s.pop("_trace")))
        rows.append(report.row_for_run(scene, s, timing))
        results.append({"scenario": scene, **s})
    probe_results = [] if args.no_probes else _probes(args, backend, args.device or cfg.device)
    rows += [report.row_for_probe(p) for p in probe_results]
    dynamic = None
    if not args.no_dynamic:
        from . import dynamic_demo

        dynamic = dynamic_demo.run(backend.name, args.device or cfg.device, live=not args.offline)
    print(f"\n{len(results)} runs in {time.monotonic() - t_start:.0f} s. Architecture III is the hard fixture: "
          "its safety column stays near zero while I and II, soft fixtures, let the pushed robot in.")
    if args.out:
        (Path(args.out) / "demo.json").write_text(json.dumps(results, indent=2) + "\n")
        print(f"recordings and summaries in {args.out}")
    if args.report:
        meta = {"configuration": cfg.path, "backend": f"{backend.name} on {backend.device_name}",
                "robot": cfg.robot.model, "fixture radius (mm)": cfg.pipeline.radius.r_base * 1000,
                "clock": "simulated" if args.offline else "live 1 kHz loop"}
        files = report.write(args.report, rows, probe_results, experiments, meta, dynamic=dynamic)
        print(f"report: {len([f for f in files if f.suffix == '.png'])} plots, table.md and table.json in {args.report}")
    print(f"demo done in {time.monotonic() - t_start:.0f} s")
    return 0


def _probes(args, backend, device) -> list:
    """The chapter-2 surface probes (rendering mode, simulated clock), printed as table rows."""
    from . import probes

    print("\nchapter-2 surface probes, haptic rendering (proxy r1 5 mm, simulated 1 kHz ticks, 30 Hz frames); "
          "safety: proxy sphere's max penetration of the true surface")
    out = probes.run_all(backend=backend.name, device=device)
    for p in out:
        row = report.row_for_probe(p)
        pop = f"{p['popthrough_speed']:6.2f}" if p.get("popthrough_speed") is not None else f"{'-':>6s}"
        extra = ""
        if p["figure"] == "2.12":
            extra = f"  force at 2 cm: {p['force_at_2cm_N']:.2f} N"
        elif p["figure"] == "2.14":
            extra = f"  proxy levels {p['upper_z'] * 1000:.1f} / {p['lower_z'] * 1000:.1f} mm"
        elif p["figure"] == "2.15":
            extra = f"  held up to {p['max_speed_held']} m/s (dissertation: pop-through at 0.08 m/s)"
        safety = _mm(p["penetration_m"]) if p.get("penetration_m") is not None else f"{'-':>5s}"
        print(f"{p['name'][:17]:17s} {'-':4s} {safety} {'-':>6s} {'-':>6s} {pop}   {'':8s} {row['tick_us_p99']:6.0f}"
              f"{'':24s}fig. {p['figure']}{extra}")
    return out
