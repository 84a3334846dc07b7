"""Dynamic scenarios of dissertation chapter 6 in simulated time (no wall clock anywhere):
pop-through against a translating plane (fig. 2.15, 6.2), shared by ``pointfence bench dynamic``
and the tests.

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
