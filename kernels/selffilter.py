"""Robot self-filter (SPEC 6, dissertation 6.4): depth pixels that see the robot's own tool are
dropped before the frames reach the pipeline, so the tool never creates fixtures around itself.

The tool is a set of capsules (segment a-b, radius) in the world frame at the frame's capture
time, from the robot's kinematics and a tool model (``pointfence.service.robot.tool``). A pixel
is dropped (depth set to 0, "no reading") when the point it measures lies within
``radius + margin`` of a capsule; ``margin`` covers depth noise and the pose error between the
kinematics and the camera registration.

Why a filter on the frames rather than a stage inside every backend's pipeline: the result is
the same (a dropped pixel is a hole, exactly like an invalid reading, in every backend and in
the motion estimate), it needs no change to three kernel sets, and it is cheap: per capsule
only the image window that can see the capsule is tested: the capsule is the convex hull of its
two end balls, so the window is the union of theirs, each the bounding box of the projected
corners of the ball's bounding cube (a projection keeps convex hulls), widened to whole pixel
rows and columns through each row's and column's ray extent (rays precomputed per camera), so
distortion cannot hide a pixel from it. Each window pixel's reading is deprojected along its
ray and tested against the capsule by compiled code (``native/selffilter.c``) that runs without
Python's interpreter lock: the haptic loop never waits for a frame thread's filter. The frames
are copied only when a pixel is dropped.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from .camera import Camera
from .errors import InputError
from .frame import DepthFrame
from .yielding import checkpoint


@dataclass(frozen=True)
class Capsule:
    """Points within ``radius`` (m) of the segment ``a``-``b`` (world frame, m)."""

    a: tuple
    b: tuple
    radius: float

    def __post_init__(self):
        for key in ("a", "b"):
            v = np.asarray(getattr(self, key), dtype=np.float64).reshape(-1)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise InputError(f"capsule {key} = {getattr(self, key)!r}; expected 3 finite numbers (world m)")
            object.__setattr__(self, key, tuple(float(x) for x in v))
        if not (np.isfinite(self.radius) and self.radius >= 0):
            raise InputError(f"capsule radius = {self.radius!r}; expected a finite number >= 0 m")

    def distance(self, points) -> np.ndarray:
        """Distance (m) of points (N, 3) to the capsule's surface (negative inside)."""
        return segment_distance(points, self.a, self.b) - self.radius


def segment_distance(points, a, b) -> np.ndarray:
    """Distance of points (N, 3) to the segment a-b (float64)."""
    p = np.atleast_2d(np.asarray(points, dtype=np.float64))
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ab = b - a
    L2 = float(ab @ ab)
    t = np.zeros(len(p)) if L2 == 0 else np.clip((p - a) @ ab / L2, 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


_PIXEL_TEST = None


def _pixel_test():
    """The compiled per-capsule pixel test (``native/selffilter.c``: every pixel of a window
    whose point lies within reach of a segment), built on first use. It runs without the
    interpreter lock, beside the haptic loop that needs it."""
    global _PIXEL_TEST
    if _PIXEL_TEST is None:
        from pointfence.native.build import load_self_filter

        _PIXEL_TEST = load_self_filter().pf_selffilter_capsule
    return _PIXEL_TEST


_CUBE = np.array([(x, y, z) for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])


class SelfFilter:
    """Drops the pixels that see the tool, per camera of a rig.

    Args:
        cameras: the rig (``Camera`` objects; a frame's own ``T_world_cam`` wins when present).
        margin: extra clearance around every capsule (m), for depth noise and registration error.
    """

    def __init__(self, cameras: Sequence[Camera], margin: float = 0.003):
        if not (np.isfinite(margin) and margin >= 0):
            raise InputError(f"self-filter margin = {margin!r}; expected a finite number >= 0 m")
        self.margin = float(margin)
        self.cameras = {c.name: c for c in cameras}
        self._rays = {}
        self.removed = 0  # pixels dropped by the last apply()

    def _rays_of(self, cam: Camera):
        """(rays (H, W, 3) with z = 1, extents) of ``cam``; extents: each column's x range and
        each row's y range of the normalised rays."""
        r = self._rays.get(cam.name)
        if r is None:
            xy = cam.ray_table().astype(np.float64)
            rays = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], axis=2)  # z = 1: the ray parameter is the depth
            ext = (xy[:, :, 0].min(axis=0), xy[:, :, 0].max(axis=0), xy[:, :, 1].min(axis=1), xy[:, :, 1].max(axis=1))
            r = self._rays[cam.name] = (np.ascontiguousarray(rays), ext)
        return r

    @staticmethod
    def _window(ext, balls):
        """(row slice, column slice) of the pixels whose rays can pass through any of ``balls``
        ((center, radius), camera frame) or their convex hull; the whole image when one reaches
        behind the camera."""
        lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
        for center, bound in balls:
            corners = center + bound * _CUBE
            if np.any(corners[:, 2] <= 1e-6):
                return slice(None), slice(None)
            xy = corners[:, :2] / corners[:, 2:3]
            np.minimum(lo, xy.min(axis=0), out=lo)
            np.maximum(hi, xy.max(axis=0), out=hi)
        cmin, cmax, rmin, rmax = ext
        cols = np.flatnonzero((cmax >= lo[0]) & (cmin <= hi[0]))
        rows = np.flatnonzero((rmax >= lo[1]) & (rmin <= hi[1]))
        if not cols.size or not rows.size:
            return slice(0, 0), slice(0, 0)
        return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)

    def mask(self, frame: DepthFrame, capsules: Sequence[Capsule]) -> np.ndarray:
        """Boolean (H, W): pixels of ``frame`` whose measured point lies on the tool."""
        cam = self.cameras.get(frame.camera)
        if cam is None:
            raise InputError(f"self-filter: frame from unknown camera {frame.camera!r}; cameras: {sorted(self.cameras)}")
        rays, ext = self._rays_of(cam)
        T = np.asarray(frame.T_world_cam if frame.T_world_cam is not None else cam.T_world_cam, np.float64)
        R, t = T[:3, :3], T[:3, 3]
        depth = np.ascontiguousarray(frame.depth, np.uint16)
        out = np.zeros(depth.shape, bool)
        for c in capsules:
            checkpoint()
            a_c = R.T @ (np.asarray(c.a) - t)
            b_c = R.T @ (np.asarray(c.b) - t)
            reach = c.radius + self.margin
            # the capsule is the convex hull of its end balls, and its image the hull of theirs:
            # the window bounds both (a shaft seen end-on is small, its bounding sphere is not)
            rs, cs = self._window(ext, ((a_c, reach), (b_c, reach)))
            r0, r1, _ = rs.indices(depth.shape[0])
            c0, c1, _ = cs.indices(depth.shape[1])
            if r1 <= r0 or c1 <= c0:
                continue
            _pixel_test()(depth.ctypes.data, rays.ctypes.data, depth.shape[1], r0, r1, c0, c1, float(cam.depth_scale),
                          a_c.ctypes.data, b_c.ctypes.data, float(reach), out.ctypes.data)
        return out

    def apply(self, frames: Sequence[DepthFrame], capsules: Sequence[Capsule]) -> list:
        """The frames with every tool pixel's depth set to 0 (frames without any are passed on
        unchanged); ``removed`` counts the dropped pixels."""
        out, removed = [], 0
        for f in frames:
            m = self.mask(f, capsules) if capsules else None
            if m is None or not m.any():
                out.append(f)
                continue
            d = f.depth.copy()
            d[m] = 0
            removed += int(m.sum())
            out.append(replace(f, depth=d))
        self.removed = removed
        return out
