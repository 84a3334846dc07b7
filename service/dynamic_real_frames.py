"""Real depth frames moved at a known speed, with their true surface at every instant
(dissertation ch. 6 on real data; used by ``service/dynamic_real.py``).

A real depth image (a recording's first frame, millimetres, 0 = no data) is the scene at
t = 0, in its camera's frame (camera at the origin looking along +z, metres). The scene then
moves rigidly, p(t) = R(t) p + c(t):

* ``toward``: translated along -z (toward the camera) at ``speed``: every surface point's depth
  drops by speed * t;
* ``sideways``: translated along +x (parallel to the image plane) at ``speed``;
* ``rocking``: rotated about an axis parallel to the image's y axis through a hinge ``HINGE``
  m to the side of the anchor point (a platform rocking on a mixer, fig. 3.10), at the rate
  that moves the anchor toward the camera at ``speed``;

and, given a ``stop`` time, halts there (a stroke of known length: the hold case of
``dynamic_real``).

The frame the camera sees at t is the real cloud (its valid pixels) moved and re-projected
into the camera with a depth test (the nearest point per pixel wins), quantised as the
recording was (``depth_steps``: whole codes, and a disparity camera's levels): the real holes, clutter and edges move with the scene, and the re-projection
adds the holes a moving scene opens (one-pixel gaps between two pixels of one surface are
closed, ``close_gaps``: a surface coming closer spreads over more pixels). Each moved point
lands between pixel centres; the pixel it lands in gets the depth at which the pixel's ray
crosses the true surface (the triangles around the point, moved with it), as a camera samples
a surface along its rays. Keeping the point's own depth instead puts it off the surface by its
sideways offset times the surface's slope, and shifts every depth of the image by the same
fraction of a code (the recording's depths are whole millimetres), so that the quantisation
steps the whole surface at once: it would appear to move by 3, 3 and 4 mm in three frames
that each moved it 3.3 mm.

Only the scene within ``KEEP`` of the contact point (and what is nearer the camera than it) is
kept: the evaluation's workspace lies within. The true surface is the real depth image,
dequantised (``DepthSteps.surface``: smoothed, each depth kept within half a step of the
recorded one, so that the recording is this surface as its camera quantised it; the moved
scene is quantised again where the rays sample it, as a camera would, not in unison; a
disparity camera's levels stay at their depths while the surface moves through them: moving
the recorded staircase with the scene would make its treads slide under a proxy as no real
camera's do), with its small holes filled
(nearest valid pixel within ``FILL_PX`` pixels: the warping-hole grid of a registered image),
triangulated (``depth_mesh``: two triangles per 2 x 2 block of pixels whose depths agree
within ``JUMP`` of their depth; depth steps are edges, not surface). Its signed distance to a
point q at t is the exact distance of R(t)^T (q - c(t)) to that mesh at t = 0, negative behind
it: further along the camera's ray than the closest surface point (a foreground object between
the camera and the point does not make it "behind"), and its own ray blocked by the surface (a
point beside a hole or in a gap between objects, with the surface behind it, is in front).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError
from pointfence.kernels.frame import DepthFrame

from .depth_mesh import MeshDistance, depth_blocks, depth_triangles, depth_vertices
from .depth_steps import DepthSteps

#: pixels a hole is filled across for the true surface
FILL_PX = 3
#: relative depth step (of the depth) that separates two surfaces (an edge) in the true surface
JUMP = 0.02
#: hinge of the rocking motion: this far (m) from the anchor along the camera's +x axis
HINGE = 0.1
#: the scene kept around the contact point (m): the true surface and the moving cloud beyond it
#: (the evaluation's workspace lies within) are left out, except what is nearer the camera
KEEP = 0.3
MOTIONS = ("toward", "sideways", "rocking")


def load_real(frames, index: int = 0) -> tuple[np.ndarray, Camera]:
    """(depth uint16 (H, W) in mm codes, camera at the origin) of frame ``index`` of a
    recording: a directory of 16-bit depth images with intrinsics (any layout
    ``pointfence.service.sources.recorded`` reads: 7-Scenes, tsdf-fusion, PCL grabber) or a
    single recording file it reads."""
    from pointfence.service.sources.recorded import RecordedSource

    path = Path(frames)
    if not path.exists():
        raise InputError(f"--frames {frames}: no such file or directory; give a directory of 16-bit depth images "
                         "with their intrinsics (e.g. ../shared/data/apc_shelfbin_50f)")
    src = RecordedSource(path, loop=False, cache=False)
    if not 0 <= index < len(src):
        raise InputError(f"--frames {frames}: frame {index} asked for; the recording has {len(src)} frames")
    depth, _, _ = src.load(index)
    return np.asarray(depth, np.uint16), src.camera.with_pose(np.eye(4))


def deproject(depth_m: np.ndarray, cam: Camera, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) of pixel coordinates (u, v) at depths ``depth_m`` (m)."""
    return np.stack([(u - cam.cx) / cam.fx * depth_m, (v - cam.cy) / cam.fy * depth_m, depth_m], axis=-1)


