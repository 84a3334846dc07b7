"""`pointfence inspect FILE.mcap`: what a recording holds, and how well the fixture did.

    pointfence inspect RUN.mcap [--json] [--plot DIR] [--recompute | --no-measures] [--backend B]

Prints the run's start (UTC) and duration, its ticks (recorded and lost while recording), every
topic with its schema, message count and rate, the cameras (resolution, intrinsics, distortion,
depth scale, source, recorded frames and their rate), the arms (CRTK robot and master names,
robot model), the faults and holds (from ``/pointfence/events``: each with its tick, time,
reasons and the SAFETY.md invariants behind them) and the dissertation's measures (6.1;
``run_measures``): the ones stored with the recording (in the file's ``pointfence/measures``
metadata, else its ``FILE.mcap.measures.json``), or computed now from the recorded depth when
none are stored or with ``--recompute``. A file cut short (a crash, ``kill -9``, a full disk) is
read up to its last whole chunk and said to be truncated; everything shown is what precedes the
cut. ``--json`` prints the same as one JSON document; ``--plot DIR`` writes the demo's figure
for each arm (signed distance of robot and master to the forbidden region over time, and the
x-z paths over the region as the last snapshot saw it: ``report.plot_experiment``) and a
timeline of forces and holds.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from pointfence.kernels.errors import InputError

from . import run_measures
from .recording_info import scan
from .ros2_schemas import camera_topics, legacy_camera_topics, master_ns, robot_ns


def add_arguments(p):
    p.add_argument("recording", metavar="FILE.mcap", help="an MCAP recording (`pointfence serve|demo --record FILE.mcap`)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON document instead of text")
    p.add_argument("--plot", metavar="DIR", default=None,
                   help="write the run's figures (PNG) to DIR: per arm the distances to the forbidden region and the "
                        "x-z paths (the demo's figure), and a timeline of forces and holds")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--recompute", action="store_true",
                   help="compute the measures from the recorded depth even if the recording has them stored")
    g.add_argument("--no-measures", action="store_true",
                   help="show no measures unless stored (no computation: fast on long runs)")
    p.add_argument("--backend", default=None,
                   help="backend that rebuilds the snapshots for the measures (default: the recorded run's)")
    p.add_argument("--device", default=None, help="device of that backend")


def build(path, *, recompute: bool = False, measure: bool = True, backend=None, device=None, want_traces=False):
    """The report of recording ``path`` as a dict (what ``--json`` prints), and the measures'
    ``run_measures.Evaluation`` if they were computed (None otherwise; ``want_traces`` computes
    them even when stored, for the plots)."""
    from .mcap_read import open_recording

    sc = scan(path)
    rec = open_recording(path)          # InputError: not a pointfence recording, or damaged at its start
    meta = rec.meta
    lay, rows = rec.layout, rec.rows
    rate = float(meta.get("rate_hz", 1000.0))
    first, last = sc.span_ns
    ticks_t = rows[:, lay.cols[("in", "t")][0]] if len(rows) else np.zeros(0)
    rep = {"file": str(sc.path), "bytes": sc.bytes, "complete": sc.complete, "truncated": sc.torn,
           "note": None if sc.complete else _truncated_note(sc, rec),
           "writer": sc.library, "profile": sc.profile,
           "start_utc": None if first is None else _utc(first),
           "duration_s": None if first is None else round((last - first) * 1e-9, 3),
           "ticks": {"recorded": int(len(rows)), "span_s": round(float(ticks_t[-1] - ticks_t[0]) + 1 / rate, 3)
                     if len(rows) else 0.0, "rate_hz": rate, "lost_while_recording": meta.get("ticks_lost"),
                     "snapshots": len(rec.snapshots), "snapshots_dropped_while_recording": meta.get("snapshots_dropped")},
           "architecture": meta.get("architecture"), "backend": meta.get("backend"),
           "topics": [{"topic": s.topic, "schema": s.schema, "messages": s.count,
                       "rate_hz": None if s.rate_hz is None else round(s.rate_hz, 2)} for s in sc.topics.values()],
           "cameras": _cameras(meta, sc), "arms": _arms(rec), **_events(sc, first)}
    ev = None
    have = None if recompute else run_measures.stored(path, rec.metadata)   # (JSON values decoded)
    if have is not None:
        rep["measures"] = {**have[0], "stored_in": have[1]}
    if (have is None and measure) or want_traces:
        ev = run_measures.evaluate(rec, backend=backend, device=device)
        if have is None:
            rep["measures"] = {**ev.summary, "stored_in": None, "computed": "now, by pointfence inspect"}
    if "measures" not in rep:
        rep["measures"] = None
    return rep, ev


def _utc(ns: int) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(ns // 1_000_000_000)) + f".{(ns // 1_000_000) % 1000:03d}Z"


def _truncated_note(sc, rec) -> str:
    return (f"TRUNCATED: {sc.torn}. Everything before the cut is read (the recorder writes whole chunks every "
            f"{rec.meta.get('flush_s', 0.25)} s, so a crash loses at most the last second); counts, events and "
            "measures below cover only that part, and the run's end-of-run metadata (ticks lost, measures) may be "
            "missing")


def _cameras(meta: dict, sc) -> list:
    out = []
    for c in meta.get("cameras", []):
        depth = (sc.topics.get(camera_topics(c["name"])["depth"])                  # (raw images, or PNGs
                 or sc.topics.get(legacy_camera_topics(c["name"])["depth"]))       # of older recordings)
        out.append({"name": c["name"], "source": c.get("source"), "width": c["width"], "height": c["height"],
                    "fx": c["fx"], "fy": c["fy"], "cx": c["cx"], "cy": c["cy"], "dist": c.get("dist"),
                    "depth_scale": c.get("depth_scale"), "configured_rate_hz": c.get("rate_hz"),
                    "near_reading": bool(c.get("near_reading", False)), "depth_step_inv": c.get("depth_step_inv", 0.0),
                    "frames": 0 if depth is None else depth.count,
                    "frame_rate_hz": None if depth is None or depth.rate_hz is None else round(depth.rate_hz, 2)})
    return out


def _arms(rec) -> list:
    from .mcap_replay import recording_config

    try:
        model = recording_config(rec).robot.model
    except InputError:
        model = None
    present = (rec.meta.get("start") or {}).get("robot_present") or [None] * rec.layout.n
    return [{"arm": b, "robot": robot_ns(b), "master": master_ns(b), "robot_model": model if present[b] else "none (ideal)"
             if present[b] is not None else model} for b in range(rec.layout.n)]


def _events(sc, first) -> dict:
    evs = [{**{k: v for k, v in e.items() if k != "log_ns"},
            "t_s": None if first is None else round((e["log_ns"] - first) * 1e-9, 3)} for e in sc.events]
    holds = [e for e in evs if e["kind"] == "hold"]
    reasons: dict = {}
    for e in holds:
        for r in filter(None, e["reason"].split(",")):
            reasons[r] = reasons.get(r, 0) + 1
    return {"faults": [e for e in evs if e["kind"] == "fault"], "holds": holds, "hold_reasons": reasons,
            "events": evs}


# --- text ---------------------------------------------------------------------------------------------
def _mm(v) -> str:
    return "-" if v is None else f"{v * 1000:.2f} mm"


def text(rep: dict) -> str:
    """The report as the lines ``pointfence inspect`` prints."""
    L = []
    t = rep["ticks"]
    L.append(f"recording  {rep['file']} ({rep['bytes'] / 1e6:.2f} MB), "
             + ("complete" if rep["complete"] else "TRUNCATED"))
    if rep["note"]:
        L.append(f"  note: {rep['note']}")
    L.append(f"run        started {rep['start_utc']}, {rep['duration_s']} s; {t['recorded']} ticks (nominal {t['rate_hz']:g} Hz) over "
             f"{t['span_s']} s (lost while recording: {t['lost_while_recording']}), {t['snapshots']} snapshots "
             f"(dropped: {t['snapshots_dropped_while_recording']}); architecture {rep['architecture']}, backend "
             f"{rep['backend']}")
    L.append(f"topics     {len(rep['topics'])}")
    w = max((len(x["topic"]) for x in rep["topics"]), default=10)
    for x in rep["topics"]:
        rate = "-" if x["rate_hz"] is None else f"{x['rate_hz']:.1f} Hz"
        L.append(f"  {x['topic']:<{w}}  {x['messages']:>8d}  {rate:>10s}  {x['schema']}")
    L.append(f"cameras    {len(rep['cameras'])}")
    for c in rep["cameras"]:
        dist = "none" if not c["dist"] or not any(c["dist"]) else " ".join(f"{d:g}" for d in c["dist"])
        rate = "-" if c["frame_rate_hz"] is None else f"{c['frame_rate_hz']:.1f} Hz"
        near = ""
        if c["near_reading"] or c["depth_step_inv"]:
            step = f", disparity step {c['depth_step_inv']:g} 1/m" if c["depth_step_inv"] else ""
            near = f", readings {'at the near end of their steps' if c['near_reading'] else 'as read'}{step}"
        L.append(f"  {c['name']}: {c['width']}x{c['height']}, fx {c['fx']:g} fy {c['fy']:g} cx {c['cx']:g} "
                 f"cy {c['cy']:g} px, distortion {dist}, depth scale {c['depth_scale']:g} m{near}; {c['frames']} "
                 f"frames recorded ({rate}; configured {c['configured_rate_hz']:g} Hz); source {c['source']}")
    L.append(f"arms       {len(rep['arms'])}")
    for a in rep["arms"]:
        L.append(f"  arm {a['arm']}: robot {a['robot']} ({a['robot_model']}), master {a['master']}")
    L.append(f"faults     {len(rep['faults'])}")
    for e in rep["faults"]:
        L.append(f"  t {e['t_s']} s, tick {e['tick']}, arm {e['arm']}: {e['reason']} ({e['invariant']}): {e['detail']}")
    why = ", ".join(f"{k} x{v}" for k, v in rep["hold_reasons"].items())
    L.append(f"holds      {len(rep['holds'])}" + (f" ({why})" if why else ""))
    for e in rep["holds"][:20]:
        L.append(f"  t {e['t_s']} s, tick {e['tick']}, arm {e['arm']}: {e['reason']} (invariants {e['invariant']})")
    if len(rep["holds"]) > 20:
        L.append(f"  ... {len(rep['holds']) - 20} more (--json lists every one)")
    others = [e for e in rep["events"] if e["kind"] in ("control", "architecture")]
    if others:
        L.append(f"control    {len(others)} change(s): " + "; ".join(f"t {e['t_s']} s {e['detail']}" for e in others[:10]))
    m = rep["measures"]
    if m is None:
        L.append("measures   none stored (run without --no-measures to compute them from the recorded depth)")
        return "\n".join(L)
    if "error" in m:
        L.append(f"measures   could not be computed: {m['error']}")
        return "\n".join(L)
    where = m.get("stored_in") or m.get("computed")
    L.append(f"measures   from the {m.get('from', 'recorded depth')} ({m.get('ticks_measured')} of {m.get('ticks')} ticks, "
             f"{m.get('snapshots_rebuilt')} snapshots rebuilt on {m.get('backend')}"
             + (f", missing {m['snapshots_missing']}" if m.get("snapshots_missing") else "") + f"; {where})")
    L.append(f"  {run_measures.line(m)}")
    for a in m.get("arms", []):
        deep = a.get("deepest")
        L.append(f"  arm {a['arm']} {a['robot']}: safety {_mm(a['safety_max_penetration_m'])}"
                 + (f" (tick {deep['tick']}, t {deep['t_s']} s)" if deep else "")
                 + f", submittance {_mm(a['submittance_min_distance_m'])}, tracking {_mm(a['tracking_rms_m'])}, "
                 f"closest {_mm(a['min_robot_distance_m'])}; inside the region {a['ticks_inside']} ticks "
                 f"({a['time_inside_s']} s), coupled {a['ticks_coupled']} ticks")
    return "\n".join(L)


# --- plots --------------------------------------------------------------------------------------------
def plot(rep: dict, ev, out_dir, every: int = 5) -> list:
    """The run's PNG figures in ``out_dir``; returns the files written."""
    from . import report

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"--plot {str(out)!r}: cannot make the folder ({e.strerror or e}); choose a folder you may "
                         "write to") from None
    files = []
    region = None if ev.last_surface is None else (lambda pts, t: ev.last_surface.signed_distance(pts))
    for b, tr in enumerate(ev.traces):
        if not len(tr["t"]):
            continue
        sl = slice(0, None, every)
        trace = {k: (v[sl] if isinstance(v, np.ndarray) else v) for k, v in tr.items()}
        if region is not None:
            trace["region"] = region
        path = out / f"arm{b}_{robot_ns(b)}_distances.png"
        report.plot_experiment("recording", [(rep["architecture"], trace)], path,
                               title=f"{Path(rep['file']).name}, arm {b} ({robot_ns(b)}): recorded depth")
        if path.exists():
            files.append(path)
    path = out / "timeline.png"
    _timeline(rep, ev, path, every)
    files.append(path)
    return files


