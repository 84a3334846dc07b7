"""Analytic solids for synthetic scenes: exact ray casting and signed distances.

All coordinates are world-frame metres. A solid is the *material* region; its boundary is the
surface a depth camera sees. Conventions, for every solid:

* ``sdf(p)``: signed distance of points ``p`` (N, 3) to the surface, positive in free space
  (outside the material), negative inside. Exact on the free side; inside the material it is
  exact for the convex pieces and a lower bound of the penetration depth for unions.
* ``enter(o, d)``: ray parameter ``s >= 0`` of the first point of ``o + s d`` inside the
  material, ``inf`` when the ray never enters it. ``o`` is (3,) or (N, 3), ``d`` is (N, 3) and
  need not be unit length (``s`` is in units of ``|d|``). A ray starting inside gives 0.

Everything is vectorised over rays and points; there are no per-pixel Python loops.
"""
from __future__ import annotations

import numpy as np

_EPS = 1e-12


def _rows(a) -> np.ndarray:
    return np.atleast_2d(np.asarray(a, dtype=np.float64))


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


class Solid:
    """Base class: material region with an exact ray entry and a signed distance."""

    def sdf(self, p) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def enter(self, o, d) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError


class HalfSpace(Solid):
    """Material where ``n . (x - point) < 0``; the surface is the plane through ``point``
    with unit outward normal ``n`` (pointing into free space)."""

    def __init__(self, normal, point):
        self.n = _unit(normal)
        self.c = float(self.n @ np.asarray(point, dtype=np.float64))

    def sdf(self, p):
        return _rows(p) @ self.n - self.c

    def enter(self, o, d):
        f0 = _rows(o) @ self.n - self.c
        nd = _rows(d) @ self.n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(nd < -_EPS, -f0 / nd, np.inf)
        s = np.where(f0 <= 0, 0.0, s)
        return np.broadcast_to(s, (max(len(f0), len(nd)),)).copy()


class Convex(Solid):
    """Intersection of half-spaces (a convex polyhedron, possibly unbounded).

    The ray entry is exact (Cyrus-Beck clipping). The signed distance is exact for one or two
    planes at any angle (a plane, a wedge: a ledge step or a ridge) and inside the material;
    outside a polyhedron of three or more planes it is the max-plane lower bound.
    """

    def __init__(self, planes):
        self.planes = list(planes)
        if not self.planes:
            raise ValueError("Convex needs at least one HalfSpace")

    def enter(self, o, d):
        o, d = _rows(o), _rows(d)
        n = max(len(o), len(d))
        lo = np.zeros(n)
        hi = np.full(n, np.inf)
        for h in self.planes:
            f0 = np.broadcast_to(o @ h.n - h.c, (n,))
            nd = np.broadcast_to(d @ h.n, (n,))
            with np.errstate(divide="ignore", invalid="ignore"):
                s = -f0 / nd
            lo = np.where(nd < -_EPS, np.maximum(lo, s), lo)
            hi = np.where(nd > _EPS, np.minimum(hi, s), hi)
            # Parallel to the plane and outside it: never enters.
            lo = np.where((np.abs(nd) <= _EPS) & (f0 > 0), np.inf, lo)
        return np.where(lo <= hi, lo, np.inf)

    def sdf(self, p):
        p = _rows(p)
        ds = np.stack([h.sdf(p) for h in self.planes])
        out = ds.max(axis=0)
        if len(self.planes) != 2:
            return out
        (h1, h2), (d1, d2) = self.planes, ds
        c12 = float(h1.n @ h2.n)
        # Outside: the nearest surface point is on face 1, on face 2 or on the edge line.
        face1 = np.where(d2 - d1 * c12 <= 0, np.abs(d1), np.inf)
        face2 = np.where(d1 - d2 * c12 <= 0, np.abs(d2), np.inf)
        e = np.cross(h1.n, h2.n)
        if np.linalg.norm(e) < 1e-9:  # parallel planes: the max is exact
            return out
        e = e / np.linalg.norm(e)
        # A point on the edge line: solve n1.x = c1, n2.x = c2, e.x = 0.
        x0 = np.linalg.solve(np.stack([h1.n, h2.n, e]), [h1.c, h2.c, 0.0])
        r = p - x0
        edge = np.linalg.norm(r - np.outer(r @ e, e), axis=1)
        outside = np.minimum(np.minimum(face1, face2), edge)
        return np.where(out > 0, outside, out)


