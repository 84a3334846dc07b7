"""Deterministic snapshots (issue 20, deliverable 0) on real recordings from ../shared/data.

The same frames must give the same snapshot, point for point in the same order, on every
build and on every backend: the order within a cell is the reference's (rig pixel order, i.e.
camera, then pixel), so the proxy's sums over a cell's points round the same way on every run
and replays are bit-exact. Scenes: the 7-Scenes kitchen (Kinect v1, 1.8-2.3 m, a moving camera)
and the APC shelf bin (0.3-0.5 m: thousands of pixels per 3 cm cell, where a scatter that hands
out ranks in arrival order has the most runs of one cell to interleave).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pointfence.kernels import Camera, DepthFrame, PipelineParams, RadiusModel, Workspace, get_backend
from pointfence.kernels.haptics import CONTACT, HapticParams, HapticScene
from pointfence.kernels.motion import MotionModel

from kernel_cases import SHARED, device_backends, read_png16

BACKENDS = device_backends()
#: Builds of the same frames compared in the repeat tests: a scatter whose order depends on
#: thread timing differs from the first build within a few builds on a 2-core PoCL.
N_BUILDS = 20


def _rigid(T: np.ndarray) -> np.ndarray:
    """The stored poses carry 8 significant digits: re-orthonormalise the rotation."""
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    return T


def apc_sequence(n: int = 6):
    """One RealSense-class camera over the APC shelf bin: the camera and ``n`` consecutive
    frames (every 2nd recorded frame, 66 ms apart), each with its pose relative to the first."""
    root = SHARED / "apc_shelfbin_50f"
    if not root.is_dir():
        pytest.skip("../shared/data/apc_shelfbin_50f not found: real-data tests need the shared folder")
    K = np.loadtxt(root / "intrinsics.K.txt")
    cam = Camera("apc", 640, 480, K[0, 0], K[1, 1], K[0, 2], K[1, 2], T_world_cam=np.eye(4), z_min=0.2, z_max=1.5)
    frames = []
    for k in range(n):
        fid = 15 + 2 * k
        T = _rigid(np.loadtxt(root / f"frame-{fid:06d}.pose.txt"))
        frames.append(DepthFrame("apc", read_png16(root / f"frame-{fid:06d}.depth.png"), k / 15.0, seq=k,
                                 T_world_cam=T))
    return cam, frames


def apc_params(motion: bool = False, cell: float = 0.03) -> PipelineParams:
    """The shelf bin in front of the first camera pose (world = that camera's frame, m)."""
    return PipelineParams(workspace=Workspace((-0.4, -0.4, 0.1), (0.4, 0.4, 1.0)), cell_size=cell,
                          radius=RadiusModel(r_base=0.004, adaptive=True, k_sigma=3.0, r_max=0.012),
                          motion=MotionModel(enabled=motion))


def kitchen_sequence(n: int = 4):
    """One Kinect v1 moving through the 7-Scenes kitchen: ``n`` consecutive frames with poses."""
    root = SHARED / "7scenes_kitchen_50f"
    if not root.is_dir():
        pytest.skip("../shared/data/7scenes_kitchen_50f not found: real-data tests need the shared folder")
    cam = Camera("kinect", 640, 480, 585.0, 585.0, 320.0, 240.0, T_world_cam=np.eye(4))
    frames = [DepthFrame("kinect", read_png16(root / f"frame-{fid:06d}.depth.png"), fid / 30.0, seq=fid - 150,
                         T_world_cam=_rigid(np.loadtxt(root / f"frame-{fid:06d}.pose.txt")))
              for fid in range(150, 150 + n)]
    return cam, frames


def kitchen_params(motion: bool = False) -> PipelineParams:
    return PipelineParams(workspace=Workspace((-3, -3, -3), (3, 3, 3)), cell_size=0.03,
                          radius=RadiusModel(r_base=0.01, adaptive=True, r_max=0.03), motion=MotionModel(enabled=motion))


def snapshot_arrays(s) -> dict:
    """Every array of a host snapshot, in its own order (nothing re-sorted)."""
    out = {"points": s.points, "sigma": s.sigma, "camera": s.camera, "protected": s.protected, "pixel": s.pixel,
           "cell_start": s.cell_start}
    if s.velocity is not None:
        out["velocity"] = s.velocity
    return out


def assert_bit_identical(a: dict, b: dict, what: str):
    assert a.keys() == b.keys(), f"{what}: arrays {sorted(a)} vs {sorted(b)}"
    for k in a:
        x, y = np.ascontiguousarray(a[k]), np.ascontiguousarray(b[k])
        assert x.dtype == y.dtype and x.shape == y.shape, f"{what}: {k} {x.dtype}{x.shape} vs {y.dtype}{y.shape}"
        rows_x = x.view(np.uint8).reshape(x.shape[0], -1)
        rows_y = y.view(np.uint8).reshape(y.shape[0], -1)
        diff = np.flatnonzero((rows_x != rows_y).any(axis=1))
        assert diff.size == 0, f"{what}: {k} differs at {diff.size} of {x.shape[0]} rows (first at {diff[:5]})"


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("scene", ["apc", "kitchen"])
def test_same_real_frame_gives_bit_identical_snapshots(backend, scene):
    """N builds of one real frame, alternating the two snapshot slots and on a second pipeline,
    give the same arrays bit for bit, in the same order."""
    cam, frames = apc_sequence(1) if scene == "apc" else kitchen_sequence(1)
    params = apc_params() if scene == "apc" else kitchen_params()
    pipe = get_backend(backend).pipeline([cam], params)
    pipe.ingest(frames)
    first = snapshot_arrays(pipe.host_snapshot())
    assert first["points"].shape[0] > 50000
    assert np.diff(first["cell_start"]).max() > 250   # dense cells: many runs of one cell to order
    for k in range(N_BUILDS):
        pipe.ingest([replace(frames[0], seq=k + 1)])
        assert_bit_identical(first, snapshot_arrays(pipe.host_snapshot()), f"{backend} {scene} build {k + 2}")
    other = get_backend(backend).pipeline([cam], params)
    other.ingest(frames)
    assert_bit_identical(first, snapshot_arrays(other.host_snapshot()), f"{backend} {scene} second pipeline")


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("scene", ["apc", "kitchen"])
def test_snapshot_order_is_the_references(backend, scene):
    """Within every cell the points are in rig pixel order, as the reference's stable sort
    leaves them: the whole snapshot equals the reference's (positions to rounding on CUDA)."""
    cam, frames = apc_sequence(1) if scene == "apc" else kitchen_sequence(1)
    params = apc_params() if scene == "apc" else kitchen_params()
    ref = get_backend("numpy").pipeline([cam], params)
    dev = get_backend(backend).pipeline([cam], params)
    ref.ingest(frames)
    dev.ingest(frames)
    a, b = ref.host_snapshot(), dev.host_snapshot()
    np.testing.assert_array_equal(b.cell_start, a.cell_start)
    np.testing.assert_array_equal(b.pixel, a.pixel)
    np.testing.assert_array_equal(b.protected, a.protected)
    np.testing.assert_allclose(b.points[:, :3], a.points[:, :3], rtol=0, atol=1e-6)
    # ascending pixels within each cell
    cell = b.cell_of()
    same = cell[1:] == cell[:-1]
    assert np.all(b.pixel[1:][same] > b.pixel[:-1][same])


@pytest.mark.parametrize("backend", BACKENDS)
def test_motion_snapshots_are_bit_identical_across_runs(backend):
    """A real moving sequence with motion estimation on: two runs give the same points, order
    and per-point velocities, snapshot by snapshot."""
    cam, frames = kitchen_sequence(4)
    runs = []
    for _ in range(2):
        pipe = get_backend(backend).pipeline([cam], kitchen_params(motion=True))
        snaps = []
        for f in frames:
            pipe.ingest([f])
            snaps.append(snapshot_arrays(pipe.host_snapshot()))
        runs.append(snaps)
    assert any("velocity" in s for s in runs[0]), "motion estimation gave no velocities: the test compares none"
    for k, (a, b) in enumerate(zip(*runs)):
        assert_bit_identical(a, b, f"{backend} motion snapshot {k}")


def _trajectory(backend: str, cam, frames, steps: int):
    """Proxies pushed into the shelf bin's contents while the frames change every 33 ticks;
    returns proxy positions, normals, states and forces of every tick."""
    params = HapticParams(mode="rendering")
    g = np.linspace(-0.12, 0.12, 8)
    starts = np.array([[x, y, 0.22] for x in g for y in g])
    scene = HapticScene([cam], positions=starts, params=params, backend=backend,
                        pipeline_params=replace(apc_params(), cell_size=0.02))
    out = []
    fi = 0
    for t in range(steps):
        if t % 33 == 0:
            scene.ingest([frames[fi % len(frames)]])
            fi += 1
        hips = starts + np.array([0.0, 0.0, 0.3 * min(t, 250) / 250])   # 1.2 mm a tick, to 0.52 m
        f = scene.step(hips)
        out.append(np.concatenate([scene.proxies.ravel(), scene.normals.ravel(), scene.states.astype(np.float64),
                                   f.ravel()]))
    return np.array(out), scene


@pytest.mark.parametrize("backend", BACKENDS)
def test_proxy_trajectory_over_real_frames_is_bit_identical(backend):
    """A few hundred haptic ticks over changing real frames, twice: every tick's proxies,
    normals, states and forces are the same bit for bit."""
    cam, frames = apc_sequence(10)
    a, scene = _trajectory(backend, cam, frames, 330)
    states = a[:, 6 * len(scene):7 * len(scene)]
    assert np.count_nonzero(states == CONTACT) > 1000, "the proxies hardly touched the scene: the test compares free motion"
    b, _ = _trajectory(backend, cam, frames, 330)
    bad = np.flatnonzero((a != b).any(axis=1))
    assert bad.size == 0, f"{backend}: ticks differ from tick {bad[0]} on ({bad.size} of {len(a)} ticks)"
