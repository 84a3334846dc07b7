"""The proxy kernel: backends agree with the reference; bad inputs; empty snapshots."""
import zlib

import numpy as np
import pytest

from pointfence.kernels import DepthFrame, InputError, get_backend
from pointfence.kernels.haptics import CONTACT, ENTRENCHED, FREE, HapticParams, HapticScene
from pointfence.kernels.proxy import LANES
from pointfence.kernels.reference.proxy import NumpyProxies

from kernel_cases import params_for, random_rig
from proxy_cases import small_camera, synthetic_scene


def random_walk(rng, start, n_ticks, scale=0.0015, drift=(0.0, 0.0, 0.0)):
    h = np.array(start, np.float64)
    for _ in range(n_ticks):
        h = h + rng.normal(0, scale, h.shape) + drift
        yield h


@pytest.mark.parametrize("mode,ws_capacity,skin,B", [
    ("rendering", 4096, 0.002, 24),
    ("rendering", 4096, 0.002, 8),   # a small batch: PoCL's in-thread device
    ("rendering", 48, 0.002, 24),  # working sets overflow: the kernel scans the hash directly
    ("rendering", 4096, 0.0, 24),  # regather on every move
    ("fixture", 4096, 0.002, 24),
    ("fixture", 64, 0.001, 8),
])
def test_backends_agree_on_random_scenes_and_trajectories(mode, ws_capacity, skin, B):
    """OpenCL and the NumPy reference on the same snapshot: equal within 1e-5 m (in fact to the
    bit: same float32 operations, same summation order), on the worker pool (24 proxies) and on
    the in-thread device (8)."""
    # (a seed of the case itself: Python's hash of a str changes from run to run, and so did the scene)
    rng = np.random.default_rng(zlib.crc32(repr((mode, ws_capacity, skin, B)).encode()))
    cams, frames = random_rig(rng, n_cams=2)
    pp = params_for("mask", adaptive=True, cell=0.02)
    pipe = get_backend("opencl").pipeline(cams, pp)
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    p = HapticParams(mode=mode, skin=skin, max_steps=40)
    surf = snap.points[rng.integers(0, snap.n_points, B), :3].astype(np.float64)
    start = surf + rng.normal(0, 0.01, (B, 3)) + [0, 0, -0.015]  # cameras look along +z
    dev = pipe.proxies(start, p, ws_capacity=ws_capacity)
    assert dev.device_kind == ("in-thread" if B <= 16 and pipe.inline_ctx is not None else "pool")
    ref = NumpyProxies(pipe, start, p, snapshot=snap, ws_capacity=dev.ws_cap, lanes=LANES)
    states = np.zeros(3, int)
    for hips in random_walk(rng, start, 50, drift=(0, 0, 0.0008)):
        dev.step(hips)
        ref.step(hips)
        np.testing.assert_allclose(dev.positions, ref.positions, atol=1e-5, rtol=0)
        np.testing.assert_allclose(dev.normals, ref.normals, atol=1e-5, rtol=0)
        np.testing.assert_array_equal(dev.states, ref.states)
        np.testing.assert_array_equal(dev.steps, ref.steps)
        np.testing.assert_array_equal(dev.converged, ref.converged)
        np.testing.assert_allclose(dev.nearest, ref.nearest, atol=1e-6, rtol=0)
        states += np.bincount(dev.states, minlength=3)
    assert states[CONTACT] + states[ENTRENCHED] > 50 and states[FREE] > 50  # both regimes exercised
    assert np.array_equal(dev.positions, ref.positions)  # bit for bit


@pytest.mark.parametrize("backend", ["numpy", "opencl"])
def test_empty_snapshot_is_free_motion(backend):
    """No frame yet (or nothing valid in it): proxies move freely onto their HIPs, zero force."""
    p = HapticParams()
    hs, src = synthetic_scene("plane", p, [(0.0, 0.0, 0.05), (0.01, 0.02, 0.0)], backend=backend)
    hips = np.array([[0.0, 0.0, 0.052], [0.01, 0.02, 0.015]])
    f = hs.step(hips)  # before any ingest
    np.testing.assert_allclose(hs.proxies, hips, atol=1e-6)
    assert np.all(hs.states == FREE) and np.all(hs.converged) and np.all(np.isinf(hs.nearest))
    assert np.all(f == 0)
    cam = src.camera
    hs.ingest([DepthFrame(cam.name, np.zeros((cam.height, cam.width), np.uint16), 0.0)])  # all invalid
    assert hs.pipeline.host_snapshot().n_points == 0
    hips2 = hips + [0.015, 0, 0]
    hs.step(hips2)
    np.testing.assert_allclose(hs.proxies, hips2, atol=1e-6)
    # far HIP: free motion at delta per step, never past the HIP
    hs.reset([(0.0, 0.0, 0.0), (0.0, 0.0, 0.0)])
    hs.step([[0.2, 0.0, 0.0], [0.0, 0.001, 0.0]])
    assert hs.steps[0] == p.max_steps and not hs.converged[0]
    assert hs.proxies[0, 0] == pytest.approx(p.max_steps * p.step, rel=1e-5)
    np.testing.assert_allclose(hs.proxies[1], [0, 0.001, 0], atol=1e-7)


