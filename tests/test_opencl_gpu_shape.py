"""The GPU-shaped OpenCL proxy kernel (a work-group a proxy, working set in local memory) against
the NumPy reference, bit for bit, on every path; and how the kernel shape is chosen.

On PoCL (a CPU device) the GPU shape is forced: PoCL runs work-groups with barriers and local
memory, slowly, and compiles this kernel once per work-group size (minutes the first time, then
from its cache), so these tests use one work-group size, 32, there. On a GPU device the
default sizing runs.
"""
import zlib

import numpy as np
import pytest

from pointfence.kernels import DepthFrame, InputError, PipelineParams, Selection, get_backend
from pointfence.kernels.haptics import CONTACT, ENTRENCHED, FREE, HapticParams, haptic_pipeline_params
from pointfence.kernels.opencl.kernel_shape import ANY, ENVIRONMENT, GroupSizing, shape_from_environment
from pointfence.kernels.proxy import LANES
from pointfence.kernels.reference.proxy import NumpyProxies
from pointfence.service.sources import SyntheticSource

from kernel_cases import params_for, random_rig
from proxy_cases import WS, fixture_params, small_camera


def gpu_sizing(pipe):
    """Work-groups of 32 on CPU devices (one PoCL compile), the default sizing on GPUs."""
    cl = pipe.cl
    return GroupSizing(group_sizes=((ANY, 32),)) if pipe.backend.device.type & cl.device_type.CPU else None


def assert_same(dev, ref):
    np.testing.assert_array_equal(dev.positions, ref.positions)
    np.testing.assert_array_equal(dev.normals, ref.normals)
    np.testing.assert_array_equal(dev.states, ref.states)
    np.testing.assert_array_equal(dev.steps, ref.steps)
    np.testing.assert_array_equal(dev.converged, ref.converged)
    np.testing.assert_array_equal(dev.nearest, ref.nearest)


@pytest.mark.parametrize("mode,ws_capacity,skin,B", [
    ("rendering", 4096, 0.002, 24),
    ("rendering", 4096, 0.002, 8),
    ("rendering", 48, 0.002, 24),  # working sets overflow: the work-group scans the hash directly
    ("rendering", 4096, 0.0, 24),  # regather on every move
    ("fixture", 4096, 0.002, 24),
    ("fixture", 64, 0.001, 8),
])
def test_gpu_shape_agrees_with_reference_bit_for_bit(mode, ws_capacity, skin, B):
    """The cases of test_proxy_kernel's parity test, with the GPU-shaped kernel: every output
    equal to the reference's to the bit on every tick of 50 (same working sets in the same
    order, normal sums in the same lane order, the same clip)."""
    rng = np.random.default_rng(zlib.crc32(repr((mode, ws_capacity, skin, B)).encode()))
    cams, frames = random_rig(rng, n_cams=2)
    pipe = get_backend("opencl").pipeline(cams, params_for("mask", adaptive=True, cell=0.02))
    pipe.ingest(frames)
    snap = pipe.host_snapshot()
    p = HapticParams(mode=mode, skin=skin, max_steps=40)
    surf = snap.points[rng.integers(0, snap.n_points, B), :3].astype(np.float64)
    start = surf + rng.normal(0, 0.01, (B, 3)) + [0, 0, -0.015]
    dev = pipe.proxies(start, p, ws_capacity=ws_capacity, kernel_shape="gpu", sizing=gpu_sizing(pipe))
    assert dev.shape == "gpu" and dev.ws_cap <= ws_capacity
    ref = NumpyProxies(pipe, start, p, snapshot=snap, ws_capacity=dev.ws_cap, lanes=LANES)
    states = np.zeros(3, int)
    h = start.copy()
    for _ in range(50):
        h = h + rng.normal(0, 0.0015, h.shape) + [0, 0, 0.0008]
        dev.step(h)
        ref.step(h)
        assert_same(dev, ref)
        states += np.bincount(dev.states, minlength=3)
    assert states[CONTACT] + states[ENTRENCHED] > 50 and states[FREE] > 50


def plane_frame(cam, z):
    src = SyntheticSource("plane", cam, noise=False, dropout=0.0, position=(0.0, 0.0, z))
    fr = src.read()
    return DepthFrame(cam.name, fr.depth, 0.0, mask=np.ones((cam.height, cam.width), np.uint8))


