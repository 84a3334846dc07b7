"""Chapter 6 on real depth frames (issue 23): real frames moved at known speeds reproduce their
true surface, the penetration measure finds known penetrations, the motion estimator follows
the true motion of a real frame, cells it cannot measure are handled conservatively, and
`bench dynamic --real --quick --json` runs."""
import json
import subprocess
import sys

import numpy as np
import pytest

from pointfence.kernels import InputError
from pointfence.kernels.grid import Grid
from pointfence.kernels.motion import (CELL_MEASURED, CELL_NONE, CELL_PROPAGATED, MotionEstimator, MotionModel,
                                       cell_moments)
from pointfence.service import dynamic_real as dr
from pointfence.kernels.camera import Camera
from pointfence.service.dynamic_real_frames import Motion, MovingRealFrame, deproject
from pointfence.service.dynamic_real_study import estimator_run

APC = dr.DATA / "apc_shelfbin_50f"
needs_data = pytest.mark.skipif(not APC.exists(), reason="../shared/data/apc_shelfbin_50f not present")


@pytest.fixture(scope="module")
def apc():
    return dr.real_surface("apc_shelfbin_50f")


def _cloud(frame, cam):
    z = frame.depth.astype(np.float64) * cam.depth_scale
    v, u = np.nonzero(z > 0)
    return deproject(z[v, u], cam, u.astype(float), v.astype(float))


@needs_data
@pytest.mark.parametrize("kind", ["toward", "sideways", "rocking"])
def test_moved_real_frame_shows_the_known_surface(apc, kind):
    """The frame rendered at t lies on the true surface at t (within the 1 mm depth codes and
    the half-pixel re-projection) and, for the motions that move the anchor's patch along its
    normal, off the surface at t = 0 by about the distance travelled."""
    a = apc.anchor()
    m = Motion(kind, 0.3, tuple(a))
    t = 0.1  # 3 cm of travel
    pts = _cloud(apc.render(m, t, 3), apc.cam)
    R, c = m.pose(t)
    near = np.linalg.norm(pts - (R @ a + c), axis=1) < 0.03
    assert near.sum() > 200
    now = np.abs(apc.distance(m, pts[near], t))
    then = np.abs(apc.distance(m, pts[near], 0.0))
    assert np.median(now) < 0.5e-3, np.median(now)
    if kind != "sideways":
        assert np.median(then) > 5e-3, np.median(then)


def _tilted_plane_frame():
    """A MovingRealFrame of the plane z = 0.4 + 0.2 x (m, camera frame) in 0.1 mm depth codes,
    with a grid of holes like apc's, and the plane's signed distance function (toward the
    camera positive)."""
    cam = Camera("t", 320, 240, 300.0, 300.0, 160.0, 120.0, depth_scale=1e-4)
    v, u = np.mgrid[0:240, 0:320].astype(np.float64)
    z = 0.4 / (1 - 0.2 * (u - 160.0) / 300.0)
    depth = np.rint(z / 1e-4).astype(np.uint16)
    depth[::4, :] = 0
    depth[:, ::3] = 0
    n = np.array([-0.2, 0.0, 1.0]) / np.sqrt(1.04)

    def sdf(q):
        return -(np.asarray(q) @ n - 0.4 / np.sqrt(1.04))

    return MovingRealFrame(depth, cam, name="tilted"), sdf, n


@pytest.mark.parametrize("kind", ["toward", "sideways", "rocking"])
def test_penetration_measure_finds_a_known_penetration(kind):
    """Points a known distance in front of / behind a plane seen as a depth image with holes,
    at t = 0 and moved with the scene to t: the measure gives that signed distance (to 0.2 mm:
    the 0.1 mm codes and the half-pixel sampling, 0.7 mm pixels), negative behind the surface, so a proxy d
    in front of a 1 cm fixture's surface reads r_f - d of penetration."""
    frame, sdf, n = _tilted_plane_frame()
    a = frame.anchor()
    assert abs(sdf(a)) < 0.5e-4    # the true surface lies within half a code of the recorded depths
    m = Motion(kind, 0.5, tuple(a))
    for t in (0.0, 0.05):
        R, c = m.pose(t)
        for d in (0.004, 0.012, -0.003, 0.0):
            q = R @ (a - n * d) + c
            got = float(frame.distance(m, q[None], t)[0])
            assert abs(got - d) < 2e-4, (t, d, got)
            if t == 0:
                assert abs(sdf(q) - sdf(a) - d) < 1e-9


