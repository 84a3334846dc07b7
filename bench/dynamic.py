"""`pointfence bench dynamic`: fixtures on a dynamic, partly hidden scene (dissertation ch. 6).

All in simulated time (30 Hz synthetic frames, 1 kHz ticks), so the figures do not depend on
the machine:

* ``popthrough_speed_mps``: translating plane, 30 Hz camera, 2 cm fixture: the first speed of
  the sweep at which the proxy pops through, with and without motion prediction (null: none
  of the speeds tried popped; ``held_speed_mps`` has the fastest held); also with 100 ms of
  camera latency, and for the 5 mm rendering proxy of fig. 2.15;
* ``occlusion_penetration_mm_1cam`` / ``_2cam``: architecture III pushing a tool onto a
  protected disc it hides from the top camera; a second, low side camera fills the shadow;
* ``self_filter_false_fixture_ratio``: protected points on the robot's own tool with the
  self-filter / without it;
* the adaptive radius study (fixed vs adaptive r_f over distance, noise, systematic error):
  rows in ``radius_study``; ``--study DIR`` also writes the table, CSV and plot there.

``--real`` runs chapter 6 on real depth frames instead (``service/dynamic_real.py``): real
frames (../shared/data's apc_shelfbin_50f and 7scenes_kitchen_50f, or ``--frames DIR``, repeatable)
moved toward the camera, sideways and rocking at known speeds, architecture III with a
point-mass robot, 1 and 2 cm fixtures; per scene / motion / master / r_f / speed the proxy's
and the robot's max penetration of the forbidden region (mm, against the true surface at every
tick) without and with prediction, the synthetic plane beside them (``real_rows``); the fastest
speeds held to the issue-23 targets (``real_held_speed_mps``); the motion estimator against the
true velocity (``real_estimator``); and the real-rig figures (occlusion, fused rig, radius study)
of ``service/dynamic_real_rig.py`` (``real_rig``). ``--quick``: two speeds, one scene, seconds;
``--speeds``, ``--cases``, ``--radii``: a subset of the sweep; ``--floor``: where each toward
case's penetration comes from (``service/dynamic_real_trace.py``: sampling, prediction,
overlap at the worst tick, ``real_floor``).
"""
from __future__ import annotations

import argparse

from pointfence.service import dynamic_scenes as ds


def add_arguments(p):
    p.add_argument("--study", metavar="DIR", default=None,
                   help="write the adaptive radius study (radius_study.md/.csv/.png) into DIR")
    p.add_argument("--no-study", action="store_true", help="skip the adaptive radius study (about 15 s)")
    p.add_argument("--latency", type=float, default=0.1, help="camera latency T of the latency runs, s (default 0.1)")
    p.add_argument("--real", action="store_true",
                   help="chapter 6 on real depth frames moved at known speeds (service/dynamic_real.py)")
    p.add_argument("--frames", action="append", default=None, metavar="DIR",
                   help="with --real: a recording (directory of 16-bit depth images + intrinsics, or a name in "
                        "../shared/data) to move instead of the default two; repeatable")
    p.add_argument("--no-rig", action="store_true",
                   help="with --real: skip the real-rig figures (occlusion, fused rig, radius study)")
    p.add_argument("--no-propagation", action="store_true",
                   help="with --real: the estimator without neighbour propagation (min_neighbours = 0), to compare")
    p.add_argument("--near-reading", action="store_true",
                   help="with --real: the cameras take each reading at the near end of its depth step "
                        "([[camera]] near_reading; the recordings' fitted steps)")
    p.add_argument("--quick", action="store_true",
                   help="with --real: a short sweep (one scene, 0.1 and 0.3 m/s, toward the camera), seconds")
    p.add_argument("--speeds", type=_floats, default=None, metavar="V,V,...",
                   help="with --real: the sweep's surface speeds, m/s (default 0.05 ... 1.5)")
    p.add_argument("--cases", type=_cases, default=None, metavar="MOTION/MASTER,...",
                   help="with --real: the sweep's cases, e.g. toward/hold,toward/push (default: all four)")
    p.add_argument("--radii", type=_floats, default=None, metavar="R,R,...",
                   help="with --real: the fixture radii r_f, m (default 0.01,0.02)")
    p.add_argument("--floor", action="store_true",
                   help="with --real: where the penetration comes from (service/dynamic_real_trace.py): per toward "
                        "case and speed (--speeds, default 0.1,0.3), 1 cm fixture, with prediction, the worst tick's "
                        "sampling / prediction / overlap terms")


def _floats(text: str) -> tuple:
    try:
        out = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        out = ()
    if not out or not all(0 < x < 10 for x in out):
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated positive numbers, e.g. 0.1,0.3")
    return out