@pytest.mark.parametrize("mode", ["rendering", "fixture"])
def test_gpu_shape_buried_proxy_matches_reference(mode):
    """Proxies pressed onto a plane, then a frame lifts the plane 4.5 mm into them: buried, they
    take the push-out and, where it is blocked, the contact rule's direction or the push away
    from their deepest points. Every tick equal to the reference's, before and after the lift."""
    p = HapticParams(mode=mode)
    cam = small_camera()
    pp = fixture_params(r_base=p.r1, r_max=p.r1, selection=Selection()) if mode == "fixture" else \
        haptic_pipeline_params(p, PipelineParams(workspace=WS))
    pipe = get_backend("opencl").pipeline([cam], pp)
    xy = np.array([[0.004, -0.003], [-0.01, 0.012], [0.02, 0.0], [0.0, 0.0]])
    start = np.c_[xy, np.full(len(xy), 0.04)]
    hips = np.c_[xy, np.full(len(xy), -0.005)]
    pipe.ingest([plane_frame(cam, 0.0)])
    dev = pipe.proxies(start, p, kernel_shape="gpu", sizing=gpu_sizing(pipe))
    ref = NumpyProxies(pipe, start, p, snapshot=pipe.host_snapshot(), ws_capacity=dev.ws_cap, lanes=LANES)
    for z in np.linspace(0.04, -0.005, 40):
        h = np.c_[xy, np.full(len(xy), z)]
        dev.step(h)
        ref.step(h)
        assert_same(dev, ref)
    pipe.ingest([plane_frame(cam, 0.0045)])
    ref = NumpyProxies(pipe, dev.positions, p, snapshot=pipe.host_snapshot(), ws_capacity=dev.ws_cap, lanes=LANES)
    assert np.all(dev.positions[:, 2] < 0.0045 + p.r1 - 0.003)   # really buried
    for _ in range(6):
        dev.step(hips)
        ref.step(hips)
        assert_same(dev, ref)
    snap = pipe.host_snapshot()
    pts = snap.points[:, :3].astype(np.float64)
    rho = snap.points[:, 3] if mode == "fixture" else np.full(len(pts), p.r1)
    d = np.linalg.norm(dev.positions[:, None, :].astype(np.float64) - pts[None], axis=2) - rho[None]
    assert np.all(d.min(axis=1) >= -p.slack - 2e-7)   # every proxy out (no deeper than the slack)


def test_auto_shape_is_cpu_on_cpu_devices_and_overrides_work():
    cams, frames = random_rig(np.random.default_rng(3), n_cams=1)
    pipe = get_backend("opencl").pipeline(cams, params_for("mask", adaptive=True, cell=0.02))
    pipe.ingest(frames)
    x = pipe.host_snapshot().points[:2, :3].astype(np.float64)
    is_gpu = bool(pipe.backend.device.type & pipe.cl.device_type.GPU)
    assert pipe.proxies(x).shape == ("gpu" if is_gpu else "cpu")
    assert pipe.proxies(x, kernel_shape="cpu").shape == "cpu"
    assert pipe.proxies(x, kernel_shape=" GPU ", sizing=gpu_sizing(pipe)).shape == "gpu"
    forced = get_backend("opencl", kernel_shape="cpu").pipeline(cams, params_for("mask", adaptive=True, cell=0.02))
    assert forced.proxies(x).shape == "cpu"
    with pytest.raises(InputError, match="kernel_shape = 'warp'"):
        pipe.proxies(x, kernel_shape="warp")
    with pytest.raises(InputError, match="kernel_shape = 'fast'"):
        get_backend("opencl", kernel_shape="fast")


def test_shape_from_environment():
    assert shape_from_environment({}) == "auto"
    assert shape_from_environment({ENVIRONMENT: "gpu"}) == "gpu"
    with pytest.raises(InputError, match=ENVIRONMENT):
        shape_from_environment({ENVIRONMENT: "vector"})


def test_group_sizing_fits_local_memory():
    s = GroupSizing()
    w, cap, tb = s.plan(1, 4096, 48 * 1024, 1024)
    assert w == 128 and tb % w == 0 and tb % 8 == 0 and cap % 8 == 0
    assert 4096 + 16 * cap + 12 * tb <= 48 * 1024 and cap >= 2000   # small batches: the largest set that fits
    assert s.plan(1 << 16, 4096, 48 * 1024, 1024)[:2] == (64, 1536)
    assert s.plan(1, 48, 48 * 1024, 1024)[1] == 48                   # never above the requested capacity
    assert s.plan(10, 4096, 1 << 20, 48)[0] == 48                    # the kernel's own work-group limit
    assert s.plan(10, 4096, 1 << 20, 40)[1] <= 64 * 40               # the clip's near bits: 64 a work-item
    with pytest.raises(InputError, match="kernel_shape='cpu'"):
        s.plan(10, 4096, 1 << 20, 16)
    with pytest.raises(InputError, match="local memory"):
        s.plan(10, 4096, 6 * 1024, 256)
