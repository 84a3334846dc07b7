"""Chapter 6 on the real two-camera rig (service/real_rig.py, dynamic_real_rig.py,
dynamic_real_noise.py) and architecture III's slip lift (service/teleop.py, tick core)."""
from __future__ import annotations

import numpy as np
import pytest

from pointfence.kernels.camera import Camera, NoiseModel
from pointfence.kernels.errors import InputError
from pointfence.kernels.selffilter import SelfFilter
from pointfence.service import dynamic_real_noise as drn
from pointfence.service import dynamic_real_rig as drr
from pointfence.service.real_rig import cloud, load_rig, render_tool, tool_capsules
from pointfence.service.teleop import Teleop


@pytest.fixture
def kitchen(shared_data):
    """The kitchen rig (loaded once per process: ``dynamic_real_rig.rig`` caches it)."""
    return drr.rig(1, shared_data)


# --- the shadow --------------------------------------------------------------------------------------

def test_tool_render_is_exact_for_a_capsule_in_front_of_a_wall():
    """A capsule 1 m in front of a wall 2 m away: the pixels whose ray meets it read its depth
    (to the millimetre), the others keep the wall."""
    cam = Camera("c", 64, 48, 50.0, 50.0, 32.0, 24.0)
    wall = np.full((48, 64), 2000, np.uint16)
    cap = tool_capsules([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], ((-0.1, 0.1, 0.05),))
    out = render_tool(cam, wall, np.eye(4), cap)
    assert out[24, 32] == 950  # the ray through the centre meets the capsule's near side at z = 0.95 m
    assert out[0, 0] == 2000 and out[24, 5] == 2000  # rays that miss it see the wall
    hit = out < 2000
    assert 0.01 < hit.mean() < 0.3
    # every hit pixel's point is on the capsule's surface
    pts = cloud(cam, np.where(hit, out, 0).astype(np.uint16), np.eye(4))
    assert np.all(np.abs(cap[0].distance(pts)) < 0.002)


def test_shadow_hides_the_protected_point_from_camera_a_only(kitchen):
    """The tool at contact, along camera A's line of sight: after rendering and the self-filter,
    A has no point within the 1 cm fixture radius of the protected point; B (not shaded) has."""
    s = kitchen.site
    tip = s.point + 0.01 * s.view / (s.view @ s.normal)
    caps = tool_capsules(tip, s.view, drr.TOOL)
    a, b = kitchen.a, kitchen.b
    filt = SelfFilter([a.camera, b.camera])
    fa = filt.apply([a.frame(0, 0.0, render_tool(a.camera, a.depths[0], a.poses[0], caps))], caps)[0]
    near = lambda p: np.sum(np.linalg.norm(p - s.point, axis=1) < 0.01)  # noqa: E731
    assert near(a.points(0)) >= 8                                       # A sees it without the tool
    assert near(cloud(a.camera, fa.depth, a.poses[0])) == 0           # the tool hides it from A
    assert near(b.points(0)) >= 8                                       # B sees it


def test_one_camera_lets_the_tool_in_two_cameras_hold(kitchen):
    kw = dict(r_f=0.01, direction=-kitchen.site.view, start_out=0.015, push=0.02, speed=0.2, max_robot_speed=0.2,
              hold=0.1)
    one = drr.arch3_run(kitchen, cameras=1, **kw)
    two = drr.arch3_run(kitchen, cameras=2, **kw)
    assert one.robot_mean > 0.01          # through the whole fixture: the tool reached the surface
    assert two.robot_mean <= 0.001        # held within 1 mm of the 1 cm region around the mean surface
    assert two.proxy_mean <= 0.002        # the proxy, pushed in at 0.2 m/s, within 2 mm


