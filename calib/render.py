"""Synthetic images of planar targets (checkerboards, ArUco/AprilTag markers) with exact ground truth.

``render_planes`` ray-casts textured rectangles through a ``Camera`` (intrinsics and its
Brown-Conrady distortion, via ``Camera.ray_table``), supersampled and box-filtered so edges are
anti-aliased like a real lens. Used by the tests and by ``pointfence calib ... --demo``.

Plane frames: a texture of W x H pixels covers a rectangle ``size = (w, h)`` metres in its
plane's local frame, x along the texture's columns, y along its rows, z = x cross y.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError

from .common import inv_T, make_T


@dataclass
class TexturedPlane:
    """A textured rectangle: ``T_world_plane`` (local frame -> world), ``texture`` uint8 (H, W),
    ``size`` (w, h) metres."""

    T_world_plane: np.ndarray
    texture: np.ndarray
    size: tuple


def supersampled_rays(camera: Camera, supersample: int = 2) -> np.ndarray:
    """Rays (H*s, W*s, 3) with unit z of the sub-pixels of ``camera`` (distortion included)."""
    s = int(supersample)
    hi = replace(camera, width=camera.width * s, height=camera.height * s, fx=camera.fx * s, fy=camera.fy * s,
                 cx=camera.cx * s + (s - 1) / 2.0, cy=camera.cy * s + (s - 1) / 2.0)
    rays = hi.ray_table().astype(np.float64)  # undistorted x/z, y/z
    return np.concatenate([rays, np.ones(rays.shape[:2] + (1,))], axis=-1)


def render_planes(camera: Camera, T_world_cam: np.ndarray, planes, background: int = 110, supersample: int = 2,
                  noise_std: float = 0.0, rng: Optional[np.random.Generator] = None,
                  rays: Optional[np.ndarray] = None) -> np.ndarray:
    """A uint8 grey image (camera.height, camera.width) of ``planes`` seen from ``T_world_cam``;
    ``rays`` = ``supersampled_rays(camera, supersample)`` when rendering many views."""
    import cv2

    s = int(supersample)
    d = supersampled_rays(camera, s) if rays is None else rays
    img = np.full(d.shape[:2], float(background))
    zbuf = np.full(d.shape[:2], np.inf)
    T_cam_world = inv_T(np.asarray(T_world_cam, dtype=np.float64))
    for pl in planes:
        T = T_cam_world @ pl.T_world_plane
        o, ex, ey, n = T[:3, 3], T[:3, 0], T[:3, 1], T[:3, 2]
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (n @ o) / denom
        p = lam[..., None] * d - o
        x, y = p @ ex, p @ ey
        w, h = pl.size
        tex = pl.texture.astype(np.float32)
        th, tw = tex.shape
        inside = (lam > 0) & (x >= 0) & (x <= w) & (y >= 0) & (y <= h) & (lam < zbuf)
        mx = (x / w * tw - 0.5).astype(np.float32)
        my = (y / h * th - 0.5).astype(np.float32)
        val = cv2.remap(tex, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        img = np.where(inside, val, img)
        zbuf = np.where(inside, lam, zbuf)
    img = img.reshape(camera.height, s, camera.width, s).mean(axis=(1, 3))
    if noise_std > 0:
        rng = np.random.default_rng(0) if rng is None else rng
        img = img + rng.normal(0.0, noise_std, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


# -- checkerboards -------------------------------------------------------------------------
def checkerboard(cols: int, rows: int, square: float, px: int = 40):
    """(TexturedPlane at identity, object points (cols*rows, 3) of the inner corners in the
    plane frame) of a board with ``cols`` x ``rows`` inner corners, squares of ``square`` m and a
    white margin of one square."""
    nx, ny = cols + 1, rows + 1
    tex = np.full(((ny + 2) * px, (nx + 2) * px), 255, np.uint8)
    for j in range(ny):
        for i in range(nx):
            if (i + j) % 2 == 0:
                tex[(j + 1) * px:(j + 2) * px, (i + 1) * px:(i + 2) * px] = 0
    gx, gy = np.meshgrid(np.arange(1, cols + 1), np.arange(1, rows + 1))
    obj = np.stack([(gx.ravel() + 1) * square, (gy.ravel() + 1) * square, np.zeros(gx.size)], axis=1)
    return TexturedPlane(np.eye(4), tex, ((nx + 2) * square, (ny + 2) * square)), obj


def checkerboard_views(camera: Camera, cols: int = 9, rows: int = 6, square: float = 0.025, n: int = 12, seed: int = 0,
                       distance: float = 0.4, noise_std: float = 1.0):
    """``n`` images of a checkerboard at varied tilts; returns (images, list of T_cam_board)."""
    from scipy.spatial.transform import Rotation

    board, _ = checkerboard(cols, rows, square)
    w, h = board.size
    rng = np.random.default_rng(seed)
    rays = supersampled_rays(camera, 2)
    images, poses = [], []
    for k in range(n):
        # strong, varied tilts (about +-20..40 deg on both axes) pin the focal length down
        sx, sy = rng.choice([-1, 1], size=2)
        ang = np.radians([sx * rng.uniform(20, 40), sy * rng.uniform(20, 40), rng.uniform(-20, 20)])
        R = Rotation.from_euler("xyz", ang).as_matrix()
        center_board = np.array([w / 2, h / 2, 0.0])
        z = distance + rng.uniform(-0.08, 0.12)
        # spread the board over the image (corners included) so distortion is observed
        u, v = (k % 3 - 1) * 0.17 * camera.width, ((k // 3) % 3 - 1) * 0.15 * camera.height
        target = np.array([u / camera.fx * z, v / camera.fy * z, z])
        T_cam_board = make_T(R, target - R @ center_board)
        images.append(render_planes(camera, np.eye(4), [TexturedPlane(T_cam_board, board.texture, board.size)],
                                    noise_std=noise_std, rng=rng, rays=rays))
        poses.append(T_cam_board)
    return images, poses


# -- markers -------------------------------------------------------------------------------
def marker_plane(dictionary, marker_id: int, size: float, T_world_marker: np.ndarray, px_per_cell: int = 12) -> TexturedPlane:
    """An ArUco/AprilTag marker of side ``size`` m (the black square) with a white quiet zone of
    one ``size/4``, at ``T_world_marker`` (OpenCV marker frame: centre, x right, y up, z out)."""
    import cv2

    bits = dictionary.markerSize + 2
    side_px = bits * px_per_cell
    img = cv2.aruco.generateImageMarker(dictionary, int(marker_id), side_px, borderBits=1)
    margin = side_px // 4
    tex = np.full((side_px + 2 * margin,) * 2, 255, np.uint8)
    tex[margin:margin + side_px, margin:margin + side_px] = img
    full = size * tex.shape[0] / side_px
    # plane-local frame (x along columns, y along rows, z into the marker) in the marker frame
    T_marker_local = np.array([[1, 0, 0, -full / 2], [0, -1, 0, full / 2], [0, 0, -1, 0], [0, 0, 0, 1.0]])
    return TexturedPlane(np.asarray(T_world_marker, dtype=np.float64) @ T_marker_local, tex, (full, full))


def get_dictionary(name: str):
    import cv2

    key = str(name).upper()
    if not key.startswith("DICT_"):
        key = "DICT_" + key
    if not hasattr(cv2.aruco, key):
        names = [n for n in dir(cv2.aruco) if n.startswith("DICT_")]
        raise InputError(f"marker dictionary {name!r} unknown; expected one of {', '.join(names)}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, key))
