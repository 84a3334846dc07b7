"""The dissertation's neighbourhood search (2.2.2): project the query's bounding cube into each
depth image and deproject only the pixels inside it. No build step; the peer of the hash."""
from __future__ import annotations

import numpy as np


class ProjectiveSearch:
    """Fixed-radius neighbours straight from organised depth images (NumPy, per query)."""

    def __init__(self, cameras, frames):
        self.views = []
        for cam, f in zip(cameras, frames):
            T = np.asarray(f.T_world_cam if f.T_world_cam is not None else cam.T_world_cam)
            Tinv = np.linalg.inv(T)
            self.views.append((cam, f.depth, cam.ray_table(), T, Tinv))

    def query(self, q: np.ndarray, radius: float) -> np.ndarray:
        """World points within ``radius`` of q, from every camera: (M, 3) float32."""
        out = []
        corners = q + radius * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        for cam, depth, rays, T, Tinv in self.views:
            pc = corners @ Tinv[:3, :3].T + Tinv[:3, 3]
            if np.all(pc[:, 2] <= cam.z_min):
                continue
            z = np.maximum(pc[:, 2], cam.z_min)
            u = cam.fx * pc[:, 0] / z + cam.cx
            v = cam.fy * pc[:, 1] / z + cam.cy
            u0, u1 = int(max(np.floor(u.min()), 0)), int(min(np.ceil(u.max()), cam.width - 1))
            v0, v1 = int(max(np.floor(v.min()), 0)), int(min(np.ceil(v.max()), cam.height - 1))
            if u0 > u1 or v0 > v1:
                continue
            d = depth[v0 : v1 + 1, u0 : u1 + 1].astype(np.float32) * np.float32(cam.depth_scale)
            r = rays[v0 : v1 + 1, u0 : u1 + 1]
            ok = (d > cam.z_min) & (d < cam.z_max)
            p = np.stack([r[..., 0] * d, r[..., 1] * d, d], axis=-1)[ok]
            pw = p @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)
            out.append(pw[np.sum((pw - q) ** 2, axis=1) <= radius * radius])
        return np.concatenate(out) if out else np.zeros((0, 3), np.float32)