def test_the_dequantized_truth_lies_within_half_a_step_of_the_measured_cloud(kitchen):
    """The cameras' dequantised points (the true surface of ``proxy_deq``) are the measured ones
    moved along their rays by at most half of the Kinect's step there (18 mm at 2.5 m), and by
    a few mm in the median: a smooth surface through the staircase, not another estimate."""
    raw = kitchen.a.points(0)
    deq = kitchen.a.points(0, dequantized=True)
    assert raw.shape == deq.shape
    from pointfence.service.depth_steps import DepthSteps

    d = kitchen.a.depths[0]
    steps = DepthSteps.fit(np.where(d < kitchen.a.camera.max_code, d, 0), 1e-3)
    cam_t = kitchen.a.poses[0][:3, 3]
    rng_raw, rng_deq = np.linalg.norm(raw - cam_t, axis=1), np.linalg.norm(deq - cam_t, axis=1)
    moved = np.abs(rng_deq - rng_raw)
    assert np.all(moved <= 0.5 * steps.step_at(rng_raw) * 1.05 + 1e-6)
    assert 0.5e-3 < np.median(moved) < 5e-3


def test_near_reading_holds_the_shadowed_tool_against_every_true_surface(kitchen):
    """Two cameras, the tool's shadow in A, pushed in at 0.2 m/s: with each Kinect's readings at
    the near end of their steps (``near_reading``, the steps fitted from the frames) the robot
    stays within 1 mm of the 1 cm region around the fused cloud as measured, and out of it
    around the denoised and the dequantised surfaces; as read, the dequantised one is entered."""
    kw = dict(r_f=0.01, direction=-kitchen.site.view, start_out=0.015, push=0.02, speed=0.2, max_robot_speed=0.2,
              hold=0.1)
    assert kitchen.a.steps().disparity and kitchen.b.steps().disparity
    as_read = drr.arch3_run(kitchen, cameras=2, **kw)
    near = drr.arch3_run(kitchen, cameras=2, near_reading=True, **kw)
    assert as_read.robot_deq > 0.0005
    assert near.robot_raw <= 0.001 and near.robot_mean == 0.0 and near.robot_deq == 0.0


def test_push_direction_along_the_surface_is_refused(kitchen):
    s = kitchen.site
    along = np.cross(s.normal, [0.0, 0.0, 1.0])
    with pytest.raises(InputError, match="from its normal"):
        drr.arch3_run(kitchen, direction=along, tool=None)


def test_rig_errors_name_the_problem(shared_data, tmp_path):
    with pytest.raises(InputError, match="window"):
        load_rig(window=40, data=shared_data)
    with pytest.raises(InputError, match="not found"):
        load_rig(data=tmp_path)


# --- the noise model ---------------------------------------------------------------------------------

def _slanted_planes(noise: NoiseModel, seed: int = 0):
    """Depth images of planes tilted 30 degrees at 0.8-3 m with noise of ``noise``, in mm."""
    cam = Camera("c", 320, 240, 290.0, 290.0, 160.0, 120.0)
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:240, 0:320]
    out = []
    for z0 in np.linspace(0.8, 3.0, 12):
        # plane z = z0 + 0.5 y in camera coordinates: 1/z linear in the pixel row
        yn = (v - cam.cy) / cam.fy
        z = z0 / (1 - 0.5 * yn)
        zn = z + rng.standard_normal(z.shape) * noise.sigma_z(z)
        out.append((np.round(zn * 1000).astype(np.uint16), cam))
    return out


def test_noise_fit_recovers_a_known_sigma():
    true = NoiseModel(0.0005, 0.0015)
    fit = drn.fit_noise(_slanted_planes(true))
    for z in (1.0, 2.0, 2.8):
        assert fit.model().sigma_z(z) == pytest.approx(true.sigma_z(z), rel=0.08)


def test_noise_fit_refuses_too_little_data():
    cam = Camera("c", 32, 24, 30.0, 30.0, 16.0, 12.0)
    with pytest.raises(InputError, match="depth bin"):
        drn.fit_noise([(np.zeros((24, 32), np.uint16), cam)])


