"""Synthetic hand-eye logs with known ground truth (``pointfence calib hand-eye --simulate``, tests).

A fixed camera (640x480, fx 575.8 px, about 0.7 m from the workspace) watches a robot move its
tool through N poses above a table (z = 0, world frame = robot base, metres):

* ``tip_log``: a ball of ``radius`` on the tool tip (at ``offset`` in the tip frame, red in the
  colour image) on a thin grey shaft; depth is ray cast exactly (``service.sources.geometry``)
  and given the camera's axial noise sigma_z = b Z^2 (b = 1.42e-3 /m, a Kinect-class sensor),
  then quantised to the depth unit (1 mm).
* ``marker_log``: an ArUco marker fixed on the tool at ``T_tip_marker``, turned 15-35 deg about a
  random axis from facing the camera at each pose, rendered anti-aliased with image noise
  (``calib.render``).

``pose_kind`` makes degenerate sets for tests: "varied" (default), "translation" (one
orientation for every pose), "line" (positions on one line), "axis" (turns about one axis only).
"""
from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

from pointfence.kernels.camera import Camera

from .common import inv_T, make_T

CENTER = np.array([0.0, 0.0, 0.10])   # middle of the poses' box (m, world)
HALF = np.array([0.12, 0.12, 0.06])   # half sizes of the box (m)


def sim_camera() -> tuple:
    """(Camera, true T_world_cam) of the simulated set-up."""
    from pointfence.service.sources.synthetic import look_at

    cam = Camera("cam0", 640, 480, 575.8, 575.8, 319.5, 239.5, depth_scale=0.001)
    return cam, look_at((0.35, -0.45, 0.55), (0.0, 0.0, 0.05))


def _positions(n: int, rng, kind: str) -> np.ndarray:
    if kind == "line":
        s = rng.uniform(-1, 1, n)
        return CENTER + s[:, None] * np.array([0.12, 0.06, 0.0])
    return CENTER + rng.uniform(-1, 1, (n, 3)) * HALF


def _turns(n: int, rng, kind: str, lo: float = 15.0, hi: float = 35.0) -> list:
    """Rotations to apply to a nominal orientation, per pose."""
    if kind == "translation":
        return [np.eye(3)] * n
    out = []
    for _ in range(n):
        axis = np.array([0.3, 0.2, 1.0]) if kind == "axis" else rng.normal(size=3)
        angle = np.radians(rng.uniform(lo, hi)) * rng.choice([-1, 1])
        out.append(Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix())
    return out


