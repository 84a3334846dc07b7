"""The demo's report folder: PNG plots of the chapter-2 probes (figs. 2.12-2.15) and of the
chapter-3 experiments (figs. 3.8-3.10, one panel per architecture), and the results table as
markdown (``table.md``) and JSON (``table.json``). Matplotlib on the Agg backend (no display).

``trace_of(service, sources, cfg)`` takes what a run's plots need from its recorder (every
``every``-th tick): times on the scene's clock, robot, command, mapped master and proxy
positions, and their signed distances to the forbidden region (ground truth of the synthetic
scene, as the measures use).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np

from . import measures

#: table columns: key, markdown header
COLUMNS = (("scenario", "scenario"), ("figure", "fig."), ("arch", "arch"), ("mode", "mode"),
           ("safety_mm", "safety (mm)"), ("submittance_mm", "submittance (mm)"), ("tracking_mm", "tracking (mm)"),
           ("popthrough_m_s", "pop-through (m/s)"), ("tick_us_p99", "tick p99 (us)"), ("misses", "misses"))
FIGURES = {"inclined_plane": "3.8", "balloon": "3.9", "rocking_platform": "3.10"}


def trace_of(svc, sources, cfg, every: int = 5) -> Optional[dict]:
    rec = svc.recorder
    if rec is None or rec.count == 0:
        return None
    a = rec.arrays()     # in tick order (a streamed recording: read back from its file)
    sl = slice(0, len(a["rows"]), every)
    rows = a["rows"][sl]
    t = rows[:, 0] + svc.scene_time_offset
    xr, cmd = a["robots"][sl, 0, :3].copy(), a["robots"][sl, 0, 3:].copy()
    xm, proxy = a["masters_world"][sl, 0].copy(), rows[:, 7:10].copy()
    out = {"t": rows[:, 0].copy(), "xr": xr, "cmd": cmd, "xm": xm, "proxy": proxy, "force": rows[:, 16:19].copy(),
           "radius": cfg.pipeline.radius.r_base}
    try:
        region = measures.region_for(cfg, sources, svc.pipeline)
        out["d_r"], out["d_m"] = region(xr, t), region(xm, t)
        scene = next((s.scene for s in sources if getattr(s, "scene", None) is not None), None)
        if scene is not None and not scene.moving:
            out["region"] = region
    except ValueError:
        pass
    return out


def row_for_run(scene: str, s: dict, timing) -> dict:
    mm = lambda v: None if v is None else round(v * 1000, 3)  # noqa: E731
    return {"scenario": scene, "figure": FIGURES.get(scene, ""), "arch": s.get("architecture"), "mode": "fixture",
            "safety_mm": mm(s.get("safety_max_penetration_m")), "submittance_mm": mm(s.get("submittance_min_distance_m")),
            "tracking_mm": mm(s.get("tracking_rms_m")), "popthrough_m_s": None,
            "tick_us_p99": round(timing.compute_us_p99, 1) if timing is not None else s.get("tick_us_p99"),
            "misses": f"{timing.misses}/{timing.periods}" if timing is not None else None}


def row_for_probe(p: dict) -> dict:
    us = np.asarray(p.get("tick_us") or [0.0])
    pen = p.get("penetration_m")
    return {"scenario": p["name"], "figure": p["figure"], "arch": "-", "mode": "rendering",
            "safety_mm": None if pen is None else round(pen * 1000, 3), "submittance_mm": None, "tracking_mm": None,
            "popthrough_m_s": p.get("popthrough_speed"), "tick_us_p99": round(float(np.percentile(us, 99)), 1),
            "misses": None}


def markdown_table(rows: list) -> str:
    def cell(v):
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v)

    lines = ["| " + " | ".join(h for _, h in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(cell(r.get(k)) for k, _ in COLUMNS) + " |" for r in rows]
    return "\n".join(lines) + "\n"


# --- plots ------------------------------------------------------------------------------------------
def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def plot_push_plane(p: dict, path) -> None:
    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    a.plot(p["t"], p["hip_z"] * 1000, label="HIP z")
    a.plot(p["t"], p["proxy_z"] * 1000, label="proxy z")
    a.axhline(p["r1"] * 1000, color="k", lw=0.6, ls="--", label="surface + r1")
    a.set(xlabel="t (s)", ylabel="z (mm)", title="fig. 2.12: push into a plane")
    a.legend()
    down = slice(0, len(p["t"]) // 2)
    b.plot(-p["hip_z"][down] * 1000, p["force_z"][down], label="pushing in")
    b.plot(-p["hip_z"][down.stop:] * 1000, p["force_z"][down.stop:], label="coming out")
    b.set(xlabel="HIP depth below the plane (mm)", ylabel="F_z (N)", title=f"force (k = {p['k']:.0f} N/m, FIR)")
    b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _profile_axes(ax, run, title):
    ax.plot(run["profile_x"] * 1000, run["profile_z"] * 1000, color="0.3", lw=2, label="true surface")
    ax.plot(run["hip"][:, 0] * 1000, run["hip"][:, 2] * 1000, color="C0", lw=0.8, label="HIP")
    px = run["proxy"][run.get("settle", 0):]
    ax.plot(px[:, 0] * 1000, px[:, 2] * 1000, color="C3", lw=1.2, label="proxy centre")
    ax.set(xlabel="x (mm)", ylabel="z (mm)", title=title)
    ax.set_aspect("equal", adjustable="datalim")


def plot_surfaces(p: dict, path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    for ax, run in zip(axes.ravel(), p["runs"]):
        _profile_axes(ax, run, f"{run['label']}: penetration {run['penetration_m'] * 1000:.2f} mm")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("fig. 2.13: sliding over concave, convex and corner surfaces (HIP 6 mm under)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_ledge(p: dict, path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4))
    _profile_axes(ax, p, f"fig. 2.14: 5 mm ledge (proxy levels {p['upper_z'] * 1000:.1f} / {p['lower_z'] * 1000:.1f} mm)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_translating_plane(p: dict, path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for r in p["runs"]:
        style = "-" if not r["popped"] else "--"
        ax.plot(r["t"] * 1000, r["distance"] * 1000, style, label=f"{r['speed']:.2f} m/s" + (" (pops through)" if r["popped"] else ""))
    ax.axhline(0, color="k", lw=0.8)
    ax.axhline(p["r1"] * 1000, color="k", lw=0.6, ls=":", label="r1")
    v = p["popthrough_speed"]
    ax.set(xlabel="t (ms)", ylabel="proxy centre to plane (mm)",
           title=f"fig. 2.15: rising plane, 30 Hz frames: pop-through at {v} m/s" if v else
           "fig. 2.15: rising plane, 30 Hz frames: no pop-through at the speeds tried")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_experiment(scene: str, runs: list, path, title: Optional[str] = None) -> None:
    """Signed distances of the robot (and the mapped master) to the forbidden region over time,
    one panel per architecture; for static scenes also the robot's x-z path over the region.
    ``title``: the figure's title (default: the dissertation figure of ``scene``)."""
    plt = _plt()
    runs = [(a, tr) for a, tr in runs if tr is not None and "d_r" in tr]
    if not runs:
        return
    static = "region" in runs[0][1]
    ncol = len(runs) + (1 if static else 0)
    fig, axes = plt.subplots(1, ncol, figsize=(4.2 * ncol, 4), squeeze=False)
    axes = axes[0]
    for ax, (arch, tr) in zip(axes, runs):
        ax.plot(tr["t"], tr["d_m"] * 1000, color="C0", lw=0.8, label="master X_m")
        ax.plot(tr["t"], tr["d_r"] * 1000, color="C3", lw=1.4, label="robot X_r")
        ax.axhline(0, color="k", lw=0.8)
        pen = max(0.0, -float(np.nanmin(tr["d_r"]))) * 1000
        ax.set(xlabel="t (s)", ylabel="distance to the forbidden region (mm)",
               title=f"architecture {arch}: max penetration {pen:.1f} mm")
        ax.set_ylim(max(ax.get_ylim()[0], -60), ax.get_ylim()[1])
        ax.legend(fontsize=8)
    if static:
        ax = axes[-1]
        tr = runs[0][1]
        allp = np.concatenate([t["xr"] for _, t in runs] + [t["xm"] for _, t in runs])
        mid = (allp.min(axis=0) + allp.max(axis=0)) / 2
        half = np.maximum((allp.max(axis=0) - allp.min(axis=0)) / 2 + 0.01, 0.04)
        lo, hi = mid - half, mid + half
        gx, gz = np.linspace(lo[0], hi[0], 90), np.linspace(lo[2], hi[2], 70)
        X, Z = np.meshgrid(gx, gz)
        y0 = float(np.median(allp[:, 1]))
        pts = np.stack([X.ravel(), np.full(X.size, y0), Z.ravel()], axis=1)
        D = tr["region"](pts, 0.0).reshape(X.shape)
        ax.contourf(X * 1000, Z * 1000, (D < 0).astype(float), levels=[0.5, 1.5], colors=["#f4b6b6"])
        ax.contour(X * 1000, Z * 1000, D + tr["radius"], levels=[0.0], colors=["0.3"], linewidths=1.5)
        for i, (arch, t) in enumerate(runs):
            ax.plot(t["xr"][:, 0] * 1000, t["xr"][:, 2] * 1000, color=f"C{i + 1}", lw=1.3, label=f"robot, {arch}")
        ax.plot(runs[0][1]["xm"][:, 0] * 1000, runs[0][1]["xm"][:, 2] * 1000, color="C0", lw=0.7, ls="--", label="master X_m")
        ax.set(xlabel="x (mm)", ylabel="z (mm)", title="x-z paths (red: forbidden region)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(fontsize=7)
    fig.suptitle(title or f"fig. {FIGURES.get(scene, '?')}: {scene.replace('_', ' ')}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _speed(v) -> str:
    return "none up to 1.5" if v is None else f"{v:g}"


def dynamic_rows(res: dict) -> list:
    """The chapter-6 figures (``dynamic_demo.run``) as rows {"experiment", "measure", "without",
    "with"}: pop-through speeds without/with motion prediction, the service's fixture penetration
    on the plane rising at 0.5 m/s, occlusion penetration with one/two cameras, the self-filter."""
    out = []
    svc = res.get("service_plane_0.5mps")
    if svc:
        out.append({"experiment": "service, plane rising at 0.5 m/s (arch III)",
                    "measure": "fixture penetration by the robot (mm), motion prediction",
                    "without": svc["without_prediction"]["penetration_mm_robot"],
                    "with": svc["with_prediction"]["penetration_mm_robot"]})
    for label, v in res.items():
        if isinstance(v, dict) and "without_prediction" in v and "with_prediction" in v and label != "service_plane_0.5mps":
            out.append({"experiment": f"translating plane, {label}", "measure": "pop-through speed (m/s), motion prediction",
                        "without": _speed(v["without_prediction"]), "with": _speed(v["with_prediction"])})
    if "occlusion_penetration_mm_1cam" in res:
        out.append({"experiment": "tool's shadow over a protected disc (arch III)",
                    "measure": "fixture penetration (mm), second (side) camera",
                    "without": res["occlusion_penetration_mm_1cam"], "with": res["occlusion_penetration_mm_2cam"]})
    sf = res.get("self_filter")
    if sf:
        out.append({"experiment": "robot self-filter", "measure": "protected points on the instrument, self-filter",
                    "without": sf["false_fixture_points_without"], "with": sf["false_fixture_points_with"]})
        out.append({"experiment": "robot self-filter", "measure": "tool tips fenced in by their own tool, self-filter",
                    "without": sf["tips_fenced_without"], "with": sf["tips_fenced_with"]})
    return out


def dynamic_markdown(rows: list) -> str:
    head = "| chapter 6 | measure | without | with |\n|---|---|---:|---:|\n"
    return head + "".join(f"| {r['experiment']} | {r['measure']} | {r['without']} | {r['with']} |\n" for r in rows)


def write(out_dir, rows: list, probes: list, experiments: dict, meta: Optional[dict] = None,
          dynamic: Optional[dict] = None) -> list:
    """Write the report folder; return the files written. ``experiments``: scene -> list of
    (architecture, trace) in run order; ``probes``: ``probes.run_all()`` results; ``dynamic``:
    ``dynamic_demo.run()`` results (a second table, chapter 6; ``dynamic`` in table.json)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    plotters = {"2.12": ("fig_2_12_push_plane.png", plot_push_plane), "2.13": ("fig_2_13_surfaces.png", plot_surfaces),
                "2.14": ("fig_2_14_ledge.png", plot_ledge), "2.15": ("fig_2_15_translating_plane.png", plot_translating_plane)}
    for p in probes:
        name, fn = plotters[p["figure"]]
        fn(p, out / name)
        files.append(out / name)
    for scene, runs in experiments.items():
        name = f"fig_{FIGURES.get(scene, scene).replace('.', '_')}_{scene}.png"
        plot_experiment(scene, runs, out / name)
        if (out / name).exists():
            files.append(out / name)
    md = ["# pointfence demo\n"]
    if meta:
        md.append("\n".join(f"- {k}: {v}" for k, v in meta.items()) + "\n")
    md.append("\nsafety: max penetration of the forbidden region (fixture rows) or of the true surface by the "
              "proxy sphere (rendering rows); submittance: closest approach while held off; tracking: r.m.s. "
              "|X_r - X_r*| with the master outside the region; pop-through: the slowest rising-plane speed that "
              "pops the proxy through (30 Hz frames); tick p99: compute time of a haptic tick.\n\n")
    md.append(markdown_table(rows))
    doc = {"meta": meta or {}, "rows": rows}
    if dynamic:
        drows = dynamic_rows(dynamic)
        md.append("\nchapter 6, dynamic scenes (simulated 1 kHz ticks, 30 Hz frames, 2 cm fixture; the service row "
                  f"on the demo's clock): each measure without and with the named feature.\n\n{dynamic_markdown(drows)}")
        doc["dynamic"] = {"rows": drows, "results": dynamic}
    md.append("\n" + "\n".join(f"![{f.stem}]({f.name})" for f in files if f.suffix == ".png") + "\n")
    (out / "table.md").write_text("".join(md))
    (out / "table.json").write_text(json.dumps(measures.json_safe(doc), indent=2) + "\n")
    return files + [out / "table.md", out / "table.json"]
