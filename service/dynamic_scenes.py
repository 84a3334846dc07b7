"""Dynamic scenarios of dissertation chapter 6 in simulated time (no wall clock anywhere):
pop-through against a translating plane (fig. 2.15, 6.2), the robot self-filter and occlusion
(6.4) and the adaptive radius study (6.3). The product runs them (``pointfence demo``:
``service/dynamic_demo.py``); ``pointfence bench dynamic`` and the tests measure them (bench
imports the product, never the other way round).

Time: haptic ticks at 1 kHz at t = k / 1000 s; frame ``seq`` is captured at seq / rate and
reaches the pipeline ``latency`` s later, stamped on arrival (as a Kinect driver does), so the
pipeline's motion model is told ``latency``. Safety is measured against the exact scene at the
tick's time: the true signed distance d of the proxy to the surface; the proxy has popped
through when d < 0, and its penetration of the forbidden region is max(0, r_f - d).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pointfence.kernels import DepthFrame, PipelineParams, RadiusModel, Workspace
from pointfence.kernels.haptics import HapticParams, HapticScene, haptic_pipeline_params
from pointfence.kernels.motion import MotionModel
from pointfence.service.sources import SyntheticSource, default_camera

RATE_HZ = 30.0
TICK_HZ = 1000.0
#: speeds tried by ``popthrough_speed`` (m/s), ascending
SPEEDS = (0.05, 0.08, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 1.0, 1.2, 1.5)


@dataclass
class PlaneRun:
    """Outcome of one translating-plane run."""

    speed: float
    popped: bool
    max_penetration: float  # m, of the forbidden region (r_f - d), or of the proxy (r1 - d) in rendering mode
    min_distance: float  # m, smallest true centre-to-surface distance
    ticks: int


def plane_scene(speed: float, predict: bool, *, mode: str = "fixture", r_f: float = 0.02, latency: float = 0.0,
                backend: str = "opencl", device: str | None = None, width: int = 160, seed: int = 0):
    """(HapticScene, SyntheticSource, radius) for a plane starting at z = -0.1 m moving up at
    ``speed`` under a camera 0.5 m above the table (30 Hz, Kinect noise and holes)."""
    cam = default_camera("cam0", eye=(0.0, 0.0, 0.5), width=width, height=width * 3 // 4)
    src = SyntheticSource("translating_plane", cam, speed=speed, travel=0.0, position=(0.0, 0.0, -0.1),
                          quantize=False, rate_hz=RATE_HZ, seed=seed)
    p = HapticParams(mode=mode)
    motion = MotionModel(enabled=bool(predict), latency=float(latency))
    pp = PipelineParams(workspace=Workspace((-0.2, -0.2, -0.15), (0.2, 0.2, 0.35)),
                        radius=RadiusModel(r_base=r_f, r_max=r_f), motion=motion)
    pp = haptic_pipeline_params(p, pp)
    radius = r_f if mode == "fixture" else p.r1
    hs = HapticScene([cam], [[0.0, 0.0, -0.1 + radius + p.band / 2]], p, pp, backend=backend, device=device)
    return hs, src, radius


def run_plane(speed: float, predict: bool, *, mode: str = "fixture", r_f: float = 0.02, latency: float = 0.0,
              duration: float | None = None, backend: str = "opencl", device: str | None = None,
              seed: int = 0) -> PlaneRun:
    """Hold a proxy against the rising plane with its HIP fixed 4 cm below the start plane."""
    hs, src, radius = plane_scene(speed, predict, mode=mode, r_f=r_f, latency=latency, backend=backend,
                                  device=device, seed=seed)
    scene = src.scene
    if duration is None:  # at most 25 cm of travel, at least 8 frames
        duration = max(8 / RATE_HZ, min(0.4, 0.25 / max(speed, 1e-9)))
    hip = np.array([[0.0, 0.0, -0.14]])
    n_ticks = int(round(duration * TICK_HZ))

    def ingest(seq):
        depth, _, _ = src.render(src.time_of(seq), np.random.default_rng([seed, seq]))
        hs.ingest([DepthFrame(src.camera.name, depth, src.time_of(seq) + latency, seq)])

    # The camera watches the moving plane for one frame before the proxy engages (as it would
    # before a tool reaches a moving organ): the proxy starts just outside the true fixture
    # when frame 1 arrives and settles there for 40 ticks.
    ingest(0)
    seq = 1
    ingest(seq)
    t0 = src.time_of(1) + latency
    hs.reset([[0.0, 0.0, float(scene.anchor(t0)[2]) + radius + hs.params.band / 2]])
    for _ in range(40):
        hs.step(hip, now=t0)
    worst, dmin, popped = 0.0, np.inf, False
    for k in range(n_ticks):
        t = t0 + k / TICK_HZ
        avail = int(np.floor((t - latency) * RATE_HZ + 1e-9))
        if avail != seq:
            seq = avail
            ingest(seq)
        hs.step(hip, now=t)
        d = float(scene.distance(hs.proxies, t)[0])
        dmin = min(dmin, d)
        worst = max(worst, radius - d)
        if d < 0:
            popped = True
            break
    return PlaneRun(speed, popped, max(worst, 0.0), dmin, k + 1)


def popthrough_speed(predict: bool, *, speeds=SPEEDS, **options) -> dict:
    """Sweep ``speeds`` upwards until the proxy pops through. Returns {"popthrough_mps": the
    first speed that popped (None: none did), "held_mps": the fastest speed held before it,
    "runs": [(speed, popped, max penetration mm)]}."""
    runs = []
    popped_at = held = None
    for v in speeds:
        r = run_plane(v, predict, **options)
        runs.append((v, r.popped, round(r.max_penetration * 1e3, 2)))
        if r.popped:
            popped_at = v
            break
        held = v
    return {"popthrough_mps": popped_at, "held_mps": held, "runs": runs}


# --- robot self-filter and occlusion (6.4) ---------------------------------------------------------

from pointfence.kernels import Selection  # noqa: E402
from pointfence.kernels.selffilter import SelfFilter  # noqa: E402
from pointfence.service.sources.scenes import make_scene  # noqa: E402
from pointfence.service.sources.toolscene import ToolInScene  # noqa: E402

#: a fan-retractor-like head at the tip: a 4 cm blade, 2.4 cm thick, across world x (tip frame)
BLADE = (((-0.02, 0.0, 0.0), (0.02, 0.0, 0.0), 0.012),)
TABLE_WS = Workspace((-0.15, -0.15, -0.05), (0.15, 0.15, 0.25))


def _render(src, seq, t, seed, cam_index=0):
    depth, color, mask = src.render(t, np.random.default_rng([seed, seq, cam_index]))
    return DepthFrame(src.camera.name, depth, t, seq, color=color, mask=mask)


def self_filter_run(filtered: bool, *, backend: str = "opencl", device: str | None = None, heights=(0.03, 0.05, 0.08),
                    margin: float = 0.003, seed: int = 0) -> dict:
    """A simulated Raven II instrument (shaft down through an RCM 15 cm above the table) over a
    table whose whole work area is protected (selection box), one camera at 0.6 m looking down
    at 25 degrees. Per tip height: the protected points on the tool (within 2 mm of its surface:
    false fixtures), the table points kept, and whether a fixture proxy at the tip is buried in
    the tool's own fixtures. With ``filtered`` the self-filter drops the tool's pixels first."""
    from pointfence.service.robot import make_robot
    from pointfence.service.robot.raven2 import Raven2
    from pointfence.service.robot.tool import ToolModel, tool_capsules

    cam = default_camera("cam0", eye=(0.25, 0.0, 0.55), width=160, height=120)
    table = make_scene("plane", disc_radius=0.1)
    scene = ToolInScene(base=table)
    src = SyntheticSource(scene, cam, quantize=False)
    p = HapticParams(mode="fixture")
    pp = haptic_pipeline_params(p, PipelineParams(
        workspace=TABLE_WS, selection=Selection("box", box_min=(-0.1, -0.1, -0.05), box_max=(0.1, 0.1, 0.25)),
        radius=RadiusModel(r_base=0.02, r_max=0.02)))
    filt = SelfFilter([cam], margin=margin)
    out = {"tool_points": 0, "false_fixture_points": 0, "table_points": 0, "buried_tips": 0, "removed_pixels": 0}
    for k, h in enumerate(heights):
        rcm = (0.0, 0.0, h + 0.083)  # the home pose puts the tip 83 mm below the RCM
        robot = make_robot("raven2", T_world_base=Raven2.mount_tool_down(rcm))
        caps = tool_capsules(robot, model=ToolModel())
        scene.capsules = caps
        tip = robot.measured_cp()[:3, 3]
        frame = _render(src, k, 0.0, seed)
        frames = filt.apply([frame], caps) if filtered else [frame]
        out["removed_pixels"] += filt.removed if filtered else 0
        hs = HapticScene([cam], [tip], p, pp, backend=backend, device=device)
        hs.ingest(frames)
        snap = hs.pipeline.host_snapshot()
        pts = snap.points[:, :3].astype(np.float64)
        on_tool = scene.tool_distance(pts) < 0.002
        prot = snap.protected != 0
        out["false_fixture_points"] += int(np.count_nonzero(on_tool & prot))
        out["tool_points"] += int(np.count_nonzero(on_tool))
        out["table_points"] += int(np.count_nonzero(np.abs(table.distance(pts)) < 0.005))
        hs.step([tip])  # HIP on the tip: the proxy stays if nothing fences it
        out["buried_tips"] += int(hs.nearest[0] < 0 or np.linalg.norm(hs.proxies[0] - tip) > 1e-4)
    return out


def self_filter_ratio(**options) -> dict:
    """false-fixture points with the filter / without it (0: the tool never fences itself), the
    share of table points the filter removed, tips buried in their own fixtures."""
    off = self_filter_run(False, **options)
    on = self_filter_run(True, **options)
    return {
        "self_filter_false_fixture_ratio": on["false_fixture_points"] / max(off["false_fixture_points"], 1),
        "false_fixture_points_without": off["false_fixture_points"],
        "false_fixture_points_with": on["false_fixture_points"],
        "table_points_lost_fraction": 1.0 - on["table_points"] / max(off["table_points"], 1),
        "tips_fenced_without": off["buried_tips"],
        "tips_fenced_with": on["buried_tips"],
    }


@dataclass
class OcclusionRun:
    cameras: int
    max_penetration: float  # m, of the 2 cm forbidden region by the robot tip (architecture III)
    final_height: float  # m, tip above the table at the end
    min_height: float


def occlusion_run(n_cameras: int, *, backend: str = "opencl", device: str | None = None, r_f: float = 0.02,
                  seed: int = 0, descend_speed: float = 0.05, max_robot_speed: float = 0.05,
                  duration: float = 2.0) -> OcclusionRun:
    """Architecture III (HIP = master, robot command = proxy, rate-limited to
    ``max_robot_speed``) pushing a tool with a wide head (``BLADE``) straight down onto a
    protected disc on the table (2 cm fixture). Camera 1 looks straight down the shaft: the head
    hides the disc under it (and the self-filter removes the head's own pixels, leaving a hole
    where the tool goes). Camera 2 (with ``n_cameras`` = 2) looks from the side, low, and sees
    under the head. 30 Hz frames, 1 kHz ticks, the tool rendered at its pose at each frame."""
    from pointfence.kernels.selffilter import Capsule
    from pointfence.service.robot.tool import ToolModel

    cams = [default_camera("top", eye=(0.0, 0.0, 0.5), width=160, height=120)]
    if n_cameras >= 2:
        cams.append(default_camera("side", eye=(0.0, 0.4, 0.12), width=160, height=120))
    table = make_scene("plane", disc_radius=0.06)
    scene = ToolInScene(base=table)
    srcs = [SyntheticSource(scene, c, quantize=False, mask=True) for c in cams]
    p = HapticParams(mode="fixture")
    pp = haptic_pipeline_params(p, PipelineParams(workspace=TABLE_WS, selection=Selection("mask"),
                                                  radius=RadiusModel(r_base=r_f, r_max=r_f)))
    filt = SelfFilter(cams, margin=0.003)
    model = ToolModel(parts=BLADE)

    def capsules(tip):
        caps = [Capsule(tuple(tip), tuple(tip + [0.0, 0.0, model.shaft_length]), model.shaft_radius)]
        for a, b, r in model.parts:
            caps.append(Capsule(tuple(tip + np.asarray(a)), tuple(tip + np.asarray(b)), r))
        return caps

    start = np.array([0.0, 0.0, 0.06])
    hs = HapticScene(cams, [start], p, pp, backend=backend, device=device)
    xr = start.copy()
    hip = start.copy()
    seq = -1
    worst, hmin = 0.0, np.inf
    step = max_robot_speed / TICK_HZ
    for k in range(int(duration * TICK_HZ)):
        t = k / TICK_HZ
        s = int(np.floor(t * RATE_HZ + 1e-9))
        if s != seq:  # a frame of every camera, the tool where the robot is now
            seq = s
            caps = capsules(xr)
            scene.capsules = caps
            frames = [_render(src, seq, t, seed, i) for i, src in enumerate(srcs)]
            hs.ingest(filt.apply(frames, caps))
        hip[2] = max(start[2] - descend_speed * t, -0.02)  # the master pushes 2 cm into the table
        hs.step([hip])
        goal = hs.proxies[0].astype(np.float64)
        d = goal - xr
        n = np.linalg.norm(d)
        xr = goal if n <= step else xr + d * (step / n)
        h = float(table.distance(xr[None])[0])
        hmin = min(hmin, h)
        worst = max(worst, r_f - h)
    return OcclusionRun(n_cameras, max(worst, 0.0), h, hmin)


# --- adaptive radius study (6.3) -------------------------------------------------------------------

def radius_run(distance: float, noise_scale: float, adaptive: bool, *, bias_sigma: float = 0.0, r_base: float = 0.02,
               k_sigma: float = 3.0, backend: str = "opencl", device: str | None = None, width: int = 320,
               duration: float = 0.5, seed: int = 0) -> dict:
    """A fixture proxy pressed into a protected plane (HIP 3 cm inside it) seen from ``distance``
    m straight above, with the Kinect noise model scaled by ``noise_scale``; fresh noisy frames at
    30 Hz. ``bias_sigma``: a systematic error (registration, depth bias) that shows the plane
    that many sigma_z too far from the camera (the mean mu of 6.3's footnote). The forbidden
    region is the nominal r_base around the true plane. Returns the safety
    measure (max penetration of that region, m), the submittance gap (median distance outside it
    while pressed, m) and the depth noise sigma_z at the plane (m)."""
    from pointfence.kernels.camera import NoiseModel

    base = default_camera("cam0", eye=(0.0, 0.0, distance), width=width, height=width * 3 // 4)
    noise = NoiseModel(base.noise.a * noise_scale, base.noise.b * noise_scale)
    cam = type(base)(**{**base.__dict__, "noise": noise})
    bias = bias_sigma * float(noise.sigma_z(distance))
    src = SyntheticSource("plane", cam, quantize=False, seed=seed, position=(0.0, 0.0, -bias))
    p = HapticParams(mode="fixture")
    pp = haptic_pipeline_params(p, PipelineParams(
        workspace=Workspace((-0.15, -0.15, -0.15), (0.15, 0.15, 0.2)),
        radius=RadiusModel(r_base=r_base, adaptive=adaptive, k_sigma=k_sigma, r_max=r_base + 0.04)))
    hs = HapticScene([cam], [[0.0, 0.0, r_base + 0.05]], p, pp, backend=backend, device=device)
    hip = np.array([[0.0, 0.0, -0.03]])
    pen, gaps = 0.0, []
    seq = -1
    n = int(duration * TICK_HZ)
    for k in range(n):
        s = int(k / TICK_HZ * RATE_HZ)
        if s != seq:
            seq = s
            depth, _, _ = src.render(src.time_of(seq), np.random.default_rng([seed, seq]))
            hs.ingest([DepthFrame("cam0", depth, src.time_of(seq), seq)])
        # the HIP comes down from above over the first 0.1 s, then presses
        h = hip.copy()
        h[0, 2] = max(r_base + 0.05 - 0.8 * k / TICK_HZ, -0.03)
        hs.step(h)
        z = float(hs.proxies[0, 2])  # the plane is z = 0: the true distance
        pen = max(pen, r_base - z)
        if k >= n // 2:
            gaps.append(z - r_base)
    return {"distance_m": distance, "noise_scale": noise_scale, "bias_sigma": bias_sigma, "adaptive": adaptive,
            "sigma_z_mm": round(float(noise.sigma_z(distance)) * 1e3, 3),
            "safety_penetration_mm": round(max(pen, 0.0) * 1e3, 3),
            "submittance_gap_mm": round(float(np.median(gaps)) * 1e3, 3)}


def radius_study(distances=(0.5, 1.0, 1.5, 2.0), noise_scales=(1.0, 2.0, 4.0), biases=(0.0, 2.0), **options) -> list:
    """Fixed vs adaptive r_f over camera distances, noise levels and systematic errors (rows of
    ``radius_run``)."""
    rows = []
    for b in biases:
        for z in distances:
            for m in noise_scales:
                for adaptive in (False, True):
                    rows.append(radius_run(z, m, adaptive, bias_sigma=b, **options))
    return rows


def write_radius_study(rows: list, out_dir) -> dict:
    """study.md (table), study.csv and study.png (safety and submittance vs sigma_z) in out_dir."""
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    keys = list(rows[0])
    (out / "radius_study.csv").write_text(
        "\n".join([",".join(keys)] + [",".join(str(r[k]) for k in keys) for r in rows]) + "\n")
    lines = ["| bias (sigma) | Z (m) | noise x | sigma_z (mm) | fixed: penetration (mm) | fixed: gap (mm) | "
             "adaptive: penetration (mm) | adaptive: gap (mm) |", "|---|---|---|---|---|---|---|---|"]
    pairs = {}
    for r in rows:
        pairs.setdefault((r["bias_sigma"], r["distance_m"], r["noise_scale"]), {})[r["adaptive"]] = r
    for (b, z, m), d in pairs.items():
        f, a = d[False], d[True]
        lines.append(f"| {b:g} | {z:g} | {m:g} | {f['sigma_z_mm']:.2f} | {f['safety_penetration_mm']:.2f} | "
                     f"{f['submittance_gap_mm']:.2f} | {a['safety_penetration_mm']:.2f} | {a['submittance_gap_mm']:.2f} |")
    (out / "radius_study.md").write_text(
        "Fixed vs adaptive fixture radius (dissertation 6.3): r_base = 2 cm, adaptive r_f = r_base + 3 sigma, "
        "a fixture proxy pressed 3 cm into a protected plane seen from Z; penetration of the nominal 2 cm "
        "region (safety) and median gap outside it while pressed (submittance). bias: a systematic error "
        "showing the plane that many sigma_z too far from the camera.\n\n" + "\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.5))
    for b in sorted({r["bias_sigma"] for r in rows}):
        for adaptive, style in ((False, "o-"), (True, "s--")):
            rs = sorted((r for r in rows if r["adaptive"] == adaptive and r["bias_sigma"] == b),
                        key=lambda r: r["sigma_z_mm"])
            s = [r["sigma_z_mm"] for r in rs]
            label = ("adaptive r_f = r_base + 3 sigma" if adaptive else "fixed r_f = 2 cm") + f", bias {b:g} sigma"
            ax[0].plot(s, [r["safety_penetration_mm"] for r in rs], style, label=label)
            ax[1].plot(s, [r["submittance_gap_mm"] for r in rs], style, label=label)
    ax[0].set(xlabel="depth noise sigma_z (mm)", ylabel="max penetration of the 2 cm region (mm)", title="safety")
    ax[1].set(xlabel="depth noise sigma_z (mm)", ylabel="median gap outside it (mm)", title="submittance")
    for a in ax:
        a.grid(True, alpha=0.3)
        a.set_xscale("log")
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "radius_study.png", dpi=100)
    plt.close(fig)
    return {"table": str(out / "radius_study.md"), "csv": str(out / "radius_study.csv"), "plot": str(out / "radius_study.png")}
