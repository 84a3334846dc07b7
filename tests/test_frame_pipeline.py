"""The frame pipeline of every backend against the NumPy reference, and the reference itself."""
import numpy as np
import pytest

from pointfence.kernels import Camera, DepthFrame, PipelineParams, Workspace, get_backend
from pointfence.kernels.reference.pipeline import sigma_max

from kernel_cases import SHARED, contracts_fma, device_backends, kitchen_params, kitchen_rig, params_for, pose, random_rig

BACKENDS = device_backends()


def by_pixel(snap):
    o = np.argsort(snap.pixel, kind="stable")
    return {k: getattr(snap, k)[o] for k in ("pixel", "points", "sigma", "camera", "protected")}


def assert_same_snapshot(a, b, fma=False):
    """b equals the reference a; with ``fma`` (CUDA), points within rounding of a cell boundary
    or of the workspace faces may fall on the other side."""
    A, B = by_pixel(a), by_pixel(b)
    if fma:
        keep = np.intersect1d(A["pixel"], B["pixel"])
        assert a.n_points - keep.size <= 1e-4 * a.n_points and b.n_points - keep.size <= 1e-4 * a.n_points
        ia, ib = np.searchsorted(A["pixel"], keep), np.searchsorted(B["pixel"], keep)
        A, B = {k: v[ia] for k, v in A.items()}, {k: v[ib] for k, v in B.items()}
        ca, cb = a.cell_of()[np.argsort(a.pixel, kind="stable")][ia], b.cell_of()[np.argsort(b.pixel, kind="stable")][ib]
        assert np.count_nonzero(ca != cb) <= 1e-4 * a.n_points
    else:
        assert a.n_points == b.n_points
        assert a.per_camera == b.per_camera
        np.testing.assert_array_equal(a.cell_start, b.cell_start)
        np.testing.assert_array_equal(a.pixel, b.pixel)   # the same order within every cell
    np.testing.assert_array_equal(A["pixel"], B["pixel"])
    np.testing.assert_allclose(A["points"][:, :3], B["points"][:, :3], rtol=0, atol=1e-6)
    np.testing.assert_allclose(A["points"][:, 3], B["points"][:, 3], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(A["sigma"], B["sigma"], rtol=1e-5, atol=1e-9)
    np.testing.assert_array_equal(A["camera"], B["camera"])
    np.testing.assert_array_equal(A["protected"], B["protected"])
    # every point lies in the cell the snapshot files it under
    cells = b.grid.linear(b.grid.cell_coords(b.points))
    np.testing.assert_array_equal(cells, b.cell_of())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("selection", ["all", "box", "color", "mask"])
def test_backend_matches_reference_random_rig(backend, selection):
    rng = np.random.default_rng(7)
    cams, frames = random_rig(rng)
    params = params_for(selection)
    ref = get_backend("numpy").pipeline(cams, params)
    dev = get_backend(backend).pipeline(cams, params)
    for f in frames:
        f.depth[:] = f.depth  # same frames for both
    ref.ingest(frames)
    dev.ingest(frames)
    a, b = ref.host_snapshot(), dev.host_snapshot()
    assert a.n_points > 10000
    if selection != "all":
        assert 0 < a.protected.sum() < a.n_points
    assert_same_snapshot(a, b, contracts_fma(backend))


@pytest.mark.parametrize("backend", BACKENDS)
def test_fixed_radius_and_repeated_ingest(backend):
    rng = np.random.default_rng(3)
    cams, frames = random_rig(rng, n_cams=2, distort=False)
    params = params_for("all", adaptive=False)
    ref = get_backend("numpy").pipeline(cams, params)
    dev = get_backend(backend).pipeline(cams, params)
    for k in range(3):  # buffers reused across ingests, alternating slots
        for f in frames:
            f.depth = np.roll(f.depth, 7 * k, axis=1)
        ref.ingest(frames)
        info = dev.ingest(frames)
        assert info.seq == k + 1
        a, b = ref.host_snapshot(), dev.host_snapshot()
        assert np.all(b.points[:, 3] == np.float32(0.004))
        assert_same_snapshot(a, b, contracts_fma(backend))


@pytest.mark.parametrize("backend", ["numpy"] + BACKENDS)
def test_depth_staging_ingests_frames_written_in_place(backend):
    """Frames whose depth a camera wrote into ``depth_staging`` give the same snapshot as frames
    with their own arrays (Warp); backends without a staging buffer say so with None."""
    from dataclasses import replace

    from pointfence.kernels import InputError

    rng = np.random.default_rng(8)
    cams, frames = random_rig(rng, n_cams=2, distort=False)
    params = params_for("all", adaptive=False)
    ref = get_backend("numpy").pipeline(cams, params)
    dev = get_backend(backend).pipeline(cams, params)
    if dev.depth_staging(0) is None:
        assert backend != "warp"
        return
    for k in range(2):
        for f in frames:
            f.depth = np.roll(f.depth, 5 * k, axis=0)
        views = [dev.depth_staging(c.name) for c in cams]
        for v, f in zip(views, frames):
            assert v.shape == f.depth.shape and v.dtype == np.uint16
            np.copyto(v, f.depth)
        ref.ingest(frames)
        dev.ingest([replace(f, depth=v) for f, v in zip(frames, views)])
        assert_same_snapshot(ref.host_snapshot(), dev.host_snapshot(), contracts_fma(backend))
    for f in frames:
        f.depth = np.roll(f.depth, 11, axis=1)
    ref.ingest(frames)
    dev.ingest(frames)     # ordinary frames are copied into the staging buffer as before
    assert_same_snapshot(ref.host_snapshot(), dev.host_snapshot(), contracts_fma(backend))
    with pytest.raises(InputError, match="no camera 'nope'"):
        dev.depth_staging("nope")


@pytest.mark.parametrize("backend", BACKENDS)
def test_real_two_camera_rig_matches_reference(backend):
    if not SHARED.is_dir():
        pytest.skip("../shared/data not found: real-data tests need the shared folder beside the project")
    cams, frames = kitchen_rig()
    params = kitchen_params(cams)
    ref = get_backend("numpy").pipeline(cams, params)
    dev = get_backend(backend).pipeline(cams, params)
    ref.ingest(frames)
    dev.ingest(frames)
    a, b = ref.host_snapshot(), dev.host_snapshot()
    assert min(a.per_camera) > 150000
    assert set(np.unique(b.camera)) == {0, 1}
    assert_same_snapshot(a, b, contracts_fma(backend))


def test_reference_deprojects_a_plane_exactly():
    """A fronto-parallel plane at 0.8 m, camera 0.5 m above the world origin looking down."""
    T = pose(0.1, 0.0, 0.5, pitch=np.pi)  # camera z axis points down the world z axis
    cam = Camera("c", 64, 48, 60.0, 60.0, 31.5, 23.5, T_world_cam=T)
    depth = np.full((48, 64), 800, np.uint16)
    params = PipelineParams(workspace=Workspace((-2, -2, -2), (2, 2, 2)), cell_size=0.1)
    pipe = get_backend("numpy").pipeline([cam], params)
    pipe.ingest([DepthFrame("c", depth, 0.0)])
    s = pipe.host_snapshot()
    assert s.n_points == 64 * 48
    np.testing.assert_allclose(s.points[:, 2], 0.5 - 0.8, atol=1e-6)
    # pixel (u, v) -> camera x = (u - cx) z / fx; world x = 0.1 + x_cam, world y = -y_cam
    u = s.pixel % 64
    v = s.pixel // 64
    np.testing.assert_allclose(s.points[:, 0], 0.1 + (u - 31.5) * 0.8 / 60.0, atol=1e-6)
    np.testing.assert_allclose(s.points[:, 1], -(v - 23.5) * 0.8 / 60.0, atol=1e-6)


def test_ray_table_inverts_brown_conrady():
    cam = Camera("c", 80, 60, 70.0, 71.0, 40.2, 29.7, dist=(0.12, -0.05, 0.002, -0.001, 0.01))
    rays = cam.ray_table().astype(np.float64)
    x, y = rays[..., 0], rays[..., 1]
    k1, k2, p1, p2, k3 = cam.dist
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    u, v = np.meshgrid(np.arange(80), np.arange(60))
    np.testing.assert_allclose(cam.fx * xd + cam.cx, u, atol=1e-4)
    np.testing.assert_allclose(cam.fy * yd + cam.cy, v, atol=1e-4)


def test_noise_sigma_model():
    """sigma grows with Z^2 and is at least the axial sigma_z = a + b Z^2 at the image centre."""
    z = np.array([0.5, 1.0, 2.0], np.float32)
    P = np.zeros((3, 24), np.float32)
    P[:, 19], P[:, 20], P[:, 21] = 0.0, 1.42e-3, 0.8 / 575.0
    s = sigma_max(z, np.zeros((3, 2), np.float32), P)
    sz = 1.42e-3 * z.astype(np.float64) ** 2
    assert np.all(s >= sz * (1 - 1e-6))
    np.testing.assert_allclose(s, np.maximum(sz, 0.8 / 575.0 * z), rtol=1e-6)  # centre ray: eigenvalues decouple
    assert s[2] / s[1] > 3.0


@pytest.mark.parametrize("backend", ["numpy"] + BACKENDS)
def test_empty_and_all_invalid_frames_give_empty_valid_snapshots(backend):
    rng = np.random.default_rng(1)
    cams, frames = random_rig(rng, n_cams=2)
    params = params_for("all")
    pipe = get_backend(backend).pipeline(cams, params)
    s = pipe.host_snapshot()  # before any ingest
    assert s.n_points == 0 and s.cell_start.max() == 0
    for f in frames:
        f.depth[:] = 0
    frames[1].depth[:] = 65535
    info = pipe.ingest(frames)
    assert info.n_points == 0
    s = pipe.host_snapshot()
    assert s.n_points == 0 and s.cell_start.max() == 0
    nb = pipe.neighbors([[0.0, 0.0, 0.8]], radius=0.01)
    assert nb.count[0] == 0 and nb.nearest[0] == -1 and np.isinf(nb.nearest_dist[0])


@pytest.mark.parametrize("backend", BACKENDS)
def test_near_reading_matches_reference(backend):
    """``Camera.near_reading`` on a random rig, one camera in whole codes, one a disparity
    camera (``depth_step_inv``): every backend gives the reference's snapshot."""
    from dataclasses import replace

    rng = np.random.default_rng(11)
    cams, frames = random_rig(rng, n_cams=2)
    cams = [replace(cams[0], near_reading=True), replace(cams[1], near_reading=True, depth_step_inv=0.0029)]
    params = params_for("all")
    ref = get_backend("numpy").pipeline(cams, params)
    dev = get_backend(backend).pipeline(cams, params)
    ref.ingest(frames)
    dev.ingest(frames)
    assert_same_snapshot(ref.host_snapshot(), dev.host_snapshot(), contracts_fma(backend))


@pytest.mark.parametrize("near,step_inv", [(False, 0.0), (True, 0.0), (True, 0.0029), (False, 0.0029)])
def test_near_reading_takes_each_reading_at_the_near_end_of_its_step(near, step_inv):
    """A fronto-parallel wall at 0.4 m (code 400) and one at 2.5 m (code 2500), camera looking
    down the world -z: with ``near_reading`` each point stands half a step nearer the camera,
    half a code (0.5 mm) or half the disparity step (0.0029 * 2.5^2 / 2 = 9.1 mm at 2.5 m, the
    code's 0.5 mm at 0.4 m where the disparity step is finer); without it, where it was read.
    The disparity step alone moves nothing."""
    T = pose(0.0, 0.0, 3.0, pitch=np.pi)
    cam = Camera("c", 64, 48, 60.0, 60.0, 31.5, 23.5, T_world_cam=T, near_reading=near, depth_step_inv=step_inv)
    depth = np.full((48, 64), 400, np.uint16)
    depth[:, 32:] = 2500
    params = PipelineParams(workspace=Workspace((-5, -5, -5), (5, 5, 5)), cell_size=0.1)
    pipe = get_backend("numpy").pipeline([cam], params)
    pipe.ingest([DepthFrame("c", depth, 0.0)])
    s = pipe.host_snapshot()
    z = 3.0 - s.points[:, 2]                          # depth along the camera axis
    far = (s.pixel % 64) >= 32
    if near:
        np.testing.assert_allclose(z[~far], 0.4 - 0.0005, atol=2e-6)
        np.testing.assert_allclose(z[far], 2.5 - (0.5 * step_inv * 2.5 ** 2 if step_inv else 0.0005), atol=2e-6)
    else:
        np.testing.assert_allclose(z[~far], 0.4, atol=2e-6)
        np.testing.assert_allclose(z[far], 2.5, atol=2e-6)


def test_near_reading_settings_are_checked():
    from pointfence.kernels import InputError

    with pytest.raises(InputError, match="depth_step_inv = -0.001"):
        Camera("c", 4, 4, 3.0, 3.0, 2.0, 2.0, depth_step_inv=-0.001)
    with pytest.raises(InputError, match="near_reading = 'yes'"):
        Camera("c", 4, 4, 3.0, 3.0, 2.0, 2.0, near_reading="yes")
    assert Camera("c", 4, 4, 3.0, 3.0, 2.0, 2.0).near_bias == (0.0, 0.0)
    assert Camera("c", 4, 4, 3.0, 3.0, 2.0, 2.0, near_reading=True, depth_step_inv=0.002).near_bias == (0.0005, 0.001)
