"""The clipping rule's guarantees (kernels/proxy.py, step 3), checked by brute force in float64
over the whole snapshot at every tick, for every backend and both modes:

* static scene: no clearance |X_p - P_i| - rho_i ever drops below -slack (a proxy placed too
  deep never gets deeper);
* a buried proxy (a new frame moved the surface into it) gets out within a few ticks, and its
  deepest penetration never grows on the way.
"""
import numpy as np
import pytest

from pointfence.kernels import DepthFrame, PipelineParams, Selection, get_backend
from pointfence.kernels.haptics import ENTRENCHED, FREE, HapticParams, HapticScene, haptic_pipeline_params
from pointfence.kernels.reference.proxy import NumpyProxies
from pointfence.service.sources import SyntheticSource

from kernel_cases import device_backends, params_for, random_rig
from proxy_cases import WS, fixture_params, small_camera

BACKENDS = ["numpy"] + device_backends()
#: what float32 rounding of a position near 1 m may add on top of the bound (m)
ROUND = 2e-7


def clearances(snap, X, mode, r1):
    """min_i |X_b - P_i| - rho_i per proxy (float64, every point of the snapshot)."""
    pts = snap.points.astype(np.float64)
    if mode == "fixture":
        pts = pts[snap.protected != 0]
        rho = pts[:, 3]
    else:
        rho = np.full(len(pts), r1)
    d = np.sqrt(((X.astype(np.float64)[:, None, :] - pts[None, :, :3]) ** 2).sum(axis=2))
    return (d - rho[None]).min(axis=1)


def make_proxies(backend, cams, frames, start, p):
    pipe = get_backend("warp" if backend == "warp" else "opencl").pipeline(cams, params_for("mask", adaptive=True, cell=0.02))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    prox = NumpyProxies(pipe, start, p, snapshot=snap) if backend == "numpy" else pipe.proxies(start, p)
    return pipe, snap, prox


