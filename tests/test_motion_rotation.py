"""Motion estimation of turning surfaces (kernels/motion.py: the affine field per block, issue 23):
a plane rotating about a hinge gets per-point velocities of the rigid rotation, a translating
one keeps a single velocity, an implausible turn predicts nothing, a hole inside a turning
patch takes its neighbours' fields, and every backend expands the cell motions as the reference."""
import math

import numpy as np
import pytest

from pointfence.kernels import PipelineParams, Workspace, get_backend
from pointfence.kernels.camera import Camera
from pointfence.kernels.grid import Grid
from pointfence.kernels.motion import (CELL_MEASURED, CELL_NONE, CELL_PROPAGATED, MotionEstimator, MotionModel,
                                       cell_moments, expand)
from pointfence.service.dynamic_real_frames import Motion, MovingRealFrame

#: hash cells of 1.25 cm: two per 2.5 cm motion cell, so a motion cell's points span a gradient
GRID = Grid(origin=(-0.15, -0.15, -0.15), h=0.0125, dims=(24, 24, 24))
GAP = 1 / 30


def _rot_y(theta):
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _plane(theta, hinge, tilt=0.0, hole=None):
    """Points (N, 3) of the 20 x 20 cm patch z = tilt * x (2 mm apart), rotated by ``theta``
    about the y axis through ``hinge``; without the points whose unrotated x is in ``hole``."""
    X, Y = np.meshgrid(np.arange(-0.1, 0.1, 0.002), np.arange(-0.1, 0.1, 0.002))
    p = np.stack([X.ravel(), Y.ravel(), tilt * X.ravel()], axis=1)
    if hole is not None:
        p = p[~((p[:, 0] >= hole[0]) & (p[:, 0] < hole[1]))]
    h = np.asarray(hinge, np.float64)
    return (p - h) @ _rot_y(theta).T + h


def _sorted(p):
    """(cell-sorted points (N, 4) float32, cell_start) of points (N, 3) on GRID."""
    ijk = np.floor((p - np.asarray(GRID.origin)) / GRID.h).astype(np.int64)
    nx, ny, nz = GRID.dims
    cell = (ijk[:, 2] * ny + ijk[:, 1]) * nx + ijk[:, 0]
    order = np.argsort(cell, kind="stable")
    start = np.searchsorted(cell[order], np.arange(nx * ny * nz + 1)).astype(np.int32)
    return np.concatenate([p[order], np.zeros((len(p), 1))], axis=1).astype(np.float32), start


def _estimate(model, before, after):
    """(estimator, per-point velocities of ``after`` (N, 3), its sorted points, cell_start, vmax)
    after snapshots of points ``before`` and ``after`` one frame apart."""
    est = MotionEstimator(model, GRID)
    pts0, start0 = _sorted(before)
    assert est.update(cell_moments(pts0, start0, GRID), 0.0) == (None, 0.0)
    pts, start = _sorted(after)
    cm, vmax = est.update(cell_moments(pts, start, GRID), GAP)
    return est, expand(cm, start, pts, GRID), pts, start, vmax


def _state_of_points(est, start):
    counts = np.diff(start)
    return est.confidence_of(np.repeat(np.arange(counts.size), counts))


def test_a_rotating_plane_gets_the_rigid_rotations_per_point_velocities():
    """A plane turning at 5 rad/s about a hinge 2 to 22 cm from its points (speeds 0.1 to 1.1
    m/s across it: a 2.5 cm cell spans 0.125 m/s): each point's velocity along the plane's
    normal is the rotation's to 1 cm/s (one velocity per cell was off by up to 0.12 m/s), so
    one frame ahead the predicted points lie on the turned plane to 0.5 mm; vmax bounds
    every point's speed."""
    w, hinge = 5.0, np.array([0.12, 0.0, 0.0])
    est, v, pts, start, vmax = _estimate(MotionModel(enabled=True), _plane(0.0, hinge), _plane(-w * GAP, hinge))
    p = pts[:, :3].astype(np.float64)
    assert np.all(_state_of_points(est, start) == CELL_MEASURED)
    true_v = np.cross([0.0, -w, 0.0], p - hinge)
    n = _rot_y(-w * GAP) @ [0.0, 0.0, 1.0]
    err = np.abs((v - true_v) @ n)
    assert err.max() < 0.01, err.max()
    ahead = p + v * GAP
    n2 = _rot_y(-2 * w * GAP) @ [0.0, 0.0, 1.0]
    assert np.max(np.abs((ahead - hinge) @ n2)) < 5e-4 + 1e-3  # + the arc's own 1 mm over one frame
    assert np.all(np.linalg.norm(v, axis=1) <= vmax)
    s = est.summary()
    assert abs(s["turn_max_radps"] - w) < 0.1 and s["rejected_w_max"] == 0


def test_a_translating_tilted_plane_keeps_one_velocity_per_cell():
    """No turn, no gradient: a tilted plane rising 9 mm per frame gets W = 0 in every cell and
    the normal velocity of the translation at every point, as before."""
    tilt = 0.3
    before = _plane(0.0, (0, 0, 0), tilt)
    est, v, pts, start, vmax = _estimate(MotionModel(enabled=True), before, before + [0.0, 0.0, 0.009])
    cm = est.cell_motion.reshape(-1, 4, 4)
    assert np.max(np.abs(cm[:, 1:, :3])) < 0.05           # 1/s: a 1.25 cm cell spans < 0.7 mm/s
    n = np.array([-tilt, 0.0, 1.0]) / math.hypot(tilt, 1.0)
    np.testing.assert_allclose(v @ n, 0.27 * n[2], atol=2e-3)
    assert np.all(_state_of_points(est, start) == CELL_MEASURED)


