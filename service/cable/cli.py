"""``pointfence cable``: demo, identify, calib-tension, run.

    pointfence cable demo [--out DIR] [--quick]
    pointfence cable identify [--tension G] [--duration S] [--rounds N] [--out FILE]
    pointfence cable calib-tension [--tensions G,G,...] [--out FILE]   (also `pointfence calib tension`)
    pointfence cable run [--seconds S] [--grasp RAD] [--contact]
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time

from pointfence.kernels.errors import InputError


def _tensions(s: str) -> list[float]:
    try:
        v = [float(x) for x in s.split(",") if x.strip()]
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"tensions {s!r}: expected comma-separated grams, e.g. 450,900,1400") from e
    if len(v) < 2 or any(not math.isfinite(x) or x <= 0 for x in v):
        raise argparse.ArgumentTypeError(f"tensions {s!r}: need at least two positive values in grams")
    return v


def add_calib_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of the tension calibration (shared with ``pointfence calib tension``)."""
    p.add_argument("--tensions", type=_tensions, default=[450.0, 650.0, 900.0, 1150.0, 1400.0, 1650.0, 1900.0],
                   help="known tensions [g] at which to identify k_e on the simulated plant")
    p.add_argument("--points", help="CSV file of 'tension_g,k_e' rows measured on hardware instead of simulating")
    p.add_argument("--duration", type=float, default=30.0, help="seconds of excitation per identification stage")
    p.add_argument("--out", default="cable_tension.json", help="calibration output (JSON)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="cable_cmd", metavar="ACTION", required=True)
    d = sub.add_parser("demo", help="reproduce figs. A.1, 4.3, 4.4, 4.8, 5.1-5.5 and table 5.1 on the simulated plant")
    d.add_argument("--out", default="out/cable_demo", help="report folder (report.md, PNGs, metrics.json)")
    d.add_argument("--quick", action="store_true", help="short identifications (smoke test, worse numbers)")
    i = sub.add_parser("identify", help="two-stage UKF identification (section 4.4) on the simulated plant")
    i.add_argument("--tension", type=float, default=743.0, help="true cable tension of the simulated plant [g]")
    i.add_argument("--duration", type=float, default=30.0, help="seconds of excitation per stage")
    i.add_argument("--rounds", type=int, default=3, help="repetitions of the two stages")
    i.add_argument("--out", help="write the identified parameters to this JSON file")
    c = sub.add_parser("calib-tension", help="fit tension = a + b ln(k_e) (chapter 5)")
    add_calib_arguments(c)
    r = sub.add_parser("run", help="run the 1 kHz control thread against the simulated plant")
    r.add_argument("--seconds", type=float, default=2.0)
    r.add_argument("--grasp", type=float, default=0.3, help="grasp command (desired jaw angle) [rad]")
    r.add_argument("--contact", action="store_true", help="tissue beyond 0.1 rad")


def run_calib(args) -> int:
    from .tension import fit_tension_curve

    if args.points:
        import numpy as np

        try:
            data = np.loadtxt(args.points, delimiter=",", ndmin=2)
        except (OSError, ValueError) as e:
            raise InputError(f"--points {args.points}: cannot read 'tension_g,k_e' rows ({e})") from e
        if data.shape[1] != 2:
            raise InputError(f"--points {args.points}: rows have {data.shape[1]} columns, expected 2 (tension_g,k_e)")
        tensions, ks = data[:, 0].tolist(), data[:, 1].tolist()
    else:
        from .identify import identify
        from .params import true_params_at_tension
        from .plant import SimulatedPlant

        tensions, ks = list(args.tensions), []
        for j, t in enumerate(tensions):
            res = identify(SimulatedPlant(true_params_at_tension(t), seed=40 + j),
                           duration1=args.duration, duration2=args.duration)
            ks.append(res.params.k_e)
            print(f"tension {t:.0f} g: identified k_e = {res.params.k_e:.0f} N/m")
    curve = fit_tension_curve(tensions, ks)
    curve.save(args.out)
    print(f"tension_g = {curve.a:.1f} + {curve.b:.1f} ln(k_e); written to {args.out}")
    return 0


def run(args) -> int:
    cmd = args.cable_cmd
    if cmd == "demo":
        from .experiments import run_all, write_report

        R = run_all(quick=args.quick)
        path = write_report(R, args.out)
        m = json.loads((path.parent / "metrics.json").read_text())
        print(f"tracking r.m.s. error: free motion {m['tracking_rms_free_rad']:.4f} rad, with tissue "
              f"{m['tracking_rms_tissue_rad']:.4f} rad (seed: 0.0069 rad)")
        for T, row in m["chapter5"].items():
            print(f"chapter 5 @ {float(T):.0f} g: hand-trajectory r.m.s. error nominal (743 g) parameters "
                  f"{row['nominal']['hand_rms_rad']:.4f} rad, re-identified {row['adjusted']['hand_rms_rad']:.4f} rad")
        print(f"report: {path}")
        return 0
    if cmd == "identify":
        from .identify import identify
        from .params import PARAM_NAMES, true_params_at_tension
        from .plant import SimulatedPlant

        truth = true_params_at_tension(args.tension)
        t0 = time.perf_counter()
        res = identify(SimulatedPlant(truth), duration1=args.duration, duration2=args.duration, rounds=args.rounds)
        out = {n: getattr(res.params, n) for n in PARAM_NAMES}
        for n in ("k_e", "b_e", "Fc_m", "Fc_l", "Fv_m", "Fv_l"):
            print(f"{n:5s} identified {getattr(res.params, n):.5g}  (simulated truth {getattr(truth, n):.5g})")
        print(f"({time.perf_counter() - t0:.1f} s)")
        if args.out:
            with open(args.out, "w") as f:
                json.dump(out, f, indent=2)
        return 0
    if cmd == "calib-tension":
        return run_calib(args)
    if cmd == "run":
        from .controller import CableController
        from .params import GrasperParams
        from .plant import HuntCrossley, SimulatedPlant

        if not (math.isfinite(args.seconds) and 0 < args.seconds <= 600):
            raise InputError(f"--seconds {args.seconds} must be in (0, 600]")
        plant = SimulatedPlant(contact=HuntCrossley(q_contact=0.1) if args.contact else None)
        ctl = CableController(plant, GrasperParams())
        with ctl:
            ctl.set_grasp_command(args.grasp)
            time.sleep(args.seconds)
            s = ctl.status()
        print(json.dumps({**s.__dict__, "true_link_angle": plant.link_angle}, indent=2, default=str))
        return 0 if s.fault is None else 1
    print(f"unknown cable action {cmd!r}", file=sys.stderr)
    return 2
