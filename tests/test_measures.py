"""service/measures.py: the ground-truth region's cut-off query (``within``) gives the exact
distances up to the cut-off, +inf beyond it outside, and exact ones inside; the measures of a
run are the same with the master's distances cut off (only their sign counts)."""
from __future__ import annotations

import numpy as np

from pointfence.service import config as config_mod
from pointfence.service import measures


def _region():
    cfg = config_mod.load(None)                     # the embedded balloon scene
    sources = cfg.open_sources()
    try:
        region = measures.region_for(cfg, sources)
    finally:
        for s in sources:
            s.close()
    assert isinstance(region, measures.SceneRegion)
    return region


def _points(region, n=3000, seed=3):
    """Points from 8 cm above the region to deep inside the balloon, over its top."""
    rng = np.random.default_rng(seed)
    exact = region(np.zeros((1, 3)) + [0.0, 0.0, 1.0], 0.0)    # (warm-up; a point far above)
    assert np.isfinite(exact).all()
    top = region.scene.cast(np.array([[0.0, 0.0, 2.0]]), np.array([[0.0, 0.0, -1.0]]), 0.0)[0]
    z0 = 2.0 - top
    p = np.column_stack([rng.uniform(-0.03, 0.03, n), rng.uniform(-0.03, 0.03, n), z0 + rng.uniform(-0.04, 0.08, n)])
    return p, np.zeros(n)


def test_a_cut_off_query_is_exact_within_it_and_inside_and_inf_beyond():
    region = _region()
    p, t = _points(region)
    exact = region(p, t)
    assert (exact < -0.02).sum() > 100 and (exact > 0.03).sum() > 100      # deep inside and well away
    for within in (0.0, 0.005, 0.02):
        cut = region(p, t, within=within)
        near = exact <= within
        np.testing.assert_array_equal(cut[near], exact[near])
        assert (exact[cut < 0] < 0).all() and (cut[exact < 0] == exact[exact < 0]).all()
        far = ~near
        assert np.all((cut[far] == np.inf) | (cut[far] == exact[far]))
        assert (cut[exact > within + 1e-3] == np.inf).all()


def test_the_measures_are_the_same_with_the_masters_distances_cut_off():
    region = _region()
    p, t = _points(region, n=2000, seed=5)
    rng = np.random.default_rng(9)
    xr = p
    xm = p + rng.normal(0.0, 0.01, p.shape)          # the master deeper or shallower than the robot
    cmd = p + rng.normal(0.0, 0.001, p.shape)
    got = measures.compute(t, xr, cmd, xm, region)
    want = measures.summarise(region(xr, t), region(xm, t), np.linalg.norm(xr - cmd, axis=1),
                              np.linalg.norm(xr - xm, axis=1))
    assert got == want
    assert got["submittance_min_distance_m"] is not None and got["safety_max_penetration_m"] > 0.02


def test_a_snapshots_region_cut_off_is_exact_within_it_and_the_measures_are_unchanged():
    from types import SimpleNamespace

    rng = np.random.default_rng(11)
    n = 4000                                         # a wavy sheet of protected points, radii 5-15 mm
    xy = rng.uniform(-0.1, 0.1, (n, 2))
    z = 0.01 * np.sin(30 * xy[:, 0]) * np.cos(20 * xy[:, 1])
    pts = np.column_stack([xy, z, rng.uniform(0.005, 0.015, n)]).astype(np.float32)
    prot = (rng.random(n) < 0.8).astype(np.uint8)
    region = measures.SnapshotRegion(SimpleNamespace(points=pts, protected=prot))
    q = np.column_stack([rng.uniform(-0.12, 0.12, (3000, 2)), rng.uniform(-0.03, 0.08, 3000)])
    exact = region(q)
    assert (exact < 0).sum() > 100 and (exact > 0.03).sum() > 100
    for within in (0.0, 0.004, 0.02):
        cut = region(q, within=within)
        near = exact <= within
        np.testing.assert_array_equal(cut[near], exact[near])
        assert np.all((cut[~near] == np.inf) | (cut[~near] == exact[~near]))
        assert (cut[exact > within + 1e-3] == np.inf).all()
    t = np.zeros(len(q))
    xm = q + rng.normal(0.0, 0.01, q.shape)
    cmd = q + rng.normal(0.0, 0.001, q.shape)
    got = measures.compute(t, q, cmd, xm, region)
    want = measures.summarise(region(q), region(xm), np.linalg.norm(q - cmd, axis=1), np.linalg.norm(q - xm, axis=1))
    assert got == want and got["submittance_min_distance_m"] is not None
