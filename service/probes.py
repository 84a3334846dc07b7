"""The dissertation's chapter-2 surface probes (figs. 2.12-2.15) in haptic rendering mode, for
`pointfence demo`: a proxy (``kernels.haptics.HapticScene``) on synthetic scenes seen by a
160x120 Kinect-like camera 0.3 m above the table (depth noise, holes), ticked at 1 kHz on the
simulated clock (deterministic; the compute time of each tick is measured but decides nothing).

* ``push_plane`` (fig. 2.12): the HIP goes 2 cm behind a plane at 0.1 m/s, holds, comes back:
  the proxy stays on the surface and the force rises with the penetration.
* ``surfaces`` (fig. 2.13): the HIP slides 6 mm under a concave bowl, a convex bump, a sharp
  ridge and a V groove: the proxy follows each surface.
* ``ledge`` (fig. 2.14): sliding off a 5 mm ledge, the proxy drops to the lower level.
* ``translating_plane`` (fig. 2.15): a plane rising at increasing speeds against a fixed HIP
  (frames at 30 Hz): the first speed at which the proxy pops through (dissertation: 0.08 m/s).

Every probe returns its traces (for the report's plots) and its measures against the scene's
exact geometry: the proxy's largest penetration of the true surface, max(0, r1 - d), where d
is the proxy centre's signed distance to the surface and r1 the proxy radius.
"""
from __future__ import annotations

import time
from typing import Optional

import numpy as np

from pointfence.kernels import DepthFrame, PipelineParams, Workspace
from pointfence.kernels.haptics import HapticParams, HapticScene, haptic_pipeline_params

from .sources import SyntheticSource, default_camera

WS = Workspace((-0.15, -0.15, -0.12), (0.15, 0.15, 0.2))
#: surfaces of fig. 2.13: (label, scene, options, end of the slide in x)
SURFACES = (("concave bowl", "bowl", {}, 0.04), ("convex bump", "bump", {}, 0.025),
            ("ridge", "corner", {"concave": False}, 0.04),
            ("V groove", "corner", {"concave": True, "angle_deg": 120.0, "position": (0.0, 0.0, 0.0)}, 0.04))
#: speeds of fig. 2.15, m/s (ascending; the probe stops at the first pop-through)
PLANE_SPEEDS = (0.03, 0.06, 0.09, 0.12, 0.15, 0.18, 0.24, 0.3)
DOWN = np.array([[0.0, 0.0, -1.0]])


class _Probe:
    """A HapticScene on one synthetic scene; ``step`` times each tick (wall clock, us)."""

    def __init__(self, scene: str, params: HapticParams, start, backend=None, device=None, **options):
        cam = default_camera("cam0", eye=(0.0, 0.0, 0.3), width=160, height=120)
        options.setdefault("quantize", False)   # 160x120: disparity steps 4x coarser than a 640x480 sensor's
        self.src = SyntheticSource(scene, cam, **options)
        self.scene = self.src.scene
        pp = haptic_pipeline_params(params, PipelineParams(workspace=WS))
        self.hs = HapticScene([cam], np.asarray([start], float), params, pp, backend=backend, device=device)
        self.tick_us: list = []

    def ingest(self, frame=None) -> None:
        self.hs.ingest([frame if frame is not None else self.src.read()])

    def step(self, hip) -> np.ndarray:
        w0 = time.perf_counter()
        f = self.hs.step(np.asarray(hip, float).reshape(1, 3))
        self.tick_us.append((time.perf_counter() - w0) * 1e6)
        return f[0].copy()

    def surface_z(self, x, y=0.0, t=0.0) -> float:
        return float(0.2 - self.scene.cast(np.array([[x, y, 0.2]]), DOWN, t)[0])

    def close(self) -> None:
        self.src.close()


def _penetration(scene, proxies, r1, t=0.0) -> float:
    d = scene.distance(np.asarray(proxies, float), t)
    return float(max(0.0, r1 - float(np.min(d))))


def push_plane(backend=None, device=None) -> dict:
    p = HapticParams(max_force=100.0)   # no saturation: the spring's rise is the figure
    pr = _Probe("plane", p, (0.01, 0.0, 0.03), backend, device)
    pr.ingest()
    down = np.linspace(0.03, -0.02, 500)   # 0.1 m/s
    zs = np.concatenate([down, np.full(100, -0.02), down[::-1]])
    px, fz = [], []
    for z in zs:
        f = pr.step((0.01, 0.0, z))
        px.append(pr.hs.proxies[0].copy())
        fz.append(f[2])
    px = np.array(px)
    out = {"name": "push into a plane", "figure": "2.12", "t": np.arange(len(zs)) * 1e-3, "hip_z": zs,
           "proxy_z": px[:, 2], "force_z": np.array(fz), "r1": p.r1, "k": p.k,
           "penetration_m": _penetration(pr.scene, px, p.r1),
           "force_at_2cm_N": float(np.mean(fz[540:600])), "tick_us": pr.tick_us}
    pr.close()
    return out


