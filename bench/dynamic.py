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
"""
from __future__ import annotations

from pointfence.service import dynamic_scenes as ds


def add_arguments(p):
    p.add_argument("--study", metavar="DIR", default=None,
                   help="write the adaptive radius study (radius_study.md/.csv/.png) into DIR")
    p.add_argument("--no-study", action="store_true", help="skip the adaptive radius study (about 15 s)")
    p.add_argument("--latency", type=float, default=0.1, help="camera latency T of the latency runs, s (default 0.1)")


def _speed(predict, backend, device, **kw):
    return ds.popthrough_speed(predict, backend=backend, device=device, **kw)


def run(args) -> dict:
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
