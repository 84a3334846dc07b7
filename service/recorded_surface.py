"""The forbidden region as one recorded snapshot saw it: signed distances (m) from world points to
the fixture of that snapshot's protected points, for the run measures (``run_measures``).

A snapshot (``kernels.snapshot.HostSnapshot``, rebuilt offline from the recorded depth frames by
a backend's own frame pipeline) holds every protected point P_i (world frame, m) with its fixture
radius r_i (m). The forbidden region is the union of the spheres |X - P_i| < r_i, so outside the
observed solid the signed distance of a point X is

    d(X) = min_i (|X - P_i| - r_i)          (m; negative inside a sphere).

A depth camera sees only the front of a protected object. A point that lies *behind* the
observed surface, i.e. it projects (through the camera's pinhole and Brown-Conrady model) onto a
valid pixel whose recorded depth is smaller than the point's depth and whose point is protected,
is inside the object: there d(X) = -(|X - P_nearest| + r_nearest), as the ground-truth region of
``measures.SceneRegion`` counts a point inside the solid. Without this, a robot pushed through a
surface by more than the fixture radius would count as outside again.

Distances are computed only near the queries: points farther than ``REACH_M`` from every
protected point get +inf ("farther than REACH_M"), which no measure needs more precisely.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: distances beyond this from every protected point are reported as +inf (m)
REACH_M = 0.05
#: protected points whose spheres are tested per query (the nearest ones)
K_NEAREST = 16


class RecordedSurface:
    """Signed distances to the fixture of one snapshot.

    ``snapshot``: the pipeline's ``HostSnapshot``; ``cameras``: the rig's ``kernels.camera.Camera``
    in rig order; ``frames``: the ``DepthFrame`` each camera contributed (its depth image and,
    when set, its per-frame pose ``T_world_cam``); ``offsets``: each camera's first rig pixel
    (``kernels.rig.Rig.offsets``)."""

    def __init__(self, snapshot, cameras, frames, offsets):
        prot = np.asarray(snapshot.protected) != 0
        self.points = np.asarray(snapshot.points[prot, :3], dtype=np.float64)
        self.radii = np.asarray(snapshot.points[prot, 3], dtype=np.float64)
        self.pixels = np.sort(np.asarray(snapshot.pixel[prot], dtype=np.int64))
        self.cameras, self.frames = list(cameras), list(frames)
        self.offsets = np.asarray(offsets, dtype=np.int64)
        self.r_max = float(self.radii.max()) if len(self.radii) else 0.0

    def __len__(self) -> int:
        return len(self.points)

    def signed_distance(self, queries) -> np.ndarray:
        """d(X) (m, see the module docstring) of each query (N, 3) world point; NaN queries give
        NaN, queries beyond ``REACH_M`` of every protected point +inf."""
        q = np.atleast_2d(np.asarray(queries, dtype=np.float64))
        out = np.full(len(q), np.inf)
        ok = np.isfinite(q).all(axis=1)
        out[~ok] = np.nan
        if not ok.any() or not len(self.points):
            return out
        reach = REACH_M + self.r_max
        lo, hi = q[ok].min(axis=0) - reach, q[ok].max(axis=0) + reach
        near = np.all((self.points >= lo) & (self.points <= hi), axis=1)
        if not near.any():
            return out
        pts, rad = self.points[near], self.radii[near]
        k = min(K_NEAREST, len(pts))
        dist, idx = cKDTree(pts).query(q[ok], k=k, distance_upper_bound=reach)
        dist, idx = dist.reshape(len(dist), k), idx.reshape(len(idx), k)
        found = np.isfinite(dist[:, 0])
        r = np.where(np.isfinite(dist), rad[np.minimum(idx, len(rad) - 1)], 0.0)
        outside = np.where(found, (dist - r).min(axis=1), np.inf)
        inside = -(dist[:, 0] + r[:, 0])
        behind = self.behind_protected(q[ok]) & found
        d = np.where(behind, inside, outside)
        d[d > REACH_M] = np.inf
        out[ok] = d
        return out

    def behind_protected(self, q: np.ndarray) -> np.ndarray:
        """Whether each world point (N, 3) lies behind the recorded depth of a protected pixel of
        some camera (see the module docstring)."""
        hit = np.zeros(len(q), bool)
        for c, (cam, f) in enumerate(zip(self.cameras, self.frames)):
            if f is None:
                continue
            T = np.asarray(f.T_world_cam if f.T_world_cam is not None else cam.T_world_cam, dtype=np.float64)
            R, t = T[:3, :3], T[:3, 3]
            pc = (q - t) @ R                       # world -> camera: R^T (X - t)
            z = pc[:, 2]
            front = z > 1e-9
            x = np.where(front, pc[:, 0] / np.where(front, z, 1.0), 0.0)
            y = np.where(front, pc[:, 1] / np.where(front, z, 1.0), 0.0)
            k1, k2, p1, p2, k3 = cam.dist
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            u = np.rint(cam.fx * xd + cam.cx)
            v = np.rint(cam.fy * yd + cam.cy)
            inimg = front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
            if not inimg.any():
                continue
            ui, vi = u[inimg].astype(np.int64), v[inimg].astype(np.int64)
            code = np.asarray(f.depth)[vi, ui].astype(np.int64)
            zs = code * cam.depth_scale
            valid = (code != 0) & (code != cam.max_code) & (zs >= cam.z_min) & (zs <= cam.z_max)
            pix = self.offsets[c] + vi * cam.width + ui
            pos = np.searchsorted(self.pixels, pix)
            prot = (pos < len(self.pixels)) & (self.pixels[np.minimum(pos, len(self.pixels) - 1)] == pix)
            sel = np.flatnonzero(inimg)
            hit[sel] |= valid & prot & (z[inimg] > zs)
        return hit


__all__ = ["RecordedSurface", "REACH_M"]