class Ball(Solid):
    """Material inside the sphere of ``radius`` (m) around ``center``."""

    def __init__(self, center, radius):
        self.center = np.asarray(center, dtype=np.float64)
        self.r = float(radius)

    def sdf(self, p):
        return np.linalg.norm(_rows(p) - self.center, axis=1) - self.r

    def _roots(self, o, d):
        oc = _rows(o) - self.center
        d = _rows(d)
        a = np.einsum("ij,ij->i", d, d)
        if len(oc) == 1:  # one origin for all rays (a camera): cheaper products
            b = d @ oc[0]
            c = float(oc[0] @ oc[0]) - self.r**2
        else:
            b = np.einsum("ij,ij->i", oc, d)
            c = np.einsum("ij,ij->i", oc, oc) - self.r**2
        disc = b * b - a * c
        sq = np.sqrt(np.maximum(disc, 0.0))
        with np.errstate(invalid="ignore"):
            s0 = np.where(disc >= 0, (-b - sq) / a, np.inf)
            s1 = np.where(disc >= 0, (-b + sq) / a, -np.inf)
        return s0, s1

    def enter(self, o, d):
        s0, s1 = self._roots(o, d)
        return np.where(s1 < 0, np.inf, np.maximum(s0, 0.0))

    def exit(self, o, d):
        """Ray parameter where the ray leaves the ball (``-inf`` when it misses)."""
        return self._roots(o, d)[1]


class Union(Solid):
    """Union of solids: the first entry of the union is the earliest entry of any part, and
    the free-side distance is the smallest part distance (exact)."""

    def __init__(self, parts):
        self.parts = list(parts)

    def enter(self, o, d):
        return np.min(np.stack([s.enter(o, d) for s in self.parts]), axis=0)

    def sdf(self, p):
        return np.min(np.stack([s.sdf(p) for s in self.parts]), axis=0)


class PlaneMinusBall(Solid):
    """A half-space with a spherical cavity cut out: a bowl in a table.

    Material = ``plane`` half-space minus ``ball``. Exact ray entry for rays that start in free
    space above the plane, exact signed distance everywhere (the nearest surface point is on
    the flat part, on the spherical part or on the rim circle).
    """

    def __init__(self, plane: HalfSpace, ball: Ball):
        self.plane, self.ball = plane, ball
        h = float(plane.sdf(ball.center)[0])  # height of the ball centre above the plane
        if abs(h) >= ball.r:
            raise ValueError("the ball does not cut the plane")
        self.h = h
        self.rim_center = ball.center - h * plane.n
        self.rim_r = float(np.sqrt(ball.r**2 - h * h))

    def enter(self, o, d):
        s_plane = self.plane.enter(o, d)
        s_exit = self.ball.exit(o, d)
        q_in_ball = np.zeros_like(s_plane, dtype=bool)
        fin = np.isfinite(s_plane)
        if fin.any():
            o2, d2 = _rows(o), _rows(d)
            q = (o2 if len(o2) == 1 else o2[fin]) + s_plane[fin, None] * d2[fin]
            q_in_ball[fin] = self.ball.sdf(q) < 0
        return np.where(q_in_ball, np.maximum(s_plane, s_exit), s_plane)

    def sdf(self, p):
        p = _rows(p)
        n = self.plane.n
        dp = self.plane.sdf(p)
        r = p - self.ball.center
        rn = np.linalg.norm(r, axis=1)
        db = rn - self.ball.r
        inside = (dp < 0) & (db > 0)
        # Flat part: foot of the perpendicular lies outside the rim circle.
        foot = p - dp[:, None] * n
        rho_foot = np.linalg.norm((foot - self.rim_center) - np.outer((foot - self.rim_center) @ n, n), axis=1)
        flat = np.where(rho_foot >= self.rim_r, np.abs(dp), np.inf)
        # Spherical part: radial projection lies below the plane.
        with np.errstate(invalid="ignore", divide="ignore"):
            proj = self.ball.center + r * (self.ball.r / np.maximum(rn, _EPS))[:, None]
        sph = np.where(self.plane.sdf(proj) <= 0, np.abs(db), np.inf)
        # Rim circle.
        w = p - self.rim_center
        axial = w @ n
        rho = np.linalg.norm(w - np.outer(axial, n), axis=1)
        rim = np.hypot(rho - self.rim_r, axial)
        dist = np.minimum(np.minimum(flat, sph), rim)
        return np.where(inside, -dist, dist)
