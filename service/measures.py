"""Performance measures of a virtual fixture (dissertation 6.1), computed after a run.

For robot positions X_r(t), commands X_r*(t) and mapped master positions X_m(t) (world, m) and
a signed distance to the forbidden region d(X, t) (m, negative inside):

* safety: the maximum penetration of the robot into the forbidden region, max(0, -min d(X_r));
* submittance: the minimum robot-to-region distance while the robot is held off, i.e. over the
  ticks where the master is inside the region (d(X_m) < 0) but the robot is not (d(X_r) >= 0);
  None if the robot was never held off;
* tracking: the r.m.s. of |X_r - X_r*| over the ticks where the master is outside the region
  (plus, as ``tracking_master_rms_m``, the r.m.s. of |X_r - X_m| over the same ticks).

Region distances come from ground truth when it exists (``SceneRegion``: the synthetic scene's
exact protected surface, at the time of each tick, minus the fixture radius) or from the last
snapshot's protected points and their radii (``SnapshotRegion``). A recording's measures (``serve
--record``, ``pointfence inspect``) come from its recorded depth, tick by tick against the snapshot
each tick used (``run_measures``, ``recorded_surface``).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree


class SceneRegion:
    """Forbidden region of a synthetic scene: points within ``radius`` of its protected surface
    (exact surface sampled every ``spacing`` m from straight above; moving scenes re-sampled
    every ``time_step`` s)."""

    def __init__(self, scene, radius: float, spacing: float = 0.0005, time_step: float = 1.0 / 30.0):
        self.scene = scene
        self.radius = float(radius)
        self.spacing = float(spacing)
        self.time_step = float(time_step)

    def _surface(self, t: float, lo, hi) -> np.ndarray:
        gx = np.arange(lo[0], hi[0] + 1e-12, self.spacing)
        gy = np.arange(lo[1], hi[1] + 1e-12, self.spacing)
        x, y = np.meshgrid(gx, gy)
        o = np.stack([x.ravel(), y.ravel(), np.full(x.size, 2.0)], axis=1)
        d = np.tile([0.0, 0.0, -1.0], (len(o), 1))
        s = self.scene.cast(o, d, t)
        ok = np.isfinite(s)
        pts = o[ok] + s[ok, None] * d[ok]
        return pts[self.scene.protected(pts, t)] if len(pts) else pts

    def __call__(self, points, times, within: Optional[float] = None) -> np.ndarray:
        """Signed distances (m) of ``points`` (N, 3) at ``times`` (s) to the region. ``within``
        (m): only distances up to it are wanted; a point further than that outside the region
        reads +inf (a nearest-neighbour query cut off there is far cheaper for points well away
        from a densely sampled surface). Points inside the solid are exact either way."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        t = np.broadcast_to(np.asarray(times, dtype=float), (len(p),))
        out = np.full(len(p), np.inf)
        ok = np.isfinite(p).all(axis=1)
        if not ok.any():
            return out
        reach = self.radius + 0.03
        lo, hi = p[ok, :2].min(axis=0) - reach, p[ok, :2].max(axis=0) + reach
        keys = np.round(t / self.time_step).astype(np.int64) if self.scene.moving else np.zeros(len(p), np.int64)
        for key in np.unique(keys[ok]):
            sel = ok & (keys == key)
            surf = self._surface(float(key) * self.time_step, lo, hi)
            if len(surf) == 0:
                continue
            tree = cKDTree(surf)
            ub = np.inf if within is None else max(float(within), 0.0) + self.radius
            dist, _ = tree.query(p[sel], workers=-1, distance_upper_bound=ub)   # (every core: a tick's point each)
            inside = self.scene.distance(p[sel], float(key) * self.time_step) < 0   # in the solid itself
            deep = inside & ~np.isfinite(dist)
            if deep.any():             # inside, further below the surface than the cut-off
                dist[deep] = tree.query(p[sel][deep], workers=-1)[0]
            out[sel] = np.where(inside, -dist, dist) - self.radius
        return out