@pytest.mark.parametrize("backend", ["numpy", "opencl", "warp"])
def test_bad_hips_raise_and_change_nothing(backend):
    if backend == "warp":
        pytest.importorskip("warp", reason="warp-lang is not installed: pip install 'pointfence[warp]'")
    hs, src = synthetic_scene("plane", positions=[(0.0, 0.0, 0.03), (0.0, 0.01, 0.03)], backend=backend)
    hs.ingest([src.read()])
    hs.step([[0, 0, 0.02], [0, 0.01, 0.02]])
    before = hs.proxies.copy()
    rows = ([[np.nan, 0, 0], [0, 0, 0]], [[0, 0, 0], [0, np.inf, 0]], [[0, 0, -np.inf], [0, 0, 0]],
            [[np.inf, 0, 0], [-np.inf, 0, 0]])
    for bad in rows + tuple(np.array(r) for r in rows):      # (an array: the tick's fast check)
        with pytest.raises(InputError, match="not finite"):
            hs.step(bad)
        np.testing.assert_array_equal(hs.proxies, before)
        assert np.all(np.isfinite(hs.forces))
    with pytest.raises(InputError, match="expected one per proxy"):
        hs.step([[0, 0, 0]])
    with pytest.raises(InputError, match="shape"):
        hs.step(np.zeros((2, 2)))
    with pytest.raises(InputError, match="not finite"):
        hs.reset([[np.nan, 0, 0]])


@pytest.mark.parametrize("changes,match", [
    (dict(r1=0.006), "r1 < r2 < r3"),
    (dict(r2=0.011), "r1 < r2 < r3"),
    (dict(r1=0.005, r2=0.005), "r1 < r2 < r3"),
    (dict(step=0.0), "step"),
    (dict(step=-0.001), "step"),
    (dict(step=0.006), "r3 - r1"),
    (dict(r3=float("nan")), "r3"),
    (dict(k=float("inf")), "k"),
    (dict(max_steps=0), "max_steps"),
    (dict(mode="soft"), "mode"),
    (dict(fir_taps=0), "fir_taps"),
    (dict(fir_cutoff_hz=600.0), "Nyquist"),
    (dict(max_force=-1.0), "max_force"),
    (dict(slack=0.005), "slack"),
    (dict(margin=0.0), "margin"),
    (dict(margin=1e-4), "margin"),
])
def test_bad_params_raise_naming_the_value(changes, match):
    with pytest.raises(InputError, match=match):
        HapticParams(**changes)


def test_proxy_state_persists_and_batch_grows():
    """The proxies keep their state between ticks; reset() may grow the batch (buffers grow)."""
    hs, src = synthetic_scene("plane", positions=[(0.0, 0.0, 0.03)])
    hs.ingest([src.read()])
    for z in np.linspace(0.03, -0.01, 60):
        hs.step([[0.0, 0.0, z]])
    z_on = hs.proxies[0, 2]
    assert hs.states[0] != FREE and 0.004 < z_on < 0.006
    hs.step([[0.0, 0.0, -0.01]])
    assert abs(hs.proxies[0, 2] - z_on) < 0.0005  # still on the surface, not restarted
    rng = np.random.default_rng(0)
    many = np.c_[rng.uniform(-0.05, 0.05, (300, 2)), np.full(300, 0.03)]
    hs.reset(many)
    assert len(hs) == 300 and hs.forces.shape == (300, 3)
    for z in np.linspace(0.03, -0.01, 60):
        hs.step(np.c_[many[:, :2], np.full(300, z)])
    assert np.all(hs.proxies[:, 2] > 0.0035)
    assert np.all(np.isfinite(hs.forces)) and np.all(hs.forces[:, 2] > 0)