def _facing(direction) -> np.ndarray:
    """A rotation whose z axis is ``direction`` and whose x axis is horizontal."""
    z = np.asarray(direction, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
    return np.stack([x, np.cross(z, x), z], axis=1)


def _near_rays(cam: Camera, X: np.ndarray, points, margin: float) -> np.ndarray:
    """Flat indices of the pixels within the image box around the projections of ``points``
    (world, m) widened by ``margin`` (m at the points' depth): the only rays the tool can hit."""
    P = (np.asarray(points) - X[:3, 3]) @ X[:3, :3]
    u, v = cam.fx * P[:, 0] / P[:, 2] + cam.cx, cam.fy * P[:, 1] / P[:, 2] + cam.cy
    m = cam.fx * margin / P[:, 2].min() + 2
    u0, u1 = int(max(0, u.min() - m)), int(min(cam.width - 1, u.max() + m))
    v0, v1 = int(max(0, v.min() - m)), int(min(cam.height - 1, v.max() + m))
    if u0 > u1 or v0 > v1:
        return np.zeros(0, np.int64)
    vv, uu = np.mgrid[v0:v1 + 1, u0:u1 + 1]
    return (vv * cam.width + uu).ravel()


def tip_log(n: int = 16, seed: int = 0, radius: float = 0.012, offset=(0.0, 0.0, 0.0), noise_b: float = 1.42e-3,
            pose_kind: str = "varied", nearest: bool = False) -> dict:
    """A tip-ball log: {camera, T_world_cam, T_world_tip (n, 4, 4), depth, color, offset, radius}.
    ``nearest``: the shaft points away from the camera and there is no table (nothing else within
    the camera's range), so the ball is the nearest surface (for ``--tip nearest``); otherwise the
    shaft rises from the tip, tilted."""
    from pointfence.service.sources.geometry import Ball, HalfSpace
    from pointfence.service.sources.toolscene import CapsuleSolid

    rng = np.random.default_rng(seed)
    cam, X = sim_camera()
    o = np.asarray(offset, dtype=np.float64)
    rays = cam.ray_table().astype(np.float64).reshape(-1, 2)
    d_cam = np.concatenate([rays, np.ones((len(rays), 1))], axis=1)
    d_world = d_cam @ X[:3, :3].T
    eye = X[:3, 3]
    pos, turns = _positions(n, rng, pose_kind), _turns(n, rng, pose_kind, 15.0, 35.0)
    W, depth, color = [], [], []
    table_hits = HalfSpace((0, 0, 1), (0, 0, 0)).enter(eye, d_world)
    for p, Rt in zip(pos, turns):
        shaft_dir = (p - eye) / np.linalg.norm(p - eye) if nearest else np.array([0.0, 0.0, 1.0])
        R = Rt @ _facing(shaft_dir)                      # tip frame: z along the shaft, away from the tip
        if nearest and (R[:, 2] @ (p - eye)) < np.cos(np.radians(50)) * np.linalg.norm(p - eye):
            R = _facing(shaft_dir)
        W.append(make_T(R, p - R @ o))                    # the ball's centre is at W o = p
        ball = Ball(p, radius)
        shaft = CapsuleSolid(p, p + 0.15 * R[:, 2], 0.003)
        hits = np.full((3, len(d_world)), np.inf)
        if not nearest:                                   # no table: the ball must be the nearest surface
            hits[0] = table_hits
        near = _near_rays(cam, X, [p, p + 0.15 * R[:, 2]], radius + 0.005)
        for k, solid in ((1, ball), (2, shaft)):
            hits[k, near] = solid.enter(eye, d_world[near])
        which = np.argmin(hits, axis=0)
        z = hits[which, np.arange(len(which))]
        hit = np.isfinite(z)
        z = np.where(hit, z, 0.0)
        z = np.where(hit, z + rng.normal(0.0, 1.0, z.shape) * noise_b * z ** 2, 0.0)
        depth.append(np.clip(np.round(z / cam.depth_scale), 0, 65535).astype(np.uint16).reshape(cam.height, cam.width))
        rgb = np.array([[235, 235, 230], [200, 30, 30], [120, 120, 125]], np.float64)[which]
        rgb = np.clip(rgb + rng.normal(0.0, 3.0, rgb.shape), 0, 255).astype(np.uint8)
        color.append(rgb[:, ::-1].reshape(cam.height, cam.width, 3).copy())
    return {"camera": cam, "T_world_cam": X, "T_world_tip": np.array(W), "depth": depth, "color": color,
            "offset": o, "radius": radius}


def marker_log(n: int = 16, seed: int = 0, size: float = 0.05, marker_id: int = 7, dictionary: str = "DICT_4X4_50",
               T_tip_marker: Optional[np.ndarray] = None, pose_kind: str = "varied", noise_std: float = 2.0) -> dict:
    """A marker log: {camera, T_world_cam, T_world_tip (n, 4, 4), color (grey images),
    T_tip_marker, size, marker_id, dictionary}."""
    from .render import get_dictionary, marker_plane, render_planes, supersampled_rays

    rng = np.random.default_rng(seed)
    cam, X = sim_camera()
    Y = make_T(Rotation.from_euler("xyz", [10, -5, 30], degrees=True).as_matrix(), [0.01, 0.02, 0.04]) \
        if T_tip_marker is None else np.asarray(T_tip_marker, dtype=np.float64)
    d = get_dictionary(dictionary)
    W, images = [], []
    for p, Rt in zip(_positions(n, rng, pose_kind), _turns(n, rng, pose_kind)):
        face = _facing(X[:3, 3] - (CENTER if pose_kind == "translation" else p))
        T_world_marker = make_T(Rt @ face, p)
        W.append(T_world_marker @ inv_T(Y))
        plane = marker_plane(d, marker_id, size, T_world_marker)
        # ray cast only the image box around the marker (a camera cropped to it: the same rays)
        w, h = plane.size
        box = [plane.T_world_plane @ np.array([x, y, 0.0, 1.0]) for x in (0, w) for y in (0, h)]
        P = (np.array(box)[:, :3] - X[:3, 3]) @ X[:3, :3]
        u, v = cam.fx * P[:, 0] / P[:, 2] + cam.cx, cam.fy * P[:, 1] / P[:, 2] + cam.cy
        u0, v0 = int(max(0, u.min() - 8)), int(max(0, v.min() - 8))
        u1, v1 = int(min(cam.width, u.max() + 9)), int(min(cam.height, v.max() + 9))
        crop = replace(cam, width=u1 - u0, height=v1 - v0, cx=cam.cx - u0, cy=cam.cy - v0)
        img = np.full((cam.height, cam.width), 90.0)
        img[v0:v1, u0:u1] = render_planes(crop, X, [plane], background=90, rays=supersampled_rays(crop, 2))
        img += rng.normal(0.0, noise_std, img.shape)
        images.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
    return {"camera": cam, "T_world_cam": X, "T_world_tip": np.array(W), "color": images, "T_tip_marker": Y,
            "size": size, "marker_id": marker_id, "dictionary": dictionary}