def fill_holes(depth_m: np.ndarray, px: int = FILL_PX) -> np.ndarray:
    """Depth (m) with every hole within ``px`` pixels of a valid pixel given that pixel's depth."""
    from scipy import ndimage

    hole = depth_m <= 0
    if not hole.any() or hole.all():
        return depth_m.copy()
    dist, (iy, ix) = ndimage.distance_transform_edt(hole, return_indices=True)
    out = depth_m[iy, ix]
    out[dist > px] = 0.0
    return out


#: the triangles of the true surface around pixel (0, 0): (block row, block column, triangle) of
#: the 2 x 2 pixel blocks (``depth_mesh``: A B / C D, triangles ABD = 0 and ADC = 1) that have it
#: as a corner
RING = ((0, 0, 0), (0, 0, 1), (0, -1, 0), (-1, 0, 1), (-1, -1, 0), (-1, -1, 1))


def ray_depth(tri: np.ndarray, cam: Camera, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Depth (N,) m at which the rays of pixels (u, v) first cross triangles ``tri`` (N, K, 3,
    3, camera frame; NaN: none); ``z`` (N,) where a ray crosses none of its K."""
    d = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones(len(u))], axis=1)
    best = np.full(len(u), np.inf)
    for k in range(tri.shape[1]):
        A, B, C = tri[:, k, 0], tri[:, k, 1], tri[:, k, 2]
        e1, e2 = B - A, C - A
        pv = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, pv)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = np.einsum("ij,ij->i", -A, pv) * inv
        q = np.cross(-A, e1)
        w = np.einsum("ij,ij->i", d, q) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (s >= -1e-9) & (w >= -1e-9) & (s + w <= 1 + 1e-9) & (t > 0)
        best = np.where(hit & (t < best), t, best)
    return np.where(np.isfinite(best), best, z)


def close_gaps(img: np.ndarray, win: np.ndarray, tri: np.ndarray, cam: Camera, steps: DepthSteps) -> None:
    """Fill, in place, the empty pixels of ``img`` (depth codes, (H, W)) between two drawn ones
    (left and right, else above and below) where the pixel's ray crosses the true surface around
    either neighbour's point: the one-pixel gaps a surface coming closer opens between its
    re-projected pixels. ``win`` (H, W): the index into ``tri`` (N, K, 3, 3: each drawn point's
    triangles, camera frame) of the point drawn in each pixel, -1 for none; ``steps``: the
    camera's depth levels."""
    for axis in (1, 0):
        lo = np.roll(win, 1, axis=axis)
        hi = np.roll(win, -1, axis=axis)
        gap = (win < 0) & (lo >= 0) & (hi >= 0)
        if axis == 1:
            gap[:, [0, -1]] = False
        else:
            gap[[0, -1], :] = False
        r, c = np.nonzero(gap)
        if not r.size:
            continue
        both = np.concatenate([tri[lo[r, c]], tri[hi[r, c]]], axis=1)
        z = ray_depth(both, cam, c.astype(np.float64), r.astype(np.float64), np.zeros(r.size))
        hit = z > 0
        img[r[hit], c[hit]] = np.clip(steps.quantize(z[hit]), 1, min(cam.max_code, 65535) - 1)
        win[r[hit], c[hit]] = lo[r[hit], c[hit]]


@dataclass(frozen=True)
class Motion:
    """A rigid motion of the scene at constant speed: kind (``MOTIONS``), the anchor's speed
    (m/s), the anchor (camera frame, m), and the time ``stop`` (s) at which the scene halts
    where it is (None: it moves throughout)."""

    kind: str
    speed: float
    anchor: tuple
    stop: float | None = None

    def __post_init__(self):
        if self.kind not in MOTIONS:
            raise InputError(f"motion {self.kind!r}; expected one of {', '.join(MOTIONS)}")
        if not (math.isfinite(self.speed) and self.speed >= 0):
            raise InputError(f"motion speed = {self.speed!r}; expected a finite speed >= 0 m/s")
        if self.stop is not None and not (math.isfinite(self.stop) and self.stop >= 0):
            raise InputError(f"motion stop = {self.stop!r}; expected a finite time >= 0 s, or None (never stops)")

    def moving(self, t: float) -> bool:
        """Whether the scene still moves at time t (s)."""
        return self.stop is None or t < self.stop

    def _moved_for(self, t: float) -> float:
        """How long (s) the scene has moved by time t."""
        return float(t) if self.stop is None else min(float(t), self.stop)

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R (3, 3), c (3,)): the scene's point p is at R p + c at time t (s)."""
        t = self._moved_for(t)
        if self.kind == "toward":
            return np.eye(3), np.array([0.0, 0.0, -self.speed * t])
        if self.kind == "sideways":
            return np.eye(3), np.array([self.speed * t, 0.0, 0.0])
        a = -self.speed / HINGE * t  # about +y through the hinge: the anchor moves toward -z
        ca, sa = math.cos(a), math.sin(a)
        R = np.array([[ca, 0.0, sa], [0.0, 1.0, 0.0], [-sa, 0.0, ca]])
        hinge = np.asarray(self.anchor, np.float64) + [HINGE, 0.0, 0.0]
        return R, hinge - R @ hinge

    def velocity(self, points: np.ndarray, t: float) -> np.ndarray:
        """True velocity (N, 3) m/s of the moved scene points ``points`` (at their place at t)."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        if not self.moving(t):
            return np.zeros_like(p)
        if self.kind == "toward":
            return np.broadcast_to([0.0, 0.0, -self.speed], p.shape).copy()
        if self.kind == "sideways":
            return np.broadcast_to([self.speed, 0.0, 0.0], p.shape).copy()
        w = np.array([0.0, -self.speed / HINGE, 0.0])
        hinge = np.asarray(self.anchor, np.float64) + [HINGE, 0.0, 0.0]
        return np.cross(w, p - hinge)


class MovingRealFrame:
    """One real depth image moving by ``Motion``; ``render(t)`` is the frame the camera sees
    at t, ``distance(q, t)`` the signed distance (m) of points q (N, 3) to the true surface."""

    def __init__(self, depth: np.ndarray, cam: Camera, name: str = "real", keep: float = KEEP):
        self.name = name
        z = np.asarray(depth, np.float64) * cam.depth_scale
        z[(depth >= min(cam.max_code, 65535))] = 0.0
        h, w = z.shape
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        ok = z > 0
        if np.count_nonzero(ok) < 100:
            raise InputError(f"{name}: {np.count_nonzero(ok)} valid depth pixels; expected a real depth image")
        self.steps = DepthSteps.fit_frames([np.asarray(depth)], cam.depth_scale, cam.max_code)
        # the camera knows its steps (``Camera.near_reading`` uses them where a run turns it on)
        self.cam = cam = replace(cam, depth_step_inv=self.steps.inv_step)
        z = self.steps.surface(z)
        self.depth_m = z
        self.valid_fraction = float(np.mean(ok))
        self.filled = fill_holes(z)
        self.contact = self._find_anchor()
        cloud = deproject(z[ok], cam, u[ok], v[ok])
        kept = self._kept(cloud, keep)
        self.cloud = cloud[kept]
        self._pixels = np.flatnonzero(ok.ravel())[kept]        # each cloud point's pixel
        self._grid = depth_vertices(self.filled, cam)           # the true surface's vertices and blocks
        self._blocks = depth_blocks(self.filled, JUMP)
        tris = depth_triangles(self.filled, cam, JUMP)
        self.mesh = MeshDistance(tris[np.linalg.norm(tris.mean(1) - self.contact, axis=1) < keep])

    def _ring_triangles(self, pixels: np.ndarray) -> np.ndarray:
        """The true surface's triangles (N, len(RING), 3, 3, camera frame at t = 0; NaN where
        there is none) around each of the image's flat pixel indices ``pixels``."""
        h, w = self.filled.shape
        corners = ((0, 1, 3), (0, 3, 2))                                       # ABD, ADC of A B / C D
        r, c = np.divmod(pixels, w)
        out = np.full((len(pixels), len(RING), 3, 3), np.nan)
        for k, (dr, dc, t) in enumerate(RING):
            br, bc = r + dr, c + dc
            inside = (br >= 0) & (br < h - 1) & (bc >= 0) & (bc < w - 1)
            i = np.flatnonzero(inside)
            i = i[self._blocks[br[i], bc[i]]]
            for j, corner in enumerate(corners[t]):
                out[i, k, j] = self._grid[br[i] + corner // 2, bc[i] + corner % 2]
        return out

    def _kept(self, p: np.ndarray, keep: float) -> np.ndarray:
        """Points within ``keep`` of the contact point or nearer the camera than it (occluders)."""
        return (np.linalg.norm(p - self.contact, axis=1) < keep) | (p[:, 2] < self.contact[2])

    def anchor(self) -> np.ndarray:
        """The contact point (camera frame, m; see ``_find_anchor``)."""
        return self.contact.copy()

    def _find_anchor(self, window: int = 30) -> np.ndarray:
        """A contact point near the image centre (camera frame, m): the valid pixel closest to
        the principal point whose filled neighbourhood (``window`` px each side) is at least
        90 % valid and one surface (no step over ``JUMP`` of the depth between neighbours)."""
        from scipy import ndimage

        z = self.filled
        size = 2 * window + 1
        ok = z > 0
        cover = ndimage.uniform_filter(ok.astype(np.float64), size=size)
        step = np.zeros_like(ok)
        dx = np.abs(np.diff(z, axis=1)) > JUMP * np.maximum(z[:, 1:], z[:, :-1])
        dy = np.abs(np.diff(z, axis=0)) > JUMP * np.maximum(z[1:], z[:-1])
        step[:, 1:] |= dx
        step[1:] |= dy
        edge = ndimage.maximum_filter(step.astype(np.uint8), size=size) > 0
        good = ok & (cover >= 0.9) & ~edge
        if not good.any():
            raise InputError(f"{self.name}: no smooth patch of {size} x {size} px in the image to touch")
        v, u = np.nonzero(good)
        i = int(np.argmin((u - self.cam.cx) ** 2 + (v - self.cam.cy) ** 2))
        return deproject(np.array(z[v[i], u[i]]), self.cam, np.array(float(u[i])), np.array(float(v[i])))

    def render(self, motion: Motion, t: float, seq: int) -> DepthFrame:
        """The frame (uint16 mm, stamped t) the camera sees of the scene moved to time t."""
        R, c = motion.pose(t)
        p = np.einsum("ij,kj->ik", self.cloud, R) + c
        cam = self.cam
        front = p[:, 2] > cam.z_min
        p = p[front]
        u = np.rint(p[:, 0] / p[:, 2] * cam.fx + cam.cx).astype(np.int64)
        v = np.rint(p[:, 1] / p[:, 2] * cam.fy + cam.cy).astype(np.int64)
        inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        keep = np.flatnonzero(front)[inside]
        tri = np.einsum("nkij,lj->nkil", self._ring_triangles(self._pixels[keep]), R) + c
        z = ray_depth(tri, cam, u[inside], v[inside], p[inside, 2])
        lin = v[inside] * cam.width + u[inside]
        code = np.clip(self.steps.quantize(z), 1, min(cam.max_code, 65535) - 1).astype(np.int64)
        order = np.argsort(lin * 65536 + code, kind="stable")       # per pixel, nearest first
        lin, code = lin[order], code[order]
        first = np.ones(lin.size, bool)
        first[1:] = lin[1:] != lin[:-1]
        img = np.zeros(cam.width * cam.height, np.uint16)
        win = np.full(cam.width * cam.height, -1, np.int64)
        img[lin[first]] = code[first]
        win[lin[first]] = order[first]
        img, win = img.reshape(cam.height, cam.width), win.reshape(cam.height, cam.width)
        close_gaps(img, win, tri, cam, self.steps)
        return DepthFrame(cam.name, img, float(t), int(seq))

    def distance(self, motion: Motion, q, t: float) -> np.ndarray:
        """Signed distance (N,) m of points q (N, 3, camera frame) to the true surface at t."""
        R, c = motion.pose(t)
        q0 = (np.asarray(q, np.float64).reshape(-1, 3) - c) @ R  # R^T (q - c), row-wise
        d = self.mesh.signed(q0)
        behind = np.flatnonzero(d < 0)
        if behind.size:
            # behind also needs the point's own ray to be blocked: the nearest triangle alone
            # calls a point beside a hole's boundary, or in a gap between two objects with the
            # surface far behind it along its ray, "behind" by a fraction of a millimetre of depth
            # (its sign then flips between ticks a millimetre apart)
            hidden = self._occluded(q0[behind])
            d[behind[~hidden]] *= -1.0
        return d

    def _occluded(self, q0: np.ndarray) -> np.ndarray:
        """Whether each point (M, 3, the frame at t = 0) is further along its camera ray than
        the surface: deeper than the nearest (filled) depth within a pixel of its projection
        (a pixel each way: on a steep wall a sub-millimetre penetration is kept)."""
        cam, z = self.cam, self.filled
        h, w = z.shape
        out = np.zeros(len(q0), bool)
        for k, p in enumerate(q0):
            if p[2] <= 0:
                continue
            u, v = int(round(p[0] / p[2] * cam.fx + cam.cx)), int(round(p[1] / p[2] * cam.fy + cam.cy))
            win = z[max(v - 1, 0):max(min(v + 2, h), 0), max(u - 1, 0):max(min(u + 2, w), 0)]
            win = win[win > 0]
            out[k] = bool(win.size) and p[2] > float(win.min())
        return out