@needs_data
def test_estimator_follows_a_real_frame_moved_at_known_speed(apc):
    """apc frame toward the camera at 0.3 m/s (1 cm per frame): near the contact point most
    points sit in measured cells, and their velocity carries them over one frame to within a
    small fraction of the frame's motion of the true surface."""
    r = estimator_run(apc, "toward", 0.3)
    print("\nestimator, apc toward 0.3 m/s:", r)
    assert r["snapshots"] >= 2
    assert r["measured"] > 0.8
    assert r["static_mm"] > 4.0
    assert r["predicted_mm"] < 0.25 * r["static_mm"]


def _patch_moments(grid, z_of_y, hole=None):
    """Cell moments of a dense patch over x, y in [-9, 9) cm at height ``z_of_y(y)`` (m),
    without the points with x in ``hole`` ((x0, x1), m)."""
    X, Y = np.meshgrid(np.arange(-0.09, 0.09, 0.002), np.arange(-0.09, 0.09, 0.002))
    p = np.stack([X.ravel(), Y.ravel(), z_of_y(Y.ravel())], axis=1)
    if hole is not None:
        p = p[~((p[:, 0] >= hole[0]) & (p[:, 0] < hole[1]))]
    ijk = np.floor((p - np.asarray(grid.origin)) / grid.h).astype(np.int64)
    nx, ny, nz = grid.dims
    cell = (ijk[:, 2] * ny + ijk[:, 1]) * nx + ijk[:, 0]
    order = np.argsort(cell, kind="stable")
    start = np.searchsorted(cell[order], np.arange(nx * ny * nz + 1))
    pts = np.concatenate([p[order], np.zeros((len(p), 1))], axis=1).astype(np.float32)
    return cell_moments(pts, start.astype(np.int32), grid)


#: motion cells = hash cells of 2.5 cm; x cell 4 is [0, 2.5 cm), cell 3 [-2.5, 0) cm
GRID = Grid(origin=(-0.1, -0.1, -0.1), h=0.025, dims=(8, 8, 8))
#: cell 3 emptied, a sliver of cell 4 left: cell 4's blocks lose about half their points
HOLE = (-0.025, 0.021)


