"""Calibration against synthetic renders with known ground truth, the 7-Scenes two-camera rig,
bad inputs, the TOML output and the CLI."""
import io
import textwrap

import numpy as np
import pytest

pytest.importorskip("cv2", reason="calibration needs OpenCV (pip install opencv-python-headless)")

from pointfence.calib import extrinsics as ex  # noqa: E402
from pointfence.calib.common import inv_T, make_T, pose_error, perturb, progress  # noqa: E402
from pointfence.calib.intrinsics import calibrate  # noqa: E402
from pointfence.calib.noise import fit_noise, plane_residuals, synthetic_captures  # noqa: E402
from pointfence.calib.output import camera_snippet, update_config  # noqa: E402
from pointfence.calib.render import checkerboard_views  # noqa: E402
from pointfence.kernels.camera import Camera  # noqa: E402
from pointfence.kernels.errors import InputError  # noqa: E402

TRUTH = Camera("truth", 640, 480, 600.0, 602.0, 322.0, 241.0, dist=(-0.08, 0.05, 0.0005, -0.0004, 0.0))


@pytest.fixture(scope="module")
def board_images():
    images, _ = checkerboard_views(TRUTH, n=20, seed=1)
    return images


@pytest.fixture(scope="module")
def marker_scene():
    camera, layout, T_true, images = ex.demo_scene()
    return camera, layout, T_true, images[:6]


# -- intrinsics -----------------------------------------------------------------------------
def test_intrinsics_within_half_pixel(board_images):
    res = calibrate(board_images, 9, 6, 0.025, show_progress=False)
    assert len(res.used) >= 15
    err = np.abs(np.array([res.K[0, 0] - 600.0, res.K[1, 1] - 602.0, res.K[0, 2] - 322.0, res.K[1, 2] - 241.0]))
    assert err.max() < 0.5, f"intrinsics off by {err} px"
    assert res.rms < 0.2
    assert res.dist[0] == pytest.approx(-0.08, abs=0.01) and res.dist[1] == pytest.approx(0.05, abs=0.02)
    assert "reprojection RMS" in res.report() and "1-sigma" in res.report()
    cam = res.camera("c")  # valid Camera keys
    assert cam.width == 640


def test_intrinsics_no_checkerboard():
    blank = [np.full((480, 640), 128, np.uint8)] * 4
    with pytest.raises(InputError, match=r"no checkerboard of 9x6 inner corners found.*--cols/--rows"):
        calibrate(blank, 9, 6, 0.025, show_progress=False)


def test_intrinsics_wrong_pattern_size(board_images):
    with pytest.raises(InputError, match="no checkerboard of 8x6"):
        calibrate(board_images[:3], 8, 6, 0.025, show_progress=False)
    with pytest.raises(InputError, match="at least 2x2"):
        calibrate(board_images[:3], 1, 6, 0.025, show_progress=False)


# -- extrinsics -----------------------------------------------------------------------------
def test_marker_extrinsics_within_2mm_half_degree(marker_scene):
    camera, layout, T_true, images = marker_scene
    res = ex.extrinsics_from_markers(images, layout, camera, show_progress=False)
    dt, dr = pose_error(res.T_world_cam, T_true)
    assert dt < 0.002 and dr < 0.5, f"{dt * 1000:.2f} mm, {dr:.3f} deg"
    assert len(res.frames) == len(images) and not res.dropped
    assert set(res.frames[0].ids) == set(layout.markers)


def test_marker_extrinsics_with_distortion_single_frame():
    camera, layout, T_true, _ = ex.demo_scene()
    from pointfence.calib.render import get_dictionary, marker_plane, render_planes

    cam = Camera("d", 640, 480, 575.8, 575.8, 319.5, 239.5, dist=(-0.1, 0.05, 0.0, 0.0, 0.0))
    planes = [marker_plane(get_dictionary(layout.dictionary), i, s, T) for i, (T, s) in layout.markers.items()]
    img = render_planes(cam, T_true, planes, noise_std=2.0)
    res = ex.extrinsics_from_markers([img], layout, cam, show_progress=False)
    dt, dr = pose_error(res.T_world_cam, T_true)
    assert dt < 0.002 and dr < 0.5