def test_hip_on_the_proxy_gives_zero_force_not_nan():
    hs, src = synthetic_scene("plane", positions=[(0.0, 0.0, 0.03)], backend="numpy")
    hs.ingest([src.read()])
    for _ in range(3):
        f = hs.step([[0.0, 0.0, 0.03]])
        assert np.all(f == 0)


def test_fixture_mode_ignores_unprotected_points():
    """Rendering uses every point; fixture mode only protected points with their own radius."""
    cam = small_camera()
    from pointfence.service.sources import SyntheticSource

    src = SyntheticSource("plane", cam, noise=False, dropout=0.0)
    fr = src.read()
    mask = np.zeros((cam.height, cam.width), np.uint8)
    mask[:, :40] = 1  # protect only the -x side of the table
    fr = DepthFrame(cam.name, fr.depth, 0.0, mask=mask)
    from proxy_cases import fixture_params

    pp = fixture_params(r_base=0.01, r_max=0.01)
    fx = HapticScene([cam], [(0.05, 0.0, 0.05)], HapticParams(mode="fixture"), pp)
    rd = HapticScene([cam], [(0.05, 0.0, 0.05)], HapticParams(), pp)
    fx.ingest([fr])
    rd.ingest([fr])
    snap = fx.pipeline.host_snapshot()
    side = snap.points[snap.protected != 0, 0].mean() / 0.05  # world x of the protected strip
    fx.reset([(-0.05 * side, 0.0, 0.05)])
    rd.reset([(-0.05 * side, 0.0, 0.05)])
    for z in np.linspace(0.05, -0.01, 80):
        fx.step([[-0.05 * side, 0.0, z]])
        rd.step([[-0.05 * side, 0.0, z]])
    assert fx.states[0] == FREE and fx.proxies[0, 2] == pytest.approx(-0.01, abs=1e-6)  # unprotected: passes
    assert rd.proxies[0, 2] > 0.004  # rendering mode stops on the table
    fx.reset([(0.05 * side, 0.0, 0.05)])
    for z in np.linspace(0.05, -0.01, 80):
        fx.step([[0.05 * side, 0.0, z]])
    assert fx.states[0] != FREE and fx.proxies[0, 2] == pytest.approx(0.01, abs=0.0006)  # 1 cm spheres


@pytest.mark.parametrize("shape,inline", [("cpu", True), ("cpu", False), ("gpu", False)])
def test_results_land_in_the_batch_arrays_when_capacity_exceeds_the_batch(shape, inline):
    """The kernels write each result straight into the batch's arrays, laid out for the batch's
    capacity (kernels/opencl/proxy.py, ``out_block``): after growing to 5 proxies (capacity 6)
    and shrinking to 2, every output still equals the reference's to the bit, on the in-thread
    device, the worker pool and the GPU-shaped kernel (work-groups of 32 on PoCL)."""
    from pointfence.kernels.opencl.kernel_shape import ANY, GroupSizing

    rng = np.random.default_rng(7)
    cams, frames = random_rig(rng, n_cams=2)
    pipe = get_backend("opencl").pipeline(cams, params_for("mask", adaptive=True, cell=0.02))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    p = HapticParams(max_steps=40)
    sizing = GroupSizing(group_sizes=((ANY, 32),)) if shape == "gpu" else None
    surf = snap.points[rng.integers(0, snap.n_points, 5), :3].astype(np.float64)
    start = surf + rng.normal(0, 0.01, (5, 3)) + [0, 0, -0.015]
    dev = pipe.proxies(start[:3], p, inline=inline, kernel_shape=shape, sizing=sizing)
    dev.reset(start)    # capacity 6 (twice 3) for 5 proxies
    assert dev.device_kind == ("in-thread" if inline and pipe.inline_ctx is not None else "pool")
    for rows in (slice(0, 5), slice(3, 5)):
        dev.reset(start[rows])
        ref = NumpyProxies(pipe, start[rows], p, snapshot=snap, lanes=LANES)
        seen = set()
        for hips in random_walk(rng, start[rows], 60, drift=(0, 0, 0.0008)):
            dev.step(hips)
            ref.step(hips)
            for name in ("positions", "normals", "states", "steps", "converged", "nearest"):
                np.testing.assert_array_equal(getattr(dev, name), getattr(ref, name), err_msg=name)
            seen.update(dev.states.tolist())
        assert len(seen) >= 2   # free and in contact: the states and the steps vary