def _cases(text: str) -> tuple:
    from pointfence.service.dynamic_real import CASES

    out = tuple(tuple(c.strip().split("/")) for c in text.split(",") if c.strip())
    bad = [("/".join(c)) for c in out if c not in CASES]
    if not out or bad:
        raise argparse.ArgumentTypeError(f"{text!r}: expected cases among {', '.join('/'.join(c) for c in CASES)}")
    return out


def _speed(predict, backend, device, **kw):
    return ds.popthrough_speed(predict, backend=backend, device=device, **kw)


def run_real(args) -> dict:
    """The ``--real`` figures (see the module docstring)."""
    from pointfence.kernels.motion import MotionModel
    from pointfence.service import dynamic_real as dr
    from pointfence.service import dynamic_real_study as study

    b, dev = args.backend, args.device
    scenes = tuple(args.frames) if args.frames else dr.REAL_SCENES[:1] if args.quick else dr.REAL_SCENES
    opts = dict(speeds=dr.QUICK_SPEEDS, radii=(0.01,), cases=(("toward", "hold"),)) if args.quick else {}
    for key in ("speeds", "cases", "radii"):
        if getattr(args, key, None):
            opts[key] = getattr(args, key)
    mo = {"min_neighbours": 0} if args.no_propagation else {}
    near = bool(getattr(args, "near_reading", False))
    res = dr.sweep(scenes, backend=b, device=dev, model_options=mo, near_reading=near, **opts)
    out = {"backend": b, "motion_options": mo, "near_reading": near, "frame_rate_hz": dr.RATE_HZ,
           "tick_rate_hz": dr.TICK_HZ,
           "robot_speed_limit_mps": dr.ROBOT_SPEED,
           "real_scenes": res["scenes"], "real_rows": res["rows"],
           "real_held_speed_mps": dr.held_speeds(res["rows"], proxy_mm=0.5, robot_mm=1.0),
           "real_no_popthrough_speed_mps": dr.held_speeds(res["rows"], proxy_mm=float("inf"), robot_mm=float("inf"),
                                                          popped=True)}
    if getattr(args, "floor", False):
        from pointfence.service.dynamic_real_trace import floor_table

        out["real_floor"] = floor_table(scenes, speeds=opts.get("speeds", dr.QUICK_SPEEDS),
                                        masters=sorted({m for k, m in opts.get("cases", dr.CASES) if k == "toward"}),
                                        backend=b, device=dev)
    est = dict(speeds=(0.3,), motions=("toward",)) if args.quick else dict(speeds=(0.3, 1.0))
    out["real_estimator"] = study.estimator_table(scenes, backend=b, device=dev, model=MotionModel(enabled=True, **mo),
                                                  **est)
    if not (args.frames or args.quick or args.no_rig):
        from pointfence.service.dynamic_real_rig import rig_figures  # the real two-camera rig, real noise

        out["real_rig"] = rig_figures(b, dev)
    return out


def run(args) -> dict:
    if args.real:
        return run_real(args)
    b, dev = args.backend, args.device
    out = {"backend": b, "frame_rate_hz": ds.RATE_HZ, "tick_rate_hz": ds.TICK_HZ, "fixture_radius_m": 0.02,
           "speeds_tried_mps": list(ds.SPEEDS)}
    pop, held, runs = {}, {}, {}
    for name, kw in (("without_prediction", dict(predict=False)), ("with_prediction", dict(predict=True)),
                     (f"without_prediction_latency_{args.latency:g}s", dict(predict=False, latency=args.latency)),
                     (f"with_prediction_latency_{args.latency:g}s", dict(predict=True, latency=args.latency)),
                     ("rendering_r1_5mm_without_prediction", dict(predict=False, mode="rendering")),
                     ("rendering_r1_5mm_with_prediction", dict(predict=True, mode="rendering"))):
        r = _speed(kw.pop("predict"), b, dev, **kw)
        pop[name], held[name], runs[name] = r["popthrough_mps"], r["held_mps"], r["runs"]
    out["popthrough_speed_mps"] = pop
    out["held_speed_mps"] = held
    out["popthrough_runs"] = {k: [{"speed_mps": v, "popped": p, "max_penetration_mm": m} for v, p, m in r]
                              for k, r in runs.items()}
    one, two = ds.occlusion_run(1, backend=b, device=dev), ds.occlusion_run(2, backend=b, device=dev)
    out["occlusion_penetration_mm_1cam"] = round(one.max_penetration * 1e3, 3)
    out["occlusion_penetration_mm_2cam"] = round(two.max_penetration * 1e3, 3)
    sf = ds.self_filter_ratio(backend=b, device=dev)
    out["self_filter_false_fixture_ratio"] = sf.pop("self_filter_false_fixture_ratio")
    out["self_filter"] = sf
    if not args.no_study or args.study:
        rows = ds.radius_study(backend=b, device=dev)
        out["radius_study"] = rows
        if args.study:
            out["radius_study_files"] = ds.write_radius_study(rows, args.study)
    return out
