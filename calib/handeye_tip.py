"""Finding the tool tip in a depth frame: a small ball on the tip, fitted as a sphere.

The tip carries a ball of known radius (a bead, a 3-D printed sphere). Its pixels are found
either by colour (``find_ball(..., color=image, lo, hi)``: a matte coloured ball in the registered
colour image, the largest connected blob in range) or, depth only, as the blob around the pixel
nearest the camera (``color=None``: mount the ball so that it is the closest thing to the camera,
e.g. the tool pointing towards it). The blob's rim pixels (mixed depth at the silhouette) are
eroded away; the remaining pixels are deprojected through the camera (its distortion included) and
the centre c minimising sum (|p - c| - r)^2 with the radius r fixed is the tip (camera frame, m).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.optimize import least_squares

from pointfence.kernels.camera import Camera

#: fewest ball pixels (after erosion) for a fit
MIN_PIXELS = 20


@dataclass
class BallFit:
    """``center`` (3,) camera frame, m; ``rms`` the points' r.m.s. distance from the sphere (m);
    ``pixels`` used."""

    center: np.ndarray
    rms: float
    pixels: int


def _points(depth: np.ndarray, camera: Camera, mask: np.ndarray, rays: np.ndarray) -> np.ndarray:
    z = depth[mask].astype(np.float64) * camera.depth_scale
    r = rays[mask].astype(np.float64)
    return np.stack([r[:, 0] * z, r[:, 1] * z, z], axis=1)


def _valid(depth: np.ndarray, camera: Camera) -> np.ndarray:
    z = depth.astype(np.float64) * camera.depth_scale
    return (depth > 0) & (depth < camera.max_code) & (z >= camera.z_min) & (z <= camera.z_max)


def _largest_blob(mask: np.ndarray, seed: Optional[tuple] = None) -> np.ndarray:
    """The connected component of ``mask`` holding ``seed`` (or the largest one)."""
    import cv2

    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(mask, bool)
    k = labels[seed] if seed is not None else 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == k if k > 0 else np.zeros_like(mask, bool)


def _erode(mask: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def fit_sphere(points: np.ndarray, radius: float) -> BallFit:
    """Centre of the sphere of ``radius`` (m) through ``points`` (N, 3) seen from the origin
    (the camera): the initial centre is the points' centroid pushed ``radius`` away from the camera."""
    P = np.asarray(points, dtype=np.float64)
    c0 = P.mean(axis=0)
    c0 = c0 + radius * 0.6 * c0 / np.linalg.norm(c0)
    sol = least_squares(lambda c: np.linalg.norm(P - c, axis=1) - radius, c0, method="lm")
    res = np.linalg.norm(P - sol.x, axis=1) - radius
    return BallFit(sol.x, float(np.sqrt(np.mean(res ** 2))), len(P))


def find_ball(depth: np.ndarray, camera: Camera, radius: float, color: Optional[np.ndarray] = None,
              lo=(150, 0, 0), hi=(255, 90, 90), rays: Optional[np.ndarray] = None) -> tuple:
    """(BallFit or None, why) for the tip ball in one frame; ``lo``/``hi`` inclusive RGB bounds of
    the ball's colour in ``color`` (BGR as OpenCV reads it). ``rays``: ``camera.ray_table()``,
    reused over many frames."""
    rays = camera.ray_table() if rays is None else rays
    valid = _valid(depth, camera)
    if not valid.any():
        return None, "no valid depth"
    if color is not None:
        if color.ndim != 3:
            return None, "the colour image is grey; --tip color needs a colour image (or use --tip nearest)"
        rgb = color[..., ::-1]
        inside = np.all((rgb >= np.asarray(lo)) & (rgb <= np.asarray(hi)), axis=-1) & valid
        blob = _largest_blob(inside)
        what = f"pixels of the ball's colour (RGB {list(lo)}..{list(hi)})"
    else:
        z = np.where(valid, depth.astype(np.float64) * camera.depth_scale, np.inf)
        seed = np.unravel_index(int(np.argmin(z)), z.shape)
        xyz = np.zeros(depth.shape + (3,))
        xyz[valid] = _points(depth, camera, valid, rays)
        p0 = xyz[seed]
        near = valid & (np.linalg.norm(xyz - p0, axis=-1) <= 2.2 * radius)
        blob = _largest_blob(near, seed)
        what = "pixels around the nearest depth"
    core = _erode(blob)
    if core.sum() < MIN_PIXELS:
        return None, f"{int(blob.sum())} {what} ({int(core.sum())} inside the rim); at least {MIN_PIXELS} needed"
    return fit_sphere(_points(depth, camera, core, rays), radius), ""
