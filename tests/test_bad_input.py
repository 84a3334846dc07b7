"""Bad input to the kernels: a clear error naming the value, and nothing half-built."""
import numpy as np
import pytest

from pointfence.kernels import (BackendUnavailable, Camera, DepthFrame, InputError, PipelineParams, RadiusModel,
                                Selection, Workspace, get_backend)
from pointfence.kernels.opencl.context import select_device

from kernel_cases import device_backends, params_for, random_rig

BACKENDS = ["numpy"] + device_backends()


def make(backend, n_cams=2):
    rng = np.random.default_rng(9)
    cams, frames = random_rig(rng, n_cams=n_cams)
    pipe = get_backend(backend).pipeline(cams, params_for("all"))
    pipe.ingest(frames)
    return pipe, cams, frames


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mutate, message", [
    (lambda f: setattr(f[0], "depth", f[0].depth.astype(np.float32)), "dtype float32; expected uint16"),
    (lambda f: setattr(f[0], "depth", f[0].depth[:, :-1].copy()), "expected (120, 160)"),
    (lambda f: setattr(f[1], "color", np.zeros((120, 160), np.uint8)), "expected uint8 (120, 160, 3)"),
    (lambda f: setattr(f[1], "camera", "nosuchcam"), "unknown camera 'nosuchcam'"),
    (lambda f: f.pop(), "no frame for camera(s) cam1"),
    (lambda f: f.append(f[0]), "two frames from camera 'cam0'"),
    (lambda f: setattr(f[0], "T_world_cam", np.diag([1.0, 1.0, 2.0, 1.0])), "T_world_cam: rotation part is not a rotation"),
    (lambda f: setattr(f[0], "T_world_cam", np.full((4, 4), np.nan)), "contains NaN"),
])
def test_bad_frames_raise_and_keep_the_previous_snapshot(backend, mutate, message):
    pipe, cams, frames = make(backend)
    before = pipe.host_snapshot()
    seq = pipe.seq
    bad = list(frames)
    mutate(bad)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        pipe.ingest(bad)
    after = pipe.host_snapshot()
    assert pipe.seq == seq and after.seq == before.seq
    np.testing.assert_array_equal(after.points, before.points)
    np.testing.assert_array_equal(after.cell_start, before.cell_start)


