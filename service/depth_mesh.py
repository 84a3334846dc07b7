"""The continuous surface of a depth image: a triangle mesh over its pixels, and the exact
signed distance of points to it (the ground truth of ``dynamic_real_frames``).

Every 2 x 2 block of valid pixels whose depths agree within ``jump`` of their depth (a step
beyond is an edge between two surfaces, not surface) gives two triangles (camera frame, m).
``MeshDistance.signed(q)`` is the exact distance of each point to the nearest triangle,
negative on the far side of it as the camera sees it (a camera sees the face of a surface that
faces it). Candidates come from a KD-tree over the triangle centroids: a triangle within d of q
has its centroid within d + its circumradius; the few long triangles (grazing views, steep
Kinect disparity steps) are kept apart and always checked.
"""
from __future__ import annotations

import numpy as np

from pointfence.kernels.camera import Camera


def depth_vertices(depth_m: np.ndarray, cam: Camera) -> np.ndarray:
    """The mesh's vertices (H, W, 3): every pixel of ``depth_m`` (m) deprojected, camera frame, m."""
    h, w = depth_m.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([(u - cam.cx) / cam.fx * depth_m, (v - cam.cy) / cam.fy * depth_m, depth_m], axis=-1)


def depth_blocks(depth_m: np.ndarray, jump: float) -> np.ndarray:
    """(H - 1, W - 1) bool: the 2 x 2 pixel blocks (top-left corner) that give two triangles: all
    four depths valid and within ``jump`` of their depth of each other."""
    q = np.stack([depth_m[:-1, :-1], depth_m[:-1, 1:], depth_m[1:, :-1], depth_m[1:, 1:]])
    return (q > 0).all(0) & (q.max(0) - q.min(0) <= jump * q.max(0))


def depth_triangles(depth_m: np.ndarray, cam: Camera, jump: float) -> np.ndarray:
    """Triangles (T, 3, 3) of the depth map ``depth_m`` (m, 0 = none), camera frame, m: ABD and
    ADC of every block A B / C D of ``depth_blocks``."""
    P = depth_vertices(depth_m, cam)
    ok = depth_blocks(depth_m, jump)
    A, B, C, D = P[:-1, :-1][ok], P[:-1, 1:][ok], P[1:, :-1][ok], P[1:, 1:][ok]
    return np.concatenate([np.stack([A, B, D], 1), np.stack([A, D, C], 1)])


def _tri_distance(q: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances (M,) of point q (3,) to triangles (M, 3, 3) and their closest points (M, 3)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    nn = np.einsum("ij,ij->i", n, n)
    n = n / np.sqrt(np.maximum(nn, 1e-30))[:, None]
    h = np.einsum("ij,ij->i", q - a, n)
    p = q - h[:, None] * n
    inside = np.ones(len(tri), bool)
    for x, y in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(y - x, p - x), n) >= 0
    best = np.where(inside, np.abs(h), np.inf)
    closest = np.where(inside[:, None], p, 0.0)
    for x, y in ((a, b), (b, c), (c, a)):
        e = y - x
        t = np.clip(np.einsum("ij,ij->i", q - x, e) / np.maximum(np.einsum("ij,ij->i", e, e), 1e-30), 0.0, 1.0)
        s = x + t[:, None] * e
        d = np.linalg.norm(q - s, axis=1)
        better = d < best
        best = np.where(better, d, best)
        closest = np.where(better[:, None], s, closest)
    return best, closest


class MeshDistance:
    """Exact signed distance (m) of points to a triangle mesh seen from the origin (a camera at
    the origin: the side facing it is in front, positive)."""

    def __init__(self, tris: np.ndarray):
        from scipy.spatial import cKDTree

        self.tris = np.asarray(tris, np.float64)
        cen = self.tris.mean(1)
        rad = np.max(np.linalg.norm(self.tris - cen[:, None], axis=2), axis=1)
        self.r_short = float(np.percentile(rad, 99)) if len(rad) else 0.0
        long = rad > self.r_short
        self._short = np.flatnonzero(~long)
        self._long = np.flatnonzero(long)
        self._long_cen, self._long_rad = cen[long], rad[long]
        self.tree = cKDTree(cen[~long])

    def signed(self, points) -> np.ndarray:
        """Signed distances (N,) of points (N, 3) to the mesh (inf where it is empty)."""
        out = np.empty(len(points))
        for k, q in enumerate(np.asarray(points, np.float64).reshape(-1, 3)):
            out[k] = self._one(q)
        return out

    def _one(self, q: np.ndarray) -> float:
        if not len(self.tris):
            return np.inf
        d0, _ = self.tree.query(q)
        cand = self._short[self.tree.query_ball_point(q, d0 + self.r_short)]
        far = np.linalg.norm(self._long_cen - q, axis=1) - self._long_rad <= d0
        cand = np.concatenate([cand, self._long[far]]).astype(np.int64)
        d, s = _tri_distance(q, self.tris[cand])
        i = int(np.argmin(d))
        # behind: further along the camera's ray than the closest surface point
        behind = float(np.dot(q - s[i], s[i])) > 0
        return -float(d[i]) if behind else float(d[i])