def test_marker_not_in_layout(marker_scene):
    camera, layout, T_true, images = marker_scene
    small = ex.MarkerLayout(layout.dictionary, {k: v for k, v in layout.markers.items() if k != 4})
    with pytest.raises(InputError, match=r"marker id\(s\) \[4\] are not in the layout.*--ignore-unknown"):
        ex.extrinsics_from_markers(images[:1], small, camera, show_progress=False)
    res = ex.extrinsics_from_markers(images[:2], small, camera, ignore_unknown=True, show_progress=False)
    assert pose_error(res.T_world_cam, T_true)[0] < 0.002


def test_no_marker_visible(marker_scene):
    camera, layout, _, _ = marker_scene
    with pytest.raises(InputError, match="no layout marker"):
        ex.extrinsics_from_markers([np.full((480, 640), 90, np.uint8)], layout, camera, show_progress=False)


def test_layout_errors(tmp_path):
    with pytest.raises(InputError, match="no \\[\\[marker\\]\\]"):
        ex.load_layout({"dictionary": "DICT_4X4_50", "size": 0.05})
    with pytest.raises(InputError, match="dictionary 'DICT_9X9'"):
        ex.load_layout({"dictionary": "DICT_9X9", "marker": [{"id": 1, "position": [0, 0, 0]}]})
    with pytest.raises(InputError, match="size"):
        ex.load_layout({"marker": [{"id": 1, "position": [0, 0, 0]}]})
    with pytest.raises(InputError, match="appears twice"):
        ex.load_layout({"size": 0.05, "marker": [{"id": 1, "position": [0, 0, 0]}, {"id": 1, "position": [1, 0, 0]}]})
    f = tmp_path / "layout.toml"
    f.write_text('dictionary = "DICT_APRILTAG_36h11"\nsize = 0.05\n[[marker]]\nid = 7\nposition = [0.1, 0.2, 0.0]\nrotation_deg = [0, 0, 90]\n')
    lay = ex.load_layout(f)
    c = lay.corners_base(7)
    assert np.allclose(c.mean(axis=0), [0.1, 0.2, 0.0]) and np.allclose(np.linalg.norm(c[0] - c[1]), 0.05)


def test_low_pass_filter():
    rng = np.random.default_rng(0)
    T0 = make_T(np.eye(3), [0.1, 0.2, 0.3])
    noisy = [perturb(T0, abs(rng.normal(0, 0.003)), abs(rng.normal(0, 0.3)), seed=i) for i in range(200)]
    lp = ex.LowPassPose(alpha=0.05)
    outs = [lp.update(T) for T in noisy]
    raw = np.mean([pose_error(T, T0)[0] for T in noisy[100:]])
    filt = np.mean([pose_error(T, T0)[0] for T in outs[100:]])
    assert filt < raw / 2, "the filter attenuates frame-to-frame noise"
    # a step is followed with time constant 1/alpha frames
    lp2 = ex.LowPassPose(alpha=0.2)
    for _ in range(30):
        lp2.update(T0)
    T1 = make_T(np.eye(3), [0.2, 0.2, 0.3])
    xs = [lp2.update(T1)[0, 3] for _ in range(5)]
    assert xs[0] == pytest.approx(0.1 + 0.2 * 0.1) and xs[-1] == pytest.approx(0.2 - 0.1 * 0.8 ** 5)
    with pytest.raises(InputError, match="alpha"):
        ex.LowPassPose(0)


