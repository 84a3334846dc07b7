"""The depth levels of a recording (``service/depth_steps.py``, issue 23): a disparity camera's
steps found from one image's distinct depths, a camera in whole codes left as it is, and the
real-frame evaluation's camera re-quantising onto the recording's levels."""
import numpy as np
import pytest

from pointfence.service import dynamic_real as dr
from pointfence.service.depth_steps import DepthSteps, dequantize
from pointfence.service.dynamic_real_frames import Motion, deproject

KINECT = 1.0 / (8 * 580.0 * 0.075)     # 1/z step (1/m) of a 1/8-px disparity step, f 580 px, baseline 7.5 cm


def _needs(scene):
    return pytest.mark.skipif(not (dr.DATA / scene).exists(), reason=f"../shared/data/{scene} not present")


def _kinect_plane(offset=0.0011, seed=0):
    """A slanted plane 1.5-2 m away as a Kinect v1 records it: 1/z on its disparity levels,
    stored in whole millimetres (treads of 3-10 pixels); with a few holes."""
    v, u = np.mgrid[0:240, 0:320].astype(np.float64)
    z = 1.5 + 0.001 * u + 0.0005 * v
    k = np.rint((1.0 / z - offset) / KINECT)
    codes = np.rint(1.0 / (offset + KINECT * k) / 1e-3)
    codes[np.random.default_rng(seed).random(codes.shape) < 0.05] = 0
    return codes.astype(np.uint16), z


def test_fit_finds_a_kinects_disparity_levels():
    """The fitted comb matches the camera's to 0.5 % of its step, and re-quantising the recorded
    depths gives the recording back (each code on its level; 97 %: a code at a level's rounding
    boundary may go either way under the fitted comb)."""
    codes, _ = _kinect_plane()
    s = DepthSteps.fit(codes, 1e-3)
    assert s.disparity
    assert abs(s.inv_step - KINECT) < 0.005 * KINECT, s
    d = codes[codes > 0].astype(np.float64)
    assert np.mean(s.quantize(d * 1e-3) == d) > 0.97
    # the local step grows as z^2: 9.3 mm at 1.8 m, 1 mm (the code) close up
    assert abs(float(s.step_at(1.8)) - KINECT * 1.8 ** 2) < 1e-4
    assert float(s.step_at(0.3)) == 1e-3


def test_depths_in_whole_codes_stay_codes():
    """A close-range plane in 1 mm codes, and a sparse far background of random whole-millimetre
    depths (gaps of several codes by chance, no comb): both fit as plain codes."""
    v, u = np.mgrid[0:240, 0:320].astype(np.float64)
    near = np.rint((0.4 + 0.0007 * u + 0.0003 * v) / 1e-3).astype(np.uint16)
    assert not DepthSteps.fit(near, 1e-3).disparity
    rng = np.random.default_rng(1)
    far = np.zeros((240, 320), np.uint16)
    far.flat[rng.choice(far.size, 400, replace=False)] = rng.integers(1000, 3000, 400)
    assert not DepthSteps.fit(far, 1e-3).disparity
    assert not DepthSteps.fit(np.zeros((10, 10), np.uint16), 1e-3).disparity


@_needs("7scenes_kitchen_50f")
@_needs("apc_shelfbin_50f")
def test_the_real_recordings_levels():
    """7-Scenes (Kinect v1) comes in disparity steps of the Kinect's 1/8 pixel (within 2 %);
    apc in 1 mm codes."""
    k = dr.real_surface("7scenes_kitchen_50f")
    assert k.steps.disparity and abs(k.steps.inv_step - KINECT) < 0.02 * KINECT, k.steps
    assert not dr.real_surface("apc_shelfbin_50f").steps.disparity


def test_dequantize_smooths_a_disparity_staircase_within_half_its_step():
    """The Kinect plane's staircase (treads several pixels wide): with the passes of a disparity
    recording the dequantised surface stays within half the local step of every recorded depth
    and is at least three times as close to the plane as one pass leaves it."""
    codes, plane = _kinect_plane()
    s = DepthSteps.fit(codes, 1e-3)
    z = codes * 1e-3
    ok = z > 0
    step = s.step_at(z)
    one = dequantize(z, step)
    many = dequantize(z, step, passes=16)
    assert np.all(np.abs(many - z)[ok] <= 0.5 * step[ok])
    inner = ok.copy()
    inner[:12], inner[-12:], inner[:, :12], inner[:, -12:] = False, False, False, False
    err_one = np.sqrt(np.mean((one[inner] - plane[inner]) ** 2))
    err_many = np.sqrt(np.mean((many[inner] - plane[inner]) ** 2))
    assert err_many < err_one / 3, (err_many, err_one)


@_needs("7scenes_kitchen_50f")
def test_the_moved_kinect_frame_keeps_the_cameras_levels():
    """7-Scenes moved toward the camera at 0.1 m/s: every depth of every frame lies on one of the
    recording's disparity levels (the camera's steps stay at fixed depths while the surface moves
    through them), and near the contact each lies within half its step of the true surface along
    its ray. Moving the recorded staircase rigidly instead puts the levels at depths the camera
    cannot report."""
    s = dr.real_surface("7scenes_kitchen_50f")
    a = s.anchor()
    m = Motion("toward", 0.1, tuple(a))
    for k in (1, 3, 4):
        f = s.render(m, k / 30, k)
        d = f.depth[f.depth > 0].astype(np.float64)
        assert np.array_equal(s.steps.quantize(d * 1e-3), d)
    cam = s.cam
    z = f.depth.astype(np.float64) * cam.depth_scale
    v, u = np.nonzero(z > 0)
    pts = deproject(z[v, u], cam, u.astype(float), v.astype(float))
    R, c = m.pose(4 / 30)
    near = np.linalg.norm(pts - (R @ a + c), axis=1) < 0.03
    assert near.sum() > 100
    d_ray = np.abs(s.distance(m, pts[near], 4 / 30))
    assert np.all(d_ray <= 0.5 * s.steps.step_at(pts[near, 2]) + 0.6e-3)
    # the rigidly moved recording: 3.3 mm per frame off the levels
    moved = np.rint((s.depth_m[s.depth_m > 0] - 0.1 * 4 / 30) / 1e-3)
    assert np.mean(s.steps.quantize(moved * 1e-3) == moved) < 0.8


@_needs("7scenes_kitchen_50f")
def test_near_reading_keeps_the_proxy_out_of_the_kinects_steps():
    """7-Scenes pushed at 0.1 m/s toward the tool, 1 cm fixture, prediction on: the proxy rests
    on the Kinect's levels, up to half a 9 mm step behind the true surface, and enters the
    fixture's region by more than 0.5 mm; with ``near_reading`` (the fitted step on the camera)
    the readings stand at the near end of their steps and it stays within 0.2 mm."""
    s = dr.real_surface("7scenes_kitchen_50f")
    assert s.cam.depth_step_inv == s.steps.inv_step > 0
    m = Motion("toward", 0.1, tuple(s.anchor()))
    as_read = dr.run_case(s, m, 0.1, True, r_f=0.01, master="push")
    near = dr.run_case(s, m, 0.1, True, r_f=0.01, master="push", near_reading=True)
    assert as_read.proxy_penetration > 0.5e-3
    assert near.proxy_penetration < 0.2e-3 and near.robot_penetration < 0.2e-3