class SnapshotRegion:
    """Forbidden region from a host snapshot: min_i |X - P_i| - r_f(i) over protected points."""

    def __init__(self, snapshot, k: int = 16):
        prot = snapshot.protected != 0
        self.points = np.asarray(snapshot.points[prot, :3], dtype=float)
        self.radii = np.asarray(snapshot.points[prot, 3], dtype=float)
        self.tree = cKDTree(self.points) if len(self.points) else None
        self.r_max = float(self.radii.max()) if len(self.radii) else 0.0
        self.k = int(k)

    def __call__(self, points, times=None, within: Optional[float] = None) -> np.ndarray:
        """Signed distances (m) of ``points`` (N, 3) to the region (``times`` asks nothing of a
        snapshot); ``within`` as for SceneRegion: a point further than it reads +inf."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        if self.tree is None:
            return np.full(len(p), np.inf)
        k = min(self.k, len(self.points))
        # (a point within ``within`` of the region is within ``within`` + its radius of its point)
        ub = np.inf if within is None else max(float(within), 0.0) + self.r_max * (1 + 1e-9) + 1e-12
        dist, idx = self.tree.query(np.nan_to_num(p, nan=1e9), k=k, distance_upper_bound=ub, workers=-1)
        dist, idx = np.atleast_2d(dist.T).T, np.atleast_2d(idx.T).T
        d = (dist - self.radii[np.minimum(idx, len(self.radii) - 1)]).min(axis=1)
        if within is not None:       # (beyond it, only some of a point's nearest were looked at)
            d[d > max(float(within), 0.0)] = np.inf
        return d


def compute(times, xr, cmd, xm, region, mask=None) -> dict:
    """Safety, submittance and tracking (see the module docstring) over the ticks in ``mask``
    (default all). Arrays (N, 3) m; ``region(points, times, within=None)`` -> signed distances
    (N,), exact up to ``within`` (m) and +inf beyond it outside the region."""
    t = np.asarray(times, dtype=float)
    xr, cmd, xm = (np.asarray(a, dtype=float) for a in (xr, cmd, xm))
    m = np.ones(len(t), bool) if mask is None else np.asarray(mask, bool)
    if not m.any():
        return summarise(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    # (of the mapped master only the sign counts: d_m < 0, in the region)
    return summarise(region(xr[m], t[m]), region(xm[m], t[m], within=0.0), np.linalg.norm(xr[m] - cmd[m], axis=1),
                     np.linalg.norm(xr[m] - xm[m], axis=1))


def summarise(d_r, d_m, err_cmd, err_m, coupled=None) -> dict:
    """The measures from per-tick values: signed distances of the robot ``d_r`` and of the mapped
    master ``d_m`` to the forbidden region (m, negative inside), |X_r - X_r*| ``err_cmd`` and
    |X_r - X_m| ``err_m`` (m), all (N,). Safety and ``min_robot_distance_m`` are over every
    tick; submittance and tracking over the ticks in ``coupled`` (default all: the ticks where
    the master drives the robot). A value with no tick to take it from is None."""
    d_r, d_m, err_cmd, err_m = (np.asarray(a, dtype=float) for a in (d_r, d_m, err_cmd, err_m))
    c = np.ones(len(d_r), bool) if coupled is None else np.asarray(coupled, bool)
    held = c & (d_m < 0) & (d_r >= 0)
    free = c & (d_m >= 0)

    def r(v) -> Optional[float]:
        return None if v is None or not math.isfinite(v) else float(v)

    if not len(d_r):
        return {"safety_max_penetration_m": None, "submittance_min_distance_m": None, "tracking_rms_m": None,
                "tracking_master_rms_m": None, "min_robot_distance_m": None}
    return {
        "safety_max_penetration_m": r(max(0.0, -float(d_r.min()))),
        "submittance_min_distance_m": r(float(d_r[held].min())) if held.any() else None,
        "tracking_rms_m": r(float(np.sqrt(np.mean(err_cmd[free] ** 2)))) if free.any() else None,
        "tracking_master_rms_m": r(float(np.sqrt(np.mean(err_m[free] ** 2)))) if free.any() else None,
        "min_robot_distance_m": r(float(d_r.min())),
    }


def region_for(cfg, sources, pipeline=None):
    """Ground truth for the configured scene if the first camera is synthetic, else the
    pipeline's current snapshot."""
    radius = cfg.pipeline.radius.r_base if cfg.mode == "fixture" else 0.0
    for s in sources:
        scene = getattr(s, "scene", None)
        if scene is not None:
            return SceneRegion(scene, radius)
    if pipeline is not None:
        return SnapshotRegion(pipeline.host_snapshot())
    raise ValueError("no synthetic scene and no pipeline to measure against")


def json_safe(o):
    """``o`` with every non-finite float (NaN, inf) replaced by None, through dicts, lists and
    tuples: what JSON can hold."""
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: json_safe(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_safe(v) for v in o]
    return o