def test_kabsch_and_points_file(tmp_path):
    rng = np.random.default_rng(3)
    T = perturb(make_T(np.eye(3), [0.4, -0.1, 0.8]), 0.0, 40.0, seed=2)
    P_cam = rng.uniform(-0.3, 0.3, (12, 3)) + [0, 0, 1.0]
    P_base = P_cam @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.0005, (12, 3))
    fit = ex.kabsch(P_cam, P_base)
    dt, dr = pose_error(fit.T, T)
    assert dt < 0.001 and dr < 0.1 and fit.rms < 0.0015
    f = tmp_path / "pairs.csv"
    f.write_text("x_cam,y_cam,z_cam,x_base,y_base,z_base\n" + "\n".join(",".join(f"{v:.6f}" for v in row) for row in np.hstack([P_cam, P_base])))
    a, b = ex.read_point_pairs(f)
    assert np.allclose(a, P_cam, atol=1e-6)
    with pytest.raises(InputError, match="collinear"):
        ex.kabsch([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    with pytest.raises(InputError, match="at least 3"):
        ex.kabsch([[0, 0, 0], [1, 0, 0]], [[0, 0, 0], [1, 0, 0]])


# -- multi-camera ICP -----------------------------------------------------------------------
@pytest.mark.parametrize("pair", [(20, 25), (40, 45)])
def test_icp_7scenes_rig(shared_data, pair):
    from pointfence.calib.multi import refine_pair
    from pointfence.service.sources import RecordedSource

    rec = RecordedSource(shared_data / "7scenes_kitchen_50f", loop=False)
    d0, _, T0 = rec.load(pair[0])
    d1, _, T1 = rec.load(pair[1])
    T_true = inv_T(T0) @ T1  # camera 1 in camera 0's frame, from the recorded camera-to-world poses
    T_rough = perturb(T_true, 0.02, 3.0, seed=pair[0])
    assert pose_error(T_rough, T_true)[0] == pytest.approx(0.02) and pose_error(T_rough, T_true)[1] == pytest.approx(3.0)
    res = refine_pair(d0, rec.camera, d1, rec.camera, T_rough)
    dt, dr = pose_error(res.T, T_true)
    assert dt < 0.005 and dr < 0.5, f"{dt * 1000:.2f} mm, {dr:.3f} deg"
    assert res.overlap > 0.5 and res.rms < 0.006


def test_icp_no_overlap_is_an_error():
    from pointfence.calib.multi import icp

    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, (500, 3))
    n = np.tile([0, 0, 1.0], (500, 1))
    with pytest.raises(InputError, match="too far off or the views do not overlap"):
        icp(a, a + [5.0, 0, 0], n, np.eye(4))


# -- noise ----------------------------------------------------------------------------------
def test_noise_model_within_10_percent():
    caps, cam = synthetic_captures(a=0.0, b=1.42e-3)
    fit = fit_noise(caps, cam, show_progress=False)
    assert fit.b == pytest.approx(1.42e-3, rel=0.10)
    for z in (0.6, 1.5, 2.5):
        assert fit.model.sigma_z(z) == pytest.approx(1.42e-3 * z ** 2, rel=0.10)
    caps, cam = synthetic_captures(a=0.001, b=2.0e-3, distances=(0.5, 1.0, 1.5, 2.0), seed=5)
    fit = fit_noise(caps, cam, show_progress=False)
    for z in (0.5, 1.0, 2.0):
        assert fit.model.sigma_z(z) == pytest.approx(0.001 + 2e-3 * z ** 2, rel=0.10)
    assert "residual" in fit.report()


def test_noise_degenerate_inputs():
    caps, cam = synthetic_captures(distances=(1.0,), frames=1)
    with pytest.raises(InputError, match="2 or more distances"):
        fit_noise(caps, cam, show_progress=False)
    empty = np.zeros((cam.height, cam.width), np.uint16)
    with pytest.raises(InputError, match="degenerate plane fit"):
        plane_residuals(empty, cam)
    line = np.zeros((cam.height, cam.width), np.uint16)
    line[:, cam.width // 2] = 1000  # one column: the points lie on a line
    line[:, cam.width // 2 + 1] = 1000
    with pytest.raises(InputError, match="degenerate plane fit"):
        plane_residuals(line, cam, roi=1.0)


# -- output and CLI -------------------------------------------------------------------------
def test_snippet_and_config_update(tmp_path):
    from pointfence.service import config

    T = perturb(np.eye(4), 0.1, 20.0)
    snip = camera_snippet("kin", {"fx": 575.8, "fy": 575.8, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480,
                                  "dist": (0.1, 0, 0, 0, 0), "T_world_cam": T, "noise": {"a": 0.0, "b": 1.5e-3}},
                          "openni2:any")
    f = tmp_path / "snip.toml"
    f.write_text(snip)
    cfg = config.load(f)
    cam = cfg.cameras[0].camera
    assert cam.fx == 575.8 and np.allclose(cam.T_world_cam, T) and cam.noise.b == 1.5e-3 and cam.dist[0] == 0.1
    scene = tmp_path / "scene.toml"
    scene.write_text(textwrap.dedent("""
        backend = "numpy"
        [workspace]
        min = [-0.5, -0.5, -0.5]
        max = [0.5, 0.5, 0.5]
        [[camera]]
        name = "a"
        source = "synthetic:plane"
    """))
    update_config(scene, "a", {"noise": {"a": 0.0, "b": 2e-3}})
    update_config(scene, "b", {"fx": 500.0, "fy": 500.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240},
                  source="synthetic:sphere")
    cfg = config.load(scene)
    assert [c.camera.name for c in cfg.cameras] == ["a", "b"] and cfg.backend == "numpy"
    assert cfg.cameras[0].camera.noise.b == 2e-3 and cfg.cameras[1].camera.fx == 500.0
    assert (tmp_path / "scene.toml.bak").exists()
    with pytest.raises(InputError, match="pass --source"):
        update_config(scene, "c", {"fx": 1.0})


def test_progress_lines():
    out = io.StringIO()
    assert list(progress(range(20), "step", stream=out)) == list(range(20))
    text = out.getvalue()
    assert "step: 2/20" in text and "step: 20/20 done in" in text


def test_cli_table_and_runs(tmp_path, capsys):
    from pointfence.calib import cli

    assert set(cli.SUBCOMMANDS) >= {"intrinsics", "extrinsics", "multi", "noise"}
    out = tmp_path / "noise.toml"
    assert cli.main(["noise", "--demo", "--name", "k", "--source", "synthetic:plane", "--out", str(out)]) == 0
    from pointfence.service import config

    assert config.load(out).cameras[0].camera.noise.b == pytest.approx(1.42e-3, rel=0.1)
    pairs = tmp_path / "p.txt"
    pairs.write_text("0 0 1  0 0 1\n1 0 1  1 0 1\n0 1 1  0 1 1\n")
    assert cli.main(["extrinsics", "--points", str(pairs)]) == 0
    assert "RMS residual 0.00 mm" in capsys.readouterr().out
    assert cli.main(["intrinsics", str(tmp_path / "none.png")]) == 1
    assert "not found" in capsys.readouterr().err


def test_cli_noise_writes_a_disparity_cameras_depth_step(tmp_path, capsys):
    """Plane captures from a Kinect-like camera whose depths come on levels of 1/z (a 1/8-pixel
    disparity of 580 px x 7.5 cm) written as 16-bit PNGs: ``calib noise`` reports the levels and
    writes ``depth_step_inv`` within 1 % of the camera's, which the scene file then loads."""
    import cv2

    from pointfence.calib import cli
    from pointfence.service.depth_steps import DepthSteps

    kinect = DepthSteps(1e-3, 1.0 / (8 * 580.0 * 0.075), 0.0004)
    caps, _ = synthetic_captures(distances=(1.0, 1.6, 2.2, 2.8), frames=1)
    dirs = []
    for i, cap in enumerate(caps):
        d = tmp_path / f"plane{i}"
        d.mkdir()
        raw = np.repeat(np.repeat(cap[0], 2, axis=0), 2, axis=1)      # the CLI's default 640 x 480 camera
        img = raw.astype(np.float64) * 1e-3
        q = np.where(raw > 0, kinect.quantize(np.where(img > 0, img, 1.0)), 0).astype(np.uint16)
        assert cv2.imwrite(str(d / "0.png"), q)
        dirs.append(str(d))
    out = tmp_path / "noise.toml"
    assert cli.main(["noise", *dirs, "--name", "k", "--source", "synthetic:plane", "--out", str(out)]) == 0
    assert "disparity levels" in capsys.readouterr().out
    from pointfence.service import config

    cam = config.load(out).cameras[0].camera
    assert cam.depth_step_inv == pytest.approx(kinect.inv_step, rel=0.01)