@pytest.mark.parametrize("mode", ["rendering", "fixture"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_static_scene_penetration_bound(backend, mode):
    """Random rigs (adaptive fixture radii), HIPs on random walks drifting into the surfaces.
    At every tick, for every proxy: min clearance >= min(-slack, its min clearance a tick
    earlier) up to rounding; proxies that start clear stay >= -slack throughout."""
    worst = np.inf
    counts = np.zeros(3, int)
    for seed in (5, 23, 7, 11, 2):
        rng = np.random.default_rng(seed)
        cams, frames = random_rig(rng, n_cams=2)
        p = HapticParams(mode=mode, max_steps=40)
        B = 16
        probe = get_backend("opencl").pipeline(cams, params_for("mask", adaptive=True, cell=0.02))
        probe.ingest(frames)
        pts = probe.host_snapshot().points
        surf = pts[rng.integers(0, len(pts), B), :3].astype(np.float64)
        start = surf + rng.normal(0, 0.01, (B, 3)) + [0, 0, -0.015]  # cameras look along +z
        pipe, snap, prox = make_proxies(backend, cams, frames, start, p)
        prev = clearances(snap, prox.positions, mode, p.r1)
        clear = prev >= -p.slack
        h = start.copy()
        for tick in range(40):
            h = h + rng.normal(0, 0.0015, h.shape) + [0, 0, 0.0008]
            prox.step(h)
            now = clearances(snap, prox.positions, mode, p.r1)
            bound = np.minimum(-p.slack, prev) - ROUND
            bad = now < bound
            assert not bad.any(), (f"seed {seed} tick {tick}: proxy {int(np.argmax(bad))} clearance "
                                   f"{now[bad].min() * 1e3:.5f} mm < {bound[bad].min() * 1e3:.5f} mm")
            worst = min(worst, now[clear].min())
            counts += np.bincount(prox.states, minlength=3)
            prev = now
    assert worst >= -p.slack - ROUND
    assert counts[ENTRENCHED] > 100 and counts[FREE] > 100  # both regimes exercised
    print(f"\n{backend} {mode}: min clearance {worst * 1e3:.5f} mm (slack {p.slack * 1e3} mm)")


def plane_frame(cam, z):
    """A noise-free frame of a horizontal plane at height ``z`` (m), every pixel protected."""
    src = SyntheticSource("plane", cam, noise=False, dropout=0.0, position=(0.0, 0.0, z))
    fr = src.read()
    return DepthFrame(cam.name, fr.depth, 0.0, mask=np.ones((cam.height, cam.width), np.uint8))


def groove_frame(cam, z):
    """A 120-degree V groove with its edge at height ``z`` (m), noise-free, every pixel protected."""
    src = SyntheticSource("corner", cam, noise=False, dropout=0.0, concave=True, angle_deg=120.0, position=(0.0, 0.0, z))
    fr = src.read()
    return DepthFrame(cam.name, fr.depth, 0.0, mask=np.ones((cam.height, cam.width), np.uint8))


@pytest.mark.parametrize("mode", ["rendering", "fixture"])
@pytest.mark.parametrize("scene,rise", [("plane", 0.003), ("groove", 0.002), ("plane", 0.0045)])
@pytest.mark.parametrize("backend", BACKENDS)
def test_buried_proxy_gets_out(backend, scene, rise, mode):
    """A proxy rests on the surface with its HIP 5 mm behind it; a new frame moves the surface
    ``rise`` towards it (the proxy is then buried about ``rise`` deep). Within 2 ticks every
    clearance is back >= -slack, on the near side of the surface, and the deepest penetration
    never grew on the way."""
    p = HapticParams(mode=mode)
    cam = small_camera()
    make = plane_frame if scene == "plane" else groove_frame
    pp = fixture_params(r_base=p.r1, r_max=p.r1, selection=Selection()) if mode == "fixture" else \
        haptic_pipeline_params(p, PipelineParams(workspace=WS))
    x0, y0 = 0.004, -0.003
    hs = HapticScene([cam], [(x0, y0, 0.04)], p, pp, backend=backend)
    hs.ingest([make(cam, 0.0)])
    hip = np.array([[x0, y0, -0.005]])
    for z in np.linspace(0.04, -0.005, 60):
        hs.step([[x0, y0, z]])
    for _ in range(20):
        hs.step(hip)
    snap = hs.pipeline.host_snapshot()
    rest = clearances(snap, hs.proxies, mode, p.r1)[0]
    # (pressed into a groove the proxy wanders within a fraction of a millimetre: kernels/params_haptics.py)
    assert -p.slack - ROUND <= rest < 0.0005
    hs.ingest([make(cam, rise)])
    snap = hs.pipeline.host_snapshot()
    prev = clearances(snap, hs.proxies, mode, p.r1)[0]
    assert prev < -rise + 0.001  # really buried
    out_at = None
    for tick in range(10):
        hs.step(hip)
        now = clearances(snap, hs.proxies, mode, p.r1)[0]
        assert now >= min(-p.slack, prev) - ROUND, f"tick {tick}: deepest penetration grew to {-now * 1e3:.4f} mm"
        if now >= -p.slack - ROUND and out_at is None:
            out_at = tick
        if out_at is not None:
            assert now >= -p.slack - ROUND  # and stays out
        prev = now
        assert np.all(np.isfinite(hs.forces))
    assert out_at is not None and out_at <= 1, f"still buried after 10 ticks (clearance {prev * 1e3:.3f} mm)"
    x = hs.proxies[0].astype(np.float64)
    pts = snap.points[:, :3].astype(np.float64)
    below = np.linalg.norm(pts[:, :2] - x[:2], axis=1) < 0.003
    assert x[2] > pts[below, 2].max() + p.r1 / 2  # pushed back out on the near side, not through
    assert hs.forces[0, 2] > 0