def _two_snapshots(model, before, after):
    """(velocities per cell, state per cell (-1 where ``after`` has no point), x index and y
    index per cell, summary) after snapshots ``before`` and ``after`` (moments) 1/30 s apart."""
    est = MotionEstimator(model, GRID)
    assert est.update(before, 0.0) == (None, 0.0)
    v, _ = est.update(after, 1 / 30)
    c = np.arange(int(np.prod(GRID.dims)))
    state = np.where(after[:, 0] > 0, est.confidence_of(c).astype(int), -1)
    return v, state, c % GRID.dims[0], (c // GRID.dims[0]) % GRID.dims[1], est.summary()


@pytest.mark.parametrize("min_neighbours", [3, 0])
def test_a_cell_that_lost_its_points_takes_its_coherent_neighbours_velocity(min_neighbours):
    """A patch rising 9 mm per frame (0.27 m/s); in the new snapshot a hole has emptied cell
    column 3 and most of column 4: column 4's block counts disagree, so it is not measured.
    With propagation it takes the velocity its measured neighbours (column 5) agree on (state
    PROPAGATED); without (min_neighbours 0) it gets no prediction (0, state NONE)."""
    model = MotionModel(enabled=True, capture=0.025, min_neighbours=min_neighbours)
    v, state, x, y, summary = _two_snapshots(model, _patch_moments(GRID, lambda y: np.full(y.shape, 0.01)),
                                             _patch_moments(GRID, lambda y: np.full(y.shape, 0.019), HOLE))
    measured = state == CELL_MEASURED
    assert measured.any() and np.allclose(v[measured, 2], 0.27, atol=0.01)
    assert summary["cells_measured"] == np.count_nonzero(measured)
    assert abs(summary["speed_median_mps"] - 0.27) < 0.01
    lost = (x == 4) & ~measured & (np.abs(v).sum(1) > 0) if min_neighbours else (x == 4) & (state == CELL_NONE)
    assert np.count_nonzero(lost) >= 4, "the sliver column's cells should lose their estimate"
    if min_neighbours:
        prop = state == CELL_PROPAGATED
        assert np.count_nonzero(prop) == summary["cells_propagated"] and np.all(x[prop] == 4)
        assert np.allclose(v[prop, 2], 0.27, atol=0.01)
    else:
        assert summary["cells_propagated"] == 0 and summary["cells_unknown"] >= 4
        assert np.all(v[state == CELL_NONE] == 0)


def test_an_unknown_cell_between_disagreeing_neighbours_gets_no_prediction():
    """The same hole, but the patch folds: y < 0 rises and y >= 0 sinks (0.27 m/s). The sliver
    cells far from the fold take their neighbours' agreed velocity; those beside it, whose
    measured neighbours disagree, predict nothing (velocity 0): a fixture that does not try,
    never a mixture of two motions."""
    def fold(y):
        return np.where(y < 0, 0.019, 0.001)

    v, state, x, y, summary = _two_snapshots(MotionModel(enabled=True, capture=0.025),
                                             _patch_moments(GRID, lambda y: np.full(y.shape, 0.01)),
                                             _patch_moments(GRID, fold, HOLE))
    col = (x == 4) & (state != CELL_MEASURED) & (state >= 0)
    prop = col & (state == CELL_PROPAGATED)
    none = col & (state == CELL_NONE) & (np.abs(v).sum(1) == 0)
    assert np.count_nonzero(prop) >= 2 and np.count_nonzero(none) >= 1, (state[x == 4], v[x == 4, 2])
    assert np.all(np.abs(np.abs(v[prop, 2]) - 0.27) < 0.02), v[prop, 2]
    # beside the fold at y = 0 (its blocks reach cells 2..5 of y) or at the patch's ends (y cells
    # 0 and 7: two measured neighbours, fewer than min_neighbours)
    assert set(y[none]) <= {0, 2, 3, 4, 5, 7} and {3, 4} <= set(y[none]), y[none]
    assert set(y[prop]) <= {1, 6}, y[prop]
    assert np.all(v[state == CELL_NONE] == 0) and summary["cells_unknown"] == np.count_nonzero(state == CELL_NONE)


def test_motion_model_refuses_bad_propagation_settings():
    with pytest.raises(InputError):
        MotionModel(min_neighbours=-1)
    with pytest.raises(InputError):
        MotionModel(coherence=float("nan"))


@needs_data
@pytest.mark.parametrize("kind,master", [("toward", "hold"), ("rocking", "push")])
def test_prediction_is_no_less_safe_than_none_on_a_real_frame(apc, kind, master):
    """apc frame at 0.3 m/s, 1 cm fixture: the proxy's and the robot's penetration with
    prediction is no larger than without (0.1 mm: the measure's sampling)."""
    a = apc.anchor()
    runs = {p: dr.run_case(apc, Motion(kind, 0.3, tuple(a)), 0.3, p, r_f=0.01, master=master) for p in (False, True)}
    off, on = runs[False], runs[True]
    print(f"\n{kind}/{master} 0.3 m/s: without {off.proxy_penetration * 1e3:.2f}/{off.robot_penetration * 1e3:.2f} mm, "
          f"with {on.proxy_penetration * 1e3:.2f}/{on.robot_penetration * 1e3:.2f} mm")
    assert on.proxy_penetration <= off.proxy_penetration + 1e-4
    assert on.robot_penetration <= off.robot_penetration + 1e-4
    assert not on.proxy_popped


def test_run_case_refuses_an_unknown_master():
    with pytest.raises(InputError):
        dr.run_case(None, None, 0.1, True, master="pull")


def test_frames_that_do_not_exist_are_refused_with_the_path():
    with pytest.raises(InputError, match="no-such-dir"):
        dr.real_surface("/tmp/no-such-dir")


@needs_data
def test_bench_dynamic_real_quick_json_runs():
    out = subprocess.run([sys.executable, "-m", "pointfence", "bench", "dynamic", "--real", "--quick", "--json"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    rows = res["real_rows"]
    assert {r["scene"] for r in rows} == {"apc_shelfbin_50f", "synthetic_plane"}
    for r in rows:
        for k in ("proxy_mm_without", "robot_mm_without", "proxy_mm_with", "robot_mm_with"):
            assert r[k] >= 0
    assert res["real_estimator"] and res["real_estimator"][0]["predicted_mm"] < res["real_estimator"][0]["static_mm"]


@needs_data
def test_mesh_distance_equals_brute_force_over_every_triangle():
    """The KD-tree candidate search of the true-surface distance finds the nearest triangle:
    on a 60 x 60 px crop of a real apc frame (holes filled 3 px, edges left open), 300 random
    points within 3 cm of it read the brute-force minimum over all triangles."""
    from pointfence.service.depth_mesh import MeshDistance, _tri_distance, depth_triangles
    from pointfence.service.dynamic_real_frames import JUMP, fill_holes, load_real

    depth, cam = load_real(APC)
    z = fill_holes(depth.astype(np.float64) * cam.depth_scale)[200:260, 280:340]
    crop = Camera("c", 60, 60, cam.fx, cam.fy, cam.cx - 280, cam.cy - 200)
    tris = depth_triangles(z, crop, JUMP)
    mesh = MeshDistance(tris)
    rng = np.random.default_rng(3)
    q = tris[rng.integers(0, len(tris), 300)].mean(1) + rng.normal(0, 0.015, (300, 3))
    got = mesh.signed(q)
    want = np.array([_tri_distance(p, tris)[0].min() for p in q])
    np.testing.assert_allclose(np.abs(got), want, atol=1e-12)
    assert (got < 0).any() and (got > 0).any()


def test_a_motion_with_a_stop_halts_there():
    """``Motion.stop``: the pose moves until the stop and stays there; the velocity is 0 after
    it; a stop that is not a finite time >= 0 is refused."""
    a = (0.05, -0.1, 0.5)
    for kind in ("toward", "sideways", "rocking"):
        free, halted = Motion(kind, 1.0, a), Motion(kind, 1.0, a, stop=0.03)
        for t in (0.01, 0.029):
            np.testing.assert_allclose(halted.pose(t)[1], free.pose(t)[1])
        for t in (0.03, 0.05, 0.2):
            np.testing.assert_allclose(halted.pose(t)[0], free.pose(0.03)[0])
            np.testing.assert_allclose(halted.pose(t)[1], free.pose(0.03)[1])
        assert np.all(halted.velocity(np.array([a]), 0.05) == 0)
        assert np.linalg.norm(halted.velocity(np.array([a]), 0.01)) > 0.9
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(InputError, match="stop"):
            Motion("toward", 1.0, a, stop=bad)


def test_a_point_beside_a_hole_with_the_surface_behind_it_is_in_front():
    """A plane z = 0.5 m seen with its right half missing (a hole, or an object's edge) and a
    floor 5 cm behind it under the hole: a point 3 mm beyond the plane's edge, 1 mm deeper than
    the edge, its own ray ending on the floor 4 cm further, is in front of the surface (the
    nearest triangle is the edge's, the point is further along the edge point's ray: the
    nearest-point rule alone read it 3 mm behind); a point 2 mm behind the plane itself still
    reads 2 mm behind."""
    cam = Camera("h", 200, 100, 300.0, 300.0, 100.0, 50.0, depth_scale=1e-4)
    depth = np.full((100, 200), 5000, np.uint16)
    depth[:, 120:] = 5500
    frame = MovingRealFrame(depth, cam, name="edge")
    m = Motion("toward", 0.0, tuple(frame.anchor()))
    x_edge = (119 - 100) / 300 * 0.5               # the plane's last pixel column, m
    beside = np.array([[x_edge + 0.003, 0.0, 0.501]])
    got = float(frame.distance(m, beside, 0.0)[0])
    assert got > 0, got
    assert abs(got - np.hypot(0.003, 0.001)) < 2e-4, got
    behind = np.array([[x_edge - 0.02, 0.0, 0.502]])
    assert abs(float(frame.distance(m, behind, 0.0)[0]) + 0.002) < 1e-4


@needs_data
def test_a_real_frame_point_between_two_objects_is_in_front(apc):
    """apc's bin: a point 36 mm from two foreground objects' faces (above and below it in the
    image) and 65 mm in front of the bin floor along its own ray, 1 mm deeper than its nearest
    face point (a proxy pushed out by prediction at 1.5 m/s, 2 cm fixture, passed there): in
    front (the nearest-point rule alone read it 36.7 mm behind, a pop-through that was not)."""
    m = Motion("toward", 0.0, tuple(apc.anchor()))
    q = apc.anchor() + np.array([-44.3, -3.6, -19.5]) * 1e-3
    d = float(apc.distance(m, q[None], 0.0)[0])
    assert 0.03 < d < 0.04, d


@needs_data
def test_the_2cm_fixture_holds_a_real_frame_advancing_at_1mps_with_prediction(apc):
    """apc frame toward the holding master at 1 m/s (33 mm a frame, more than the 2 cm
    fixture), its 4 cm stroke, then still, 4 frames: with prediction the proxy never goes
    through and stays within 0.5 mm of the fixture; without, one frame's jump carries the
    surface past it by more than the radius."""
    a = apc.anchor()
    on = dr.run_case(apc, Motion("toward", 1.0, tuple(a)), 1.0, True, r_f=0.02, master="hold")
    off = dr.run_case(apc, Motion("toward", 1.0, tuple(a)), 1.0, False, r_f=0.02, master="hold")
    print(f"\napc toward/hold 1 m/s, 2 cm: with {on.proxy_penetration * 1e3:.2f}/{on.robot_penetration * 1e3:.2f} mm, "
          f"without {off.proxy_penetration * 1e3:.2f}/{off.robot_penetration * 1e3:.2f} mm")
    assert on.frames >= 5 and not on.proxy_popped
    assert on.proxy_penetration <= 0.5e-3
    assert off.proxy_penetration > 0.01


def test_run_case_refuses_a_bad_advance():
    with pytest.raises(InputError, match="advance"):
        dr.run_case(None, None, 0.1, True, master="hold", advance=-0.01)


# --- where the penetration comes from (service/dynamic_real_trace.py), the robot's command ---

def test_trace_splits_the_plane_floor_into_sampling_not_prediction():
    """Synthetic plane toward a holding master at 0.1 m/s, with prediction: at every tick the
    three terms add up to the measured penetration, the trace's worst tick is the run's, and the
    0.6 mm floor there is the cloud's sampling of the plane (Kinect noise, 1 mm depth codes,
    4 mm between pixels at 0.6 m), not the prediction, in the middle of the run (not its first
    frames, nor a stop)."""
    from pointfence.service.dynamic_real_trace import trace_case

    tr = trace_case(dr._PlaneSurface(0.1), None, 0.1, True, r_f=0.01, master="hold")
    total = tr.sampling_mm + tr.prediction_mm + tr.overlap_mm
    assert np.max(np.abs(total - tr.proxy_mm)) < 1e-9
    assert max(tr.proxy_mm.max(), 0.0) == pytest.approx(tr.run.proxy_penetration * 1e3, abs=1e-9)
    assert max(tr.robot_mm.max(), 0.0) == pytest.approx(tr.run.robot_penetration * 1e3, abs=1e-9)
    w = tr.worst()
    print("\nplane, hold, 0.1 m/s, worst tick:", w)
    assert w["proxy_mm"] > 0.3 and w["sampling_mm"] > 0.8 * w["proxy_mm"] and abs(w["prediction_mm"]) < 0.1
    assert w["frame_t_s"] > 3 / dr.RATE_HZ
    # the per-frame sampling term swings both ways: a draw per frame, not a drift
    sampling = [f["sampling_mm_max"] for f in tr.frames()[3:]]
    assert min(sampling) < -0.2 < 0.2 < max(sampling)
    # the recorded dt is the service's: now - frame time, clamped to the horizon (latency 0),
    # and 0 once the surface has stopped and the estimate says so
    moving = tr.t < 1 / dr.RATE_HZ + 0.03 / 0.1
    assert np.allclose(tr.dt[moving], np.clip(tr.t - tr.t_snapshot, 0.0, 0.1)[moving], atol=1e-9)
    # the run goes on AFTER_STOP past the stop (it used to end there below 0.2 m/s), and the
    # stale prediction over the stop adds nothing
    after = ~moving
    assert after.sum() >= round(dr.AFTER_STOP * dr.TICK_HZ) and np.all(tr.v_true[after] == 0)
    assert tr.proxy_mm[after].max() <= tr.proxy_mm[moving].max()


def test_trace_prediction_term_is_the_static_clouds_lag_without_prediction():
    """Without prediction the cloud stays where the frame saw it: on the plane moving along its
    normal at v the prediction term is v times the frame's age, times the cosine (> 0.9) of the
    nearest point's angle off the plane's normal (4 mm between the pixels' samples under a 1 cm
    sphere), so the term measures what it says."""
    from pointfence.service.dynamic_real_trace import trace_case

    v = 0.1
    tr = trace_case(dr._PlaneSurface(v), None, v, False, r_f=0.01, master="hold")
    touching = (tr.proxy_mm > -1.0) & (tr.t < 1 / dr.RATE_HZ + 0.03 / v)   # before the plane stops
    assert touching.sum() > 50
    lag = v * (tr.t - tr.t_snapshot) * 1e3
    pred, lag = tr.prediction_mm[touching], lag[touching]
    assert np.all(pred <= lag + 0.02) and np.all(pred >= 0.9 * lag - 0.02)
    assert np.all(tr.v_est == 0) and np.allclose(tr.v_true[touching], [0.0, 0.0, v])


@needs_data
def test_the_robot_follows_the_services_command_within_its_goal_on_a_real_frame(apc):
    """apc advancing at 0.3 m/s, master pushing 2 cm in, 1 cm fixture, prediction: the robot's
    command is the service's architecture-III command (``Teleop``, slip lift on as by default),
    so it lands within 1 mm (issue 23's target; a bare rate limit toward the proxy cut the
    corner the master's push makes across the slanted surface: 1.73 mm), and it never moves
    faster than the robot's limit."""
    from pointfence.service.dynamic_real_trace import trace_case

    m = Motion("toward", 0.3, tuple(apc.anchor()))
    tr = trace_case(apc, m, 0.3, True, r_f=0.01, master="push")
    bare = trace_case(apc, m, 0.3, True, r_f=0.01, master="push", slip_lift=False)
    print(f"\napc push 0.3 m/s: robot {tr.run.robot_penetration * 1e3:.2f} mm with the slip lift, "
          f"{bare.run.robot_penetration * 1e3:.2f} mm without; proxy {tr.run.proxy_penetration * 1e3:.2f} mm")
    assert tr.run.robot_penetration <= 1e-3
    assert bare.run.robot_penetration > tr.run.robot_penetration
    step = dr.ROBOT_SPEED / dr.TICK_HZ
    for t in (tr, bare):
        assert np.all(np.linalg.norm(np.diff(t.robot, axis=0), axis=1) <= step * (1 + 1e-9))
    # without the lift the command is the proxy, rate-limited: a step toward it, or on it
    prev, goal, now = bare.robot[:-1], bare.proxy[1:], bare.robot[1:]
    d = goal - prev
    dn = np.linalg.norm(d, axis=1, keepdims=True)
    expect = np.where(dn <= step, goal, prev + d * (step / np.maximum(dn, 1e-300)))
    assert np.allclose(now, expect, atol=1e-7)


def test_trace_case_keeps_its_own_hooks():
    from pointfence.service.dynamic_real_trace import trace_case

    with pytest.raises(TypeError, match="probe"):
        trace_case(dr._PlaneSurface(0.1), None, 0.1, True, probe=lambda hs, t: None)


@needs_data
def test_bench_dynamic_real_subset_and_floor_json():
    """--speeds / --cases choose the sweep's subset; --floor adds each case's worst tick split
    into its terms."""
    out = subprocess.run([sys.executable, "-m", "pointfence", "bench", "dynamic", "--real", "--quick", "--json",
                          "--speeds", "0.3", "--cases", "toward/push", "--floor"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    assert {(r["master"], r["speed_mps"]) for r in res["real_rows"]} == {("push", 0.3)}
    floor = res["real_floor"]
    assert {(r["scene"], r["master"], r["speed_mps"]) for r in floor} == {
        ("apc_shelfbin_50f", "push", 0.3), ("synthetic_plane", "push", 0.3)}
    for r in floor:
        w = r["worst"]
        assert w["sampling_mm"] + w["prediction_mm"] + w["overlap_mm"] == pytest.approx(w["proxy_mm"], abs=2e-3)
        assert r["contact"]["frames"] >= 1


def test_bench_dynamic_real_refuses_a_bad_speed_list():
    out = subprocess.run([sys.executable, "-m", "pointfence", "bench", "dynamic", "--real", "--speeds", "fast"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "fast" in out.stderr and "0.1,0.3" in out.stderr
