"""Temporal smoothing of the per-cell motion estimate (kernels/motion.py, ``[motion] smoothing``
and ``smooth_gate``, issue 23): where a surface keeps its motion, the mean of consecutive
estimates carries less of the per-frame error; where it changes its motion (stops, reverses)
the new estimate is taken at once."""
import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.kernels.motion import CELL_MEASURED, MotionEstimator, MotionModel, cell_moments

from test_motion_rotation import GAP, GRID, _plane, _sorted


def _speeds(model, offsets, noise=0.0, seed=3, smoothed=None):
    """The measured motion cells' mean speed along z (m/s) after each snapshot of a horizontal
    patch at heights ``offsets`` (m, one snapshot per frame), depth noise ``noise`` (m); each
    estimate's count of smoothed cells (the status's ``cells_smoothed``) appended to
    ``smoothed``."""
    rng = np.random.default_rng(seed)
    est = MotionEstimator(model, GRID)
    out = []
    for i, z in enumerate(offsets):
        p = _plane(0.0, (0.0, 0.0, 0.0)) + (0.0, 0.0, z)
        p[:, 2] += rng.normal(0.0, noise, len(p)) if noise else 0.0
        pts, start = _sorted(p)
        cm, _ = est.update(cell_moments(pts, start, GRID), i * GAP)
        if cm is None:
            continue
        measured = est.confidence_of(np.flatnonzero(np.diff(start) > 0)) == CELL_MEASURED
        cells = np.flatnonzero(np.diff(start) > 0)[measured]
        out.append(float(np.mean(cm[cells, 2])))
        if smoothed is not None:
            smoothed.append(est.summary()["cells_smoothed"])
    return np.array(out)


def test_smoothing_lowers_the_per_frame_error_of_a_steady_surface():
    z = 0.1 * GAP * np.arange(10)                       # rising at 0.1 m/s, 4 mm of noise per point
    raw = _speeds(MotionModel(enabled=True, smoothing=1.0), z, noise=0.004)
    smooth = _speeds(MotionModel(enabled=True), z, noise=0.004)
    assert np.allclose(np.mean(raw), 0.1, atol=0.02)
    # after the first estimate (nothing to average with), the error is smaller
    assert np.abs(smooth[1:] - 0.1).max() < np.abs(raw[1:] - 0.1).max()
    assert np.std(smooth[1:] - 0.1) < 0.8 * np.std(raw[1:] - 0.1)


def test_a_surface_that_stops_is_seen_stopped_at_once():
    z = np.concatenate([0.1 * GAP * np.arange(6), np.full(3, 0.1 * GAP * 5)])   # rises, then stops
    counts = []
    smooth = _speeds(MotionModel(enabled=True), z, smoothed=counts)
    assert np.allclose(smooth[:4], 0.1, atol=1e-3)
    assert abs(smooth[5]) < 1e-6                        # the first estimate after the stop: no lag
    assert counts[0] == 0 and min(counts[1:5]) > 0      # averaged while it rose (not the first estimate)


def test_a_change_within_the_gate_is_averaged_and_one_beyond_it_is_not():
    z = np.cumsum([0.0] + [0.1 * GAP] * 4 + [0.11 * GAP] * 2)     # 0.1 m/s, then 0.11 (10 %: within 15 %)
    s = _speeds(MotionModel(enabled=True), z)
    assert 0.1 < s[4] < 0.109                           # averaged
    s = _speeds(MotionModel(enabled=True, smooth_gate=0.0, v_min=0.005), z)
    assert s[4] == pytest.approx(0.11, abs=1e-3)        # beyond the gate (v_min only): taken as it is


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5, float("nan")])
def test_smoothing_is_a_weight(bad):
    with pytest.raises(InputError, match="smoothing"):
        MotionModel(enabled=True, smoothing=bad)