def _slide(pr: _Probe, xs, depth: float):
    hips, px = [], []
    for x in xs:
        hip = np.array([x, 0.0, pr.surface_z(x) - depth])
        pr.step(hip)
        hips.append(hip)
        px.append(pr.hs.proxies[0].copy())
    return np.array(hips), np.array(px)


def surfaces(backend=None, device=None) -> dict:
    p = HapticParams()
    runs, pen, us = [], 0.0, []
    for label, scene, options, end in SURFACES:
        pr = _Probe(scene, p, (-0.04, 0.0, 0.15), backend, device, **options)
        pr.ingest()
        pr.hs.reset([(-0.04, 0.0, 0.15)])
        xs = np.concatenate([np.full(40, -0.04), np.linspace(-0.04, end, 400)])
        hips, px = _slide(pr, xs, 0.006)
        gx = np.linspace(-0.05, end + 0.01, 300)
        prof = np.array([pr.surface_z(x) for x in gx])
        d = pr.scene.distance(px[60:])
        runs.append({"label": label, "hip": hips, "proxy": px, "profile_x": gx, "profile_z": prof, "settle": 40,
                     "penetration_m": _penetration(pr.scene, px, p.r1),
                     "max_gap_m": float(max(0.0, d.max() - p.r1))})
        pen = max(pen, runs[-1]["penetration_m"])
        us += pr.tick_us
        pr.close()
    return {"name": "concave / convex / corner", "figure": "2.13", "runs": runs, "r1": p.r1,
            "penetration_m": pen, "tick_us": us}


def ledge(backend=None, device=None) -> dict:
    p = HapticParams()
    pr = _Probe("ledge", p, (0.03, 0.0, 0.04), backend, device, step=0.005)
    pr.ingest()
    xs = np.concatenate([np.full(40, 0.03), np.linspace(0.03, -0.03, 240)])
    hips, px = _slide(pr, xs, 0.004)
    gx = np.linspace(-0.035, 0.035, 300)
    out = {"name": "5 mm ledge", "figure": "2.14", "hip": hips, "proxy": px, "profile_x": gx, "settle": 40,
           "profile_z": np.array([pr.surface_z(x) for x in gx]), "r1": p.r1,
           "upper_z": float(np.median(px[40:80, 2])), "lower_z": float(np.median(px[-40:, 2])),
           "penetration_m": _penetration(pr.scene, px, p.r1), "tick_us": pr.tick_us}
    pr.close()
    return out


def translating_plane(speeds=PLANE_SPEEDS, ticks: int = 300, backend=None, device=None) -> dict:
    """Rising plane against a HIP 1 cm under its start: the first speed that pops the proxy through."""
    p = HapticParams()
    runs, popped_at, us = [], None, []
    for speed in speeds:
        pr = _Probe("translating_plane", p, (0.0, 0.0, 0.03), backend, device, speed=speed, travel=0.0)
        src, scene = pr.src, pr.scene
        hip = (0.0, 0.0, -0.01)
        frame, popped, t_pop = None, False, None
        ts, ds = [], []
        for tick in range(ticks):
            t = tick / 1000.0
            seq = int(t * src.rate_hz)
            if frame != seq:
                frame = seq
                depth, _, _ = src.render(src.time_of(seq), np.random.default_rng(seq))
                pr.ingest(DepthFrame(src.camera.name, depth, src.time_of(seq), seq))
                if tick == 0:                      # settle on the plane first
                    for _ in range(40):
                        pr.step(hip)
            pr.step(hip)
            d = float(scene.distance(pr.hs.proxies, t)[0])
            ts.append(t)
            ds.append(d)
            if d < 0:
                popped, t_pop = True, t
                break
        runs.append({"speed": speed, "popped": popped, "t_pop": t_pop, "t": np.array(ts), "distance": np.array(ds)})
        us += pr.tick_us
        pr.close()
        if popped:
            popped_at = speed
            break
    return {"name": "translating plane", "figure": "2.15", "runs": runs, "r1": p.r1, "popthrough_speed": popped_at,
            "max_speed_held": max((r["speed"] for r in runs if not r["popped"]), default=None),
            "penetration_m": None, "tick_us": us}


def run_all(backend: Optional[str] = None, device: Optional[str] = None) -> list:
    """Every probe, in figure order."""
    return [push_plane(backend, device), surfaces(backend, device), ledge(backend, device),
            translating_plane(backend=backend, device=device)]