@pytest.mark.parametrize("w_max,expect", [(20.0, CELL_NONE), (40.0, CELL_MEASURED)])
def test_a_block_turning_faster_than_w_max_predicts_nothing(w_max, expect):
    """A patch turning 0.8 rad in one frame (24 rad/s) about its own centre: above w_max the
    turn is taken for a block whose contents changed and the cells near the hinge (whose counts
    still agree) predict nothing (velocity 0, state NONE, counted in rejected_w_max); a larger
    w_max measures them."""
    hinge = np.zeros(3)
    est, v, pts, start, _ = _estimate(MotionModel(enabled=True, w_max=w_max, min_neighbours=0),
                                      _plane(0.0, hinge), _plane(-0.8, hinge))
    near = np.linalg.norm(pts[:, :3], axis=1) < 0.02
    state = _state_of_points(est, start)[near]
    assert np.all(state == expect), np.unique(state, return_counts=True)
    s = est.summary()
    if expect == CELL_NONE:
        assert s["rejected_w_max"] > 0 and s["cells_measured"] == 0
        assert np.all(v == 0)
    else:
        assert s["rejected_w_max"] == 0 and s["turn_max_radps"] > 20


def test_a_hole_in_a_turning_patch_takes_its_neighbours_fields():
    """A plane turning at 5 rad/s about a hinge 2 cm beyond its edge; in the new snapshot a
    hole empties x in [-2.5, 2.1) cm: the motion cells of x in [0, 2.5) cm keep a 4 mm sliver
    about 10 cm from the hinge (0.5 m/s) and their blocks' counts disagree. They are
    PROPAGATED with the rotation's velocity at their own points (to 2 cm/s): their measured
    neighbours' affine fields, evaluated at the cell's centroid, agree (the mean of the
    neighbours' single velocities, the one-velocity-per-cell model, misses it by 8 cm/s)."""
    w, hinge = 5.0, np.array([0.12, 0.0, 0.0])
    hole = (-0.025, 0.021)
    est, v, pts, start, _ = _estimate(MotionModel(enabled=True, capture=0.025), _plane(0.0, hinge),
                                      _plane(-w * GAP, hinge, hole=hole))
    state = _state_of_points(est, start)
    prop = state == CELL_PROPAGATED
    assert np.count_nonzero(prop) >= 20, np.unique(state, return_counts=True)
    p = pts[:, :3].astype(np.float64)
    true_v = np.cross([0.0, -w, 0.0], p - hinge)
    n = _rot_y(-w * GAP) @ [0.0, 0.0, 1.0]
    err = np.abs((v - true_v) @ n)
    assert err[prop].max() < 0.02, err[prop].max()
    assert est.summary()["cells_propagated"] > 0


def _rocking_plane_frames():
    """A plane seen by a 160 x 120 camera 0.4 m away, tilted 0.2 in x, rocking at 0.5 m/s
    (5 rad/s about a hinge 10 cm from the contact point): two frames 1/30 s apart."""
    cam = Camera("cam0", 160, 120, 150.0, 150.0, 80.0, 60.0, depth_scale=1e-4)
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    depth = np.rint(0.4 / (1 - 0.2 * (u - 80.0) / 150.0) / 1e-4).astype(np.uint16)
    frame = MovingRealFrame(depth, cam, name="tilted")
    m = Motion("rocking", 0.5, tuple(frame.anchor()))
    return cam, [frame.render(m, k * GAP, k) for k in range(2)]


@pytest.mark.parametrize("backend", ["numpy", "opencl", "warp"])
def test_every_backend_expands_the_cell_motions_as_the_reference(backend):
    """On a rocking plane (cells with a gradient), each point's velocity from the device's
    expand_velocity equals motion.expand of the same cell motions and points: OpenCL bit for
    bit (same float32 operations in the same order), Warp to float32 rounding."""
    if backend == "warp":
        pytest.importorskip("warp")
    cam, frames = _rocking_plane_frames()
    kw = {"device": "cpu"} if backend == "warp" else {}
    pipe = get_backend(backend, **kw).pipeline(
        [cam], PipelineParams(workspace=Workspace((-0.25, -0.2, 0.2), (0.25, 0.2, 0.6)), motion=MotionModel(enabled=True)))
    for f in frames:
        pipe.ingest([f])
    snap = pipe.host_snapshot()
    cm = pipe.motion.cell_motion
    assert snap.vmax > 0.3 and np.max(np.abs(cm[:, 4:])) > 1.0     # 1/s: the turning plane's gradient
    ref = expand(cm, snap.cell_start, snap.points, snap.grid)
    got = np.asarray(snap.velocity)[:, :3]
    if backend == "warp":
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)
    else:
        np.testing.assert_array_equal(got, ref)
    assert np.all(np.linalg.norm(got, axis=1) <= snap.vmax * (1 + 1e-6))