def test_kitchen_noise_is_kinect_like(shared_data):
    fit = drn.fit_noise(drn.recording_frames("7scenes_kitchen_50f", data=shared_data, every=25))
    kinect = drn.kinect_model()
    for z in (1.5, 2.5):  # within a factor of two of the built-in model, growing with depth
        assert 0.5 < fit.model().sigma_z(z) / kinect.sigma_z(z) < 2.0
    assert fit.model().sigma_z(2.5) > 2 * fit.model().sigma_z(1.2)
    assert fit.steps.disparity and "disparity" in fit.summary()["depth_steps"]


def test_modelled_frames_sit_on_the_cameras_levels_with_the_fitted_sigma():
    """A flat wall at 2.5 m modelled with a Kinect's levels: every depth on a level, the error's
    spread the model's sigma_z (quantisation and the noise beyond it together, within 15 %); in
    whole codes (no steps) the same sigma."""
    from pointfence.service.depth_steps import DepthSteps

    steps = DepthSteps(1e-3, 1.0 / (8 * 580.0 * 0.075), 0.0004)
    cam = Camera("c", 160, 120, 150.0, 150.0, 80.0, 60.0)
    truth = np.full((120, 160), 2.5) + np.linspace(0, 0.05, 160)[None, :]   # a gentle slope across the steps
    noise = NoiseModel(0.0006, 0.001)
    rng = np.random.default_rng(3)
    for st in (steps, None):
        d = drn._noisy_frame(truth, cam, noise, rng, st).astype(np.float64)
        if st is not None:
            assert np.array_equal(st.quantize(d * 1e-3), d)
        err = d * 1e-3 - truth
        assert np.std(err) == pytest.approx(float(np.mean(noise.sigma_z(truth))), rel=0.15)


def test_summary_gives_the_worst_margin_in_sigmas():
    rows = [dict(noise_scale=1.0, adaptive=a, safety_penetration_mm=p, closest_approach_mm=c, sigma_z_mm=s,
                 submittance_gap_mm=0.0)
            for a, p, c, s in ((False, 0.0, 21.0, 2.0), (False, 0.0, 25.0, 8.0), (True, 3.0, 17.0, 2.0),
                               (True, 0.0, 32.0, 8.0))]
    out = drn.summarize(rows)["noise_x1"]
    assert out["fixed"]["worst_margin_sigmas"] == pytest.approx(25.0 / 8.0, abs=0.01)
    assert out["adaptive"]["worst_margin_sigmas"] == pytest.approx(4.0, abs=0.01)
    assert out["adaptive"]["worst_penetration_mm"] == 3.0


# --- the slip lift ---------------------------------------------------------------------------------

def _slip(lift: bool):
    """A proxy slips 2 cm sideways across a bump of a 1 cm fixture (three protected points); the
    rate-limited command follows it. Returns the command's smallest clearance to the points, m,
    and where it ends."""
    r = 0.01
    pts = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.01, 0.0, 0.003]])
    tp = Teleop(1, scale=1.0, max_robot_speed=0.5, dt=1e-3, architecture="III", slip_lift=r if lift else 0.0)
    normals = np.array([[0.0, 0.0, 1.0]], np.float32)
    tp.bind_normals(normals)
    tp.start(np.zeros((1, 3)), np.array([[0.0, 0.0, r]]))
    proxy = np.array([[0.02, 0.0, r]], np.float32)
    worst = np.inf
    for _ in range(200):
        tp.command_goal(proxy, True)
        tp.limit_command(np.ones(1, bool))
        worst = min(worst, float(np.linalg.norm(pts - tp.cmd[0], axis=1).min()))
    return worst, tp.cmd[0].copy()


def test_slip_lift_keeps_the_command_out_of_the_bump():
    bare, end_bare = _slip(False)
    lifted, end_lifted = _slip(True)
    assert bare < 0.0075                          # the straight path cuts 3 mm into the bump's sphere
    assert lifted >= 0.01 - 1e-6                  # lifted over it
    assert np.allclose(end_lifted, [0.02, 0.0, 0.01], atol=1e-6)  # and landed on the proxy
    assert np.allclose(end_bare, end_lifted, atol=1e-6)


