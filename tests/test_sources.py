"""Depth sources: synthetic scenes (geometry, noise, holes, shadows, motion), recorded readers
(7-Scenes, APC, PCL TIFF / PCD / PCLZF), the factory and its errors."""
import time

import numpy as np
import pytest
from PIL import Image

from pointfence.kernels.camera import NoiseModel
from pointfence.kernels.errors import InputError
from pointfence.service.sources import (
    SCENES,
    RecordedSource,
    SyntheticSource,
    camera_from_recording,
    default_camera,
    open_source,
)
from pointfence.service.sources.lzf import lzf_decompress
from pointfence.service.sources.scenes import make_scene

SMALL = dict(width=160, height=120)  # fx = 143.95 px: same field of view as 640x480 at 575.8
B = NoiseModel().b


def small_camera(**kw):
    return default_camera(**{**SMALL, **kw})


def crop_camera(**kw):
    """The central 160x120 pixels of the default 640x480 camera (same fx, so the same
    disparity quantisation in depth as the full Kinect image)."""
    return default_camera(**{**SMALL, "fx": 575.8, **kw})


def world_points(cam, depth):
    """Deproject a uint16 depth image to world points (N, 3) of its valid pixels."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u] * cam.depth_scale
    pc = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z, np.ones_like(z)])
    return (cam.T_world_cam @ pc)[:3].T


def plane_errors(eye_height, **options):
    """Measured minus true depth (m) over valid pixels of a plane seen straight down."""
    cam = crop_camera(eye=(0, 0, eye_height), **options.pop("camera", {}))
    frame = SyntheticSource("plane", cam, dropout=0.0, **options).read()
    ok = frame.depth > 0
    return frame.depth[ok] * cam.depth_scale - eye_height, ok


# -- synthetic: geometry -----------------------------------------------------------------

def test_plane_depth_matches_analytic_depth_within_4_sigma():
    err, ok = plane_errors(0.6)
    sigma = B * 0.6**2
    assert ok.all()
    assert np.mean(np.abs(err)) < 4 * sigma
    assert abs(np.mean(err)) < 0.3e-3  # no bias
    q = 0.6**2 / (575.8 * 0.075) / 8  # disparity quantisation step at 0.6 m
    assert np.mean(np.abs(err) <= 4 * sigma + q / 2 + 0.5e-3) > 0.999


def test_inclined_plane_matches_closed_form_ray_plane_depth():
    cam = small_camera()
    src = SyntheticSource("inclined_plane", cam, noise=False, quantize=False, dropout=0.0, shadows=False)
    a = np.radians(20)  # the default slope
    n = np.array([np.sin(a), 0, np.cos(a)])
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    d_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, float)], -1)
    d_world = d_cam @ cam.T_world_cam[:3, :3].T
    expected = -(cam.T_world_cam[:3, 3] @ n) / (d_world @ n)
    depth = src.read().depth * cam.depth_scale
    assert np.abs(depth - expected).max() <= 0.5e-3 + 1e-9
    assert 0.4 < expected.min() < expected.max() < 0.8  # tabletop range


@pytest.mark.parametrize("name", list(SCENES))
def test_every_scene_deprojects_onto_its_analytic_surface(name):
    # Oblique camera, exact rendering, 20 um depth units: every valid pixel lies on the surface.
    cam = small_camera(eye=(0.15, -0.3, 0.5), depth_scale=2e-5)
    src = SyntheticSource(name, cam, noise=False, quantize=False, dropout=0.0, shadows=False,
                          color=True, mask=True, start_time=0.4)
    frame = src.read()
    frame.check(cam.width, cam.height)
    assert frame.depth.dtype == np.uint16 and frame.timestamp == pytest.approx(0.4)
    ok = frame.depth > 0
    assert ok.mean() > 0.8  # the ridge's far face turns away from oblique rays near the top
    pts = world_points(cam, frame.depth)
    assert np.abs(src.scene.distance(pts, 0.4)).max() < 5e-5
    # Free side is positive: the camera sits in free space; below the surface is material.
    assert src.scene.distance(cam.T_world_cam[:3, 3], 0.4)[0] > 0.2
    below = pts - 0.002 * src.scene.normal(pts, 0.4)
    assert np.all(src.scene.distance(below, 0.4) < 0)
    # The protected object is marked red, the rest white.
    prot = frame.mask > 0
    assert 0 < prot.mean() < 0.9
    assert np.all(frame.color[prot] == (220, 30, 30)) and np.all(frame.color[~prot & ok] == (235, 235, 235))


def test_scene_distance_is_exact_away_from_the_surface():
    sphere = make_scene("sphere", radius=0.05)
    assert sphere.distance([[0, 0, 0.05 + 0.05 + 0.03]])[0] == pytest.approx(0.03)
    ridge = make_scene("corner")  # 90 deg ridge along y at z = 0.1
    assert ridge.distance([[0, 0, 0.13]])[0] == pytest.approx(0.03)  # above the edge: to the edge
    assert ridge.distance([[0.1, 0, 0.1]])[0] == pytest.approx(0.1 / np.sqrt(2))  # to the +x face
    bowl = make_scene("bowl", radius=0.08, depth=0.03)
    assert bowl.distance([[0, 0, 0.0]])[0] == pytest.approx(0.03)  # centre of the rim plane
    ledge = make_scene("ledge")
    assert ledge.distance([[-0.01, 0, 0.005]])[0] == pytest.approx(0.005)  # lower level under the step height
    n = make_scene("plane").normal([[0.1, 0.2, 0.01]])
    assert np.allclose(n, [[0, 0, 1]], atol=1e-6)
    pts = make_scene("bump").surface_points(spacing=0.01, half_extent=0.1)
    assert len(pts) == 21 * 21 and np.abs(make_scene("bump").distance(pts)).max() < 1e-9


# -- synthetic: sensor effects ------------------------------------------------------------

def test_noise_std_grows_with_depth_squared():
    # Pool four plane heights a quarter disparity step apart: the 1/8 px quantisation lattice
    # lands differently on each, as it does on a real scene.
    def pooled_std(z):
        q = z * z / (575.8 * 0.075) / 8
        return np.concatenate([plane_errors(z + k * q / 4)[0] for k in range(4)]).std()

    # (1.4 / 0.7)^2 = 4 for the noise alone; quantisation and 1 mm codes pull the total to ~3.3
    # (a depth-linear noise would give 2).
    assert 2.8 < pooled_std(1.4) / pooled_std(0.7) < 4.8
    # Without quantisation, in fine depth units, the spread is the model's sigma_z = b Z^2.
    fine = dict(quantize=False, camera=dict(depth_scale=5e-5))
    for z in (0.7, 1.4):
        assert plane_errors(z, **fine)[0].std() == pytest.approx(B * z * z, rel=0.05)


def test_disparity_quantisation_makes_depth_steps_that_grow_with_depth_squared():
    cam = small_camera(eye=(0, 0, 1.5), depth_scale=1e-5)
    src = SyntheticSource("inclined_plane", cam, noise=False, dropout=0.0, shadows=False, angle_deg=20,
                          position=(0, 0, 0.3))
    z = np.unique(src.read().depth[src.read().depth > 0]) * 1e-5
    steps = np.diff(z)
    expected = z[:-1] ** 2 / (cam.fx * 0.075) / 8
    assert np.allclose(steps, expected, rtol=0.02)


@pytest.mark.parametrize("dropout", [0.0, 0.2])
def test_holes_fraction_as_configured(dropout):
    frame = SyntheticSource("plane", small_camera(), dropout=dropout).read()
    assert np.mean(frame.depth == 0) == pytest.approx(dropout, abs=0.015)


def test_shadows_appear_beside_the_sphere_away_from_the_projector():
    cam = small_camera()
    opts = dict(noise=False, dropout=0.0)
    with_shadow = SyntheticSource("sphere", cam, shadows=True, **opts)
    without = SyntheticSource("sphere", cam, shadows=False, **opts).read().depth
    depth = with_shadow.read().depth
    assert np.all(without > 0)
    holes = depth == 0
    assert 20 < holes.sum() < 0.05 * holes.size
    v, u = np.nonzero(holes)
    assert np.all(u < cam.cx)  # the projector is at +x (image right): shadows fall to the left
    true = with_shadow.true_depth(0.0)[holes]
    assert np.allclose(true[true > 0.59], 0.6, atol=1e-6) and np.mean(true > 0.59) > 0.9  # on the table


def test_translating_plane_moves_speed_times_dt_between_frames():
    cam = small_camera(depth_scale=1e-5)
    src = SyntheticSource("translating_plane", cam, rate_hz=30, speed=0.08, noise=False, quantize=False, dropout=0)
    f0, f1, f2 = src.read(), src.read(), src.read()
    assert (f0.timestamp, f1.timestamp, f2.timestamp) == pytest.approx((0, 1 / 30, 2 / 30))
    step = (f0.depth.astype(float) - f1.depth) * 1e-5
    assert np.mean(step) == pytest.approx(0.08 / 30, rel=0.01)  # moving up, towards the camera
    scene = src.scene
    assert scene.distance([[0, 0, 0.08 * 0.5]], 0.5)[0] == pytest.approx(0, abs=1e-12)
    assert max(abs(scene.offset(t)) for t in np.linspace(0, 10, 501)) <= 0.1 + 1e-12  # reverses at travel / 2


def test_translating_plane_rests_until_its_start():
    scene = make_scene("translating_plane", speed=0.5, travel=0.0, start=2.0)
    assert [scene.offset(t) for t in (0.0, 1.9, 2.0)] == [0.0, 0.0, 0.0]
    assert scene.offset(2.5) == pytest.approx(0.25)
    scene.start = float("inf")               # a live run holds it until its loop runs
    assert scene.offset(100.0) == 0.0
    assert make_scene("translating_plane", speed=0.5, travel=0.0).offset(-0.2) == pytest.approx(-0.1)   # no start
    with pytest.raises(InputError, match="start"):
        make_scene("translating_plane", start=float("nan"))


def test_rocking_platform_tilts_sinusoidally():
    scene = make_scene("rocking_platform", amplitude_deg=10, period=2.0)
    n = scene.normal([[0, 0, 0.05]], 0.5)[0]  # quarter period: full tilt about y
    assert np.degrees(np.arccos(n[2])) == pytest.approx(10, abs=1e-3)
    assert np.allclose(scene.normal([[0, 0, 0.05]], 1.0)[0], [0, 0, 1], atol=1e-6)


def test_same_seed_same_frames_other_seed_other_frames():
    a = [f.depth for f, _ in zip(SyntheticSource("sphere", small_camera(), seed=7), range(3))]
    b = [f.depth for f, _ in zip(SyntheticSource("sphere", small_camera(), seed=7), range(3))]
    c = SyntheticSource("sphere", small_camera(), seed=8).read().depth
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[0], a[1]) and not np.array_equal(a[0], c)


# -- source interface --------------------------------------------------------------------

def test_iteration_close_and_context_manager():
    with SyntheticSource("plane", small_camera(), max_frames=3, start_time=2.0, rate_hz=10) as src:
        frames = list(src)
        assert [f.seq for f in frames] == [0, 1, 2] and src.ended and src.read() is None
        assert [f.timestamp for f in frames] == pytest.approx([2.0, 2.1, 2.2])
    assert src.closed
    with pytest.raises(InputError, match="closed"):
        src.read()


def test_realtime_paces_frames_and_times_out():
    src = SyntheticSource("plane", small_camera(), rate_hz=50, realtime=True)
    t0 = time.monotonic()
    for _ in range(4):
        assert src.read() is not None
    assert time.monotonic() - t0 >= 3 / 50 - 2e-3
    slow = SyntheticSource("plane", small_camera(), rate_hz=2, realtime=True)
    assert slow.read() is not None
    t0 = time.monotonic()
    assert slow.read(timeout=0.02) is None
    assert 0.015 < time.monotonic() - t0 < 0.3
    late = SyntheticSource("plane", small_camera(), rate_hz=100, realtime=True)
    late.read()
    time.sleep(0.06)
    assert late.read().seq >= 5  # a late reader gets the latest due frame, like a live camera
    fast = SyntheticSource("plane", small_camera(), rate_hz=2)  # not realtime: immediate
    t0 = time.monotonic()
    fast.read(), fast.read()
    assert time.monotonic() - t0 < 0.3


def test_open_source_parses_scene_and_options():
    src = open_source("synthetic:sphere?radius=0.05&seed=3&color=true", small_camera(), rate_hz=15)
    assert isinstance(src, SyntheticSource) and src.scene.radius == 0.05 and src.seed == 3
    assert src.rate_hz == 15 and src.read().color.shape == (120, 160, 3)
    assert open_source("synthetic:plane").camera.width == 640  # default camera


@pytest.mark.parametrize("spec, words", [
    ("kinect:0", ["synthetic:", "recorded:", "openni2:", "depthai:"]),
    ("synthetic:teapot", ["teapot", "plane", "rocking_platform"]),
    ("synthetic:sphere?radiu=1", ["radiu", "radius", "rate_hz"]),
    ("synthetic:plane?dropout=1.5", ["dropout", "[0, 1)"]),
    ("no-colon", ["synthetic:"]),
    ("recorded:/no/such/folder", ["/no/such/folder", "no such file"]),
])
def test_bad_specs_give_helpful_input_errors(spec, words):
    with pytest.raises(InputError) as e:
        open_source(spec)
    for w in words:
        assert w in str(e.value)


def test_recorded_errors_name_the_path_and_what_is_expected(tmp_path):
    with pytest.raises(InputError, match="no depth frames"):
        open_source(f"recorded:{tmp_path}")
    Image.fromarray(np.zeros((4, 5), np.uint16)).save(tmp_path / "a.png")
    with pytest.raises(InputError, match="fx, fy, cx, cy"):
        RecordedSource(tmp_path)
    src = RecordedSource(tmp_path, fx=5, cx=2, cy=2, loop=False)  # intrinsics given as options
    assert src.camera.width == 5 and src.read().depth.shape == (4, 5) and src.read() is None
    Image.fromarray(np.zeros((4, 5), np.uint8)).save(tmp_path / "b.png")
    with pytest.raises(InputError, match="16-bit") as e:
        list(RecordedSource(tmp_path, fx=5, cx=2, cy=2, loop=False))
    assert "b.png" in str(e.value)
    (tmp_path / "c.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="c.png"):
        RecordedSource(tmp_path / "c.png", fx=5, cx=2, cy=2).read()


def test_lzf_decoder_handles_literals_and_overlapping_references():
    # literal "abc", then a 9-byte back-reference 3 bytes back (overlapping): "abc" * 4.
    stream = bytes([2]) + b"abc" + bytes([0xE0, 0, 2])
    assert lzf_decompress(stream, 12) == b"abc" * 4
    with pytest.raises(InputError, match="corrupt"):
        lzf_decompress(bytes([0xE0, 0, 9]), 12)
    with pytest.raises(InputError, match="promised"):
        lzf_decompress(stream, 13)


# -- recorded: real data -----------------------------------------------------------------

def test_7scenes_frame_150_and_rigid_pose(shared_data):
    folder = shared_data / "7scenes_kitchen_50f"
    cam = camera_from_recording(folder, name="kitchen")
    assert (cam.name, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == ("kitchen", 640, 480, 585, 585, 320, 240)
    src = open_source(f"recorded:{folder}", loop=False)
    assert len(src) == 50
    f = src.read()
    assert f.depth.shape == (480, 640) and f.depth.dtype == np.uint16
    valid = (f.depth > 0) & (f.depth < 65535)
    assert 0.8 < valid.mean() < 0.95 and 1500 < np.median(f.depth[valid]) < 2500
    T = f.T_world_cam
    assert T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1) and np.array_equal(T[3], [0, 0, 0, 1])
    raw = np.loadtxt(folder / "frame-000150.pose.txt")
    assert np.allclose(T, raw, atol=5e-4) and np.array_equal(T, cam.T_world_cam)
    frames = [f] + list(src)
    assert len(frames) == 50 and src.ended
    assert np.diff([g.timestamp for g in frames]) == pytest.approx(np.full(49, 1 / 30))
    step = np.linalg.norm(frames[1].T_world_cam[:3, 3] - T[:3, 3])
    assert 0.001 < step < 0.02  # hand-held camera: mm per frame


def test_7scenes_loops_and_single_file(shared_data):
    folder = shared_data / "7scenes_kitchen_50f"
    src = RecordedSource(folder, rate_hz=100)
    frames = [src.read() for _ in range(51)]
    assert frames[50].seq == 50 and frames[50].timestamp == pytest.approx(0.5)
    assert np.array_equal(frames[50].depth, frames[0].depth)
    one = open_source(f"recorded:{folder / 'frame-000151.depth.png'}")
    assert len(one) == 1 and np.array_equal(one.read().depth, frames[1].depth)


def test_apc_frames_intrinsics_and_poses(shared_data):
    src = RecordedSource(shared_data / "apc_shelfbin_50f", loop=False)
    cam = src.camera
    assert (cam.fx, cam.cx, cam.cy) == pytest.approx((615.1951904, 298.4426880, 247.5191956))
    frames = list(src)
    assert len(frames) == 50 and all(f.depth.shape == (480, 640) for f in frames)
    assert np.array_equal(frames[0].T_world_cam, np.eye(4))
    holes = np.mean([np.mean(f.depth == 0) for f in frames])
    assert 0.55 < holes < 0.75
    med = np.median(frames[0].depth[frames[0].depth > 0])
    assert 300 < med < 500  # close range, mm
    assert all(np.allclose(f.T_world_cam[:3, :3] @ f.T_world_cam[:3, :3].T, np.eye(3), atol=1e-9) for f in frames)


def test_tiff_frames_with_intrinsics_from_the_pcl_xml(shared_data):
    src = open_source(f"recorded:{shared_data / 'pcl_kinect_grabber_seq' / 'tiff'}", loop=False)
    cam = src.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.depth_scale) == (525, 525, 320, 240, 0.001)
    frames = list(src)
    assert len(frames) == 3 and frames[0].T_world_cam is None
    d = frames[0].depth
    assert d.dtype == np.uint16 and 0.8 < np.mean(d > 0) < 0.95 and 800 < np.median(d[d > 0]) < 1000


def test_pcd_depth_equals_tiff_depth(shared_data):
    seq = shared_data / "pcl_kinect_grabber_seq"
    pcd = RecordedSource(seq / "pcd", loop=False)
    assert (pcd.camera.fx, pcd.camera.fy, pcd.camera.cx, pcd.camera.cy) == pytest.approx((525, 525, 320, 240), abs=1e-3)
    tiff = RecordedSource(seq / "tiff", loop=False)
    pairs = list(zip(pcd, tiff))
    assert len(pairs) == 3
    for p, t in pairs:
        assert np.array_equal(p.depth > 0, t.depth > 0)
        ok = t.depth > 0
        assert np.abs(p.depth[ok].astype(int) - t.depth[ok]).max() <= 1
        assert p.color.shape == (480, 640, 3) and p.color.dtype == np.uint8 and p.color.std() > 10
    pclzf = RecordedSource(seq / "pclzf", loop=False)
    assert np.array_equal(pclzf.read().depth, pairs[0][1].depth)


def test_a_folder_of_recordings_points_to_its_subfolders(shared_data):
    with pytest.raises(InputError, match="subfolders") as e:
        open_source(f"recorded:{shared_data / 'pcl_kinect_grabber_seq'}")
    assert "tiff" in str(e.value)


def test_recorded_frames_must_fit_the_given_camera(shared_data):
    src = RecordedSource(shared_data / "pcl_kinect_grabber_seq" / "tiff", small_camera())
    with pytest.raises(InputError, match="160x120"):
        src.read()