@pytest.mark.parametrize("kwargs, message", [
    (dict(fx=float("nan")), "fx = nan; expected a finite number"),
    (dict(fy=-3.0), "expected > 0 pixels"),
    (dict(width=0), "width = 0; expected a positive integer"),
    (dict(depth_scale=0.0), "depth_scale = 0.0"),
    (dict(T_world_cam=np.array([[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])), "not a rotation"),
    (dict(T_world_cam=np.eye(3)), "shape (3, 3); expected 4x4"),
    (dict(dist=(0.1, 0.2)), "expected 5 finite numbers"),
    (dict(z_min=2.0, z_max=1.0), "expected 0 <= z_min < z_max"),
])
def test_bad_camera_parameters(kwargs, message):
    base = dict(name="c", width=64, height=48, fx=60.0, fy=60.0, cx=32.0, cy=24.0)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Camera(**{**base, **kwargs})


@pytest.mark.parametrize("make_params, message", [
    (lambda: Workspace((0, 0, 0), (1, -1, 1)), "expected min < max"),
    (lambda: Workspace((0, 0, float("inf")), (1, 1, 1)), "expected 3 finite numbers"),
    (lambda: Selection("colour"), "selection kind 'colour'; expected one of"),
    (lambda: Selection("color", color_lo=(0, 0, 300)), "expected 3 integers 0..255"),
    (lambda: RadiusModel(r_base=0.02, r_max=0.01), "r_max = 0.01 < r_base = 0.02"),
    (lambda: PipelineParams(cell_size=0.0), "cell_size = 0.0"),
    (lambda: PipelineParams(workspace=Workspace((-10, -10, -10), (10, 10, 10)), cell_size=0.001), "cells (limit"),
])
def test_bad_pipeline_parameters(make_params, message):
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        make_params()


@pytest.mark.parametrize("backend", BACKENDS)
def test_bad_queries(backend):
    pipe, _, _ = make(backend, n_cams=1)
    with pytest.raises(InputError, match=r"query 1 = \[nan, 0.0, 0.0\] is not finite"):
        pipe.neighbors([[0, 0, 0.8], [np.nan, 0, 0]], 0.01)
    with pytest.raises(InputError, match="queries shape"):
        pipe.neighbors(np.zeros((3, 2)), 0.01)
    with pytest.raises(InputError, match="radius = -0.01"):
        pipe.neighbors([[0, 0, 0.8]], -0.01)
    with pytest.raises(InputError, match="max_neighbors = 0"):
        pipe.neighbors([[0, 0, 0.8]], 0.01, max_neighbors=0)


def test_unknown_backend_and_device_name_what_is_available():
    with pytest.raises(BackendUnavailable, match="unknown backend 'cuda'; available: numpy, opencl"):
        get_backend("cuda")
    with pytest.raises(BackendUnavailable, match="no OpenCL device matches .no-such-gpu.. Found: .+ PoCL comes with: pip install"):
        select_device("no-such-gpu")


def test_opencl_device_spec_pocl_names_pocls_cpu_device():
    """PoCL's platform calls itself "Portable Computing Language": "pocl" still picks its CPU
    device (the threaded one before the in-thread "basic"), as the default does."""
    dev = select_device("pocl")
    assert "portable computing language" in dev.platform.name.lower()
    assert dev == select_device("") and not dev.name.lower().startswith("basic")


class _FakePlatform:
    name = "Portable Computing Language"

    def __init__(self, ptr, version, works):
        self.int_ptr, self.version, self.works = ptr, version, works
        self.devs = [_FakeDevice(self, "basic-cpu"), _FakeDevice(self, "pthread-cpu")]

    def get_devices(self):
        return self.devs


class _FakeDevice:
    def __init__(self, platform, name):
        import pyopencl as cl

        self.platform, self.name, self.type = platform, name, cl.device_type.CPU


def test_default_device_skips_a_pocl_whose_compiler_fails_on_this_cpu(monkeypatch):
    """pyopencl's wheel brings PoCL 3.0 (LLVM 14), whose compiler fails every build on CPUs newer
    than it (AMD Zen 5: "unknown target CPU 'generic'"); a distribution's PoCL installed beside it
    works. The default choice takes a PoCL whose compiler works, a release build first."""
    from pointfence.kernels.opencl import context

    old = _FakePlatform(1, "OpenCL 3.0 PoCL 3.0-rc2  Linux, Release, LLVM 14.0.6", works=False)
    distro = _FakePlatform(2, "OpenCL 3.0 PoCL 3.1+debian  Linux, None+Asserts, LLVM 15.0.6", works=True)
    fast = _FakePlatform(3, "OpenCL 3.0 PoCL 6.0  Linux, Release, LLVM 18", works=True)
    probed = []

    def works(platform, device):
        probed.append(platform.int_ptr)
        return platform.works

    monkeypatch.setattr(context, "_compiler_works", works)
    for platforms, chosen in (([old, distro], distro), ([distro, old], distro), ([distro, old, fast], fast),
                              ([old], old)):
        monkeypatch.setattr(context, "_get_platforms", lambda cl, ps=platforms: ps)
        probed.clear()
        dev = context.select_device("")
        assert dev.platform is chosen and dev.name == "pthread-cpu"    # (its in-thread "basic" device after it)
        if len(platforms) == 1:  # one PoCL: nothing probed, its build errors say what to do
            assert probed == []
    monkeypatch.setattr(context, "_get_platforms", lambda cl: [distro, fast, old])
    probed.clear()
    dev = context.select_device("")
    assert dev.platform is fast and dev.name == "pthread-cpu" and set(probed) == {3}   # the first release build works


def test_rig_rejects_duplicate_camera_names():
    c = Camera("same", 8, 8, 10.0, 10.0, 4.0, 4.0)
    with pytest.raises(InputError, match="repeated: same"):
        get_backend("numpy").pipeline([c, c], PipelineParams())
    with pytest.raises(InputError, match="no cameras given"):
        get_backend("numpy").pipeline([], PipelineParams())


def test_frame_pose_overrides_camera_pose():
    """A recorded frame's own pose moves its points; the camera's default pose is ignored."""
    cam = Camera("c", 8, 6, 10.0, 10.0, 3.5, 2.5)
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    pipe = get_backend("numpy").pipeline([cam], PipelineParams(workspace=Workspace((-2,) * 3, (2,) * 3)))
    pipe.ingest([DepthFrame("c", np.full((6, 8), 1000, np.uint16), 0.0)])
    a = pipe.host_snapshot().points[:, :3].copy()
    pipe.ingest([DepthFrame("c", np.full((6, 8), 1000, np.uint16), 0.0, T_world_cam=T)])
    b = pipe.host_snapshot().points[:, :3]
    np.testing.assert_allclose(np.sort(b, axis=0) - np.sort(a, axis=0), np.tile([0.1, -0.2, 0.3], (48, 1)), atol=1e-6)