def test_slip_lift_is_inert_while_the_command_keeps_up_and_without_normals():
    tp = Teleop(1, scale=1.0, max_robot_speed=0.5, architecture="III", slip_lift=0.01)
    tp.start(np.zeros((1, 3)), np.zeros((1, 3)))
    proxy = np.array([[0.003, 0.0, 0.0]], np.float32)
    assert np.allclose(tp.command_goal(proxy, True)[0], proxy[0], atol=1e-7)  # no normals bound: no lift
    normals = np.zeros((1, 3), np.float32)
    tp.bind_normals(normals)
    assert np.allclose(tp.command_goal(proxy, True)[0], proxy[0], atol=1e-7)  # no surface estimate: no lift
    normals[0] = (0.0, 0.0, 1.0)
    g = tp.command_goal(proxy, True)[0]
    assert g[2] == pytest.approx(0.003 ** 2 / 0.01, rel=1e-5)               # L^2 / r across the normal
    assert np.allclose(tp.command_goal(proxy, False)[0], tp.X_m[0])          # haptics off: X_m, no lift
    tp.set_architecture("I")
    assert np.allclose(tp.command_goal(proxy, True)[0], tp.X_m[0])           # only architecture III


def test_slip_lift_rejects_bad_settings():
    with pytest.raises(InputError, match="slip_lift"):
        Teleop(1, slip_lift=-0.01)
    with pytest.raises(InputError, match="slip_lift"):
        Teleop(1, slip_lift=float("nan"))
    tp = Teleop(2)
    with pytest.raises(InputError, match=r"\(2, 3\)"):
        tp.bind_normals(np.zeros((1, 3), np.float32))
    with pytest.raises(TypeError, match="float32"):
        tp.bind_normals(np.zeros((2, 3)))


def test_slip_lift_holds_the_robot_on_the_real_rig(kitchen):
    """The master pushing along camera A's line of sight, 69 degrees from the surface normal:
    the proxy slips over the fused noisy cloud and the robot, commanded straight at it, cuts
    into the 1 cm fixture; the slip lift keeps it out."""
    kw = dict(r_f=0.01, tool=None, direction=-kitchen.site.view, speed=0.1, max_robot_speed=0.5, hold=0.0)
    bare = drr.arch3_run(kitchen, **kw)
    lifted = drr.arch3_run(kitchen, slip_lift=True, **kw)
    assert bare.proxy_raw < 0.0005 and lifted.proxy_raw < 0.0005
    assert bare.robot_raw > 0.001
    assert lifted.robot_raw < 0.0005


# --- the figures -------------------------------------------------------------------------------------

def test_rig_figures_quick(shared_data):
    fig = drr.rig_figures(quick=True, data=shared_data)
    assert fig["rig"]["baseline_m"] == pytest.approx(0.2085, abs=1e-3)
    occ = fig["occlusion"]
    assert occ["one_camera"]["robot_penetration_mean_surface_mm"] > 5.0
    assert occ["two_cameras"]["robot_penetration_mean_surface_mm"] <= 1.0
    push = fig["push"]["rigid_rig"]
    assert push["slip_lift"]["robot_penetration_mm"] < push["command_as_is"]["robot_penetration_mm"]
    fitted = fig["noise_model"]["fitted_7scenes_kinect_v1"]
    assert fitted["b_per_m"] > 0 and fig["noise_model"]["built_in_kinect"]["b_per_m"] == pytest.approx(1.42e-3)
    rows = fig["radius_study"]
    assert {r["adaptive"] for r in rows} == {False, True}
    assert all(r["radius_mean_mm"] == pytest.approx(20.0, abs=0.05) for r in rows)  # equal mean radius
    assert set(fig["radius_summary"]["noise_x1"]) == {"fixed", "adaptive"}