def _timeline(rep: dict, ev, path, every: int) -> None:
    from .report import _plt

    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 3.5))
    for b, tr in enumerate(ev.traces):
        if len(tr["t"]):
            ax.plot(tr["t"][::every], np.linalg.norm(tr["force"][::every], axis=1), lw=0.9, label=f"|F| arm {b}")
    rate = rep["ticks"]["rate_hz"]        # an event's tick k is at loop time k / rate
    for e in rep["holds"]:
        ax.axvline(e["tick"] / rate, color="C3", lw=0.6, ls="--")
    for e in rep["faults"]:
        ax.axvline(e["tick"] / rate, color="k", lw=1.0)
    ax.set(xlabel="t (s, loop clock)", ylabel="force on the master (N)",
           title=f"forces; holds (red dashed) {len(rep['holds'])}, faults (black) {len(rep['faults'])}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run(args) -> int:
    if args.plot and args.no_measures:
        raise InputError("--plot needs the per-tick distances that the measures compute; drop --no-measures")
    rep, ev = build(args.recording, recompute=args.recompute, measure=not args.no_measures, backend=args.backend,
                    device=args.device, want_traces=bool(args.plot))
    if args.plot:
        rep["plots"] = [str(f) for f in plot(rep, ev, args.plot)]
    print(json.dumps(rep, indent=2) if args.json else text(rep)
          + (f"\nplots      {', '.join(rep['plots'])}" if args.plot else ""))
    return 0
