"""The fixture cloud of a recording: the protected points of the newest frames, downsampled, as a
``sensor_msgs/PointCloud2`` (x, y, z float32, world frame, m).

Computed by the recorder's writer process from the frames it records (never in the tick, never
from the backend's buffers): every ``stride``-th pixel of each camera deprojected with its
pinhole model (lens distortion ignored: a picture, not the fixture itself), kept where the
depth is valid and in range, inside the workspace, and selected as the pipeline selects
(all, box, colour or mask).
"""
from __future__ import annotations

import numpy as np

FIELDS = [{"name": n, "offset": 4 * i, "datatype": 7, "count": 1} for i, n in enumerate("xyz")]   # FLOAT32


def protected_points(cameras, frames, params, stride: int = 4) -> np.ndarray:
    """(N, 3) float32 world points (m) of ``frames`` (one per camera of ``cameras``, None: none)
    that ``params`` (``kernels.params.PipelineParams``) selects."""
    out = []
    sel, ws = params.selection, params.workspace
    for cam, f in zip(cameras, frames):
        if f is None:
            continue
        d = f.depth[::stride, ::stride]
        v, u = np.mgrid[0: f.depth.shape[0]: stride, 0: f.depth.shape[1]: stride]
        z = d.astype(np.float64) * cam.depth_scale
        ok = (d != 0) & (d != cam.max_code) & (z >= cam.z_min) & (z <= cam.z_max)
        pc = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], -1)[ok]
        T = np.asarray(f.T_world_cam if f.T_world_cam is not None else cam.T_world_cam, float)
        pw = pc @ T[:3, :3].T + T[:3, 3]
        keep = np.all((pw >= ws.min) & (pw <= ws.max), axis=1)
        if sel.kind == "box":
            keep &= np.all((pw >= sel.box_min) & (pw <= sel.box_max), axis=1)
        elif sel.kind == "color":
            rgb = f.color[::stride, ::stride][ok] if f.color is not None else None
            keep &= (np.all((rgb >= sel.color_lo) & (rgb <= sel.color_hi), axis=1) if rgb is not None
                     else np.zeros(len(pw), bool))
        elif sel.kind == "mask":
            keep &= f.mask[::stride, ::stride][ok] != 0 if f.mask is not None else np.zeros(len(pw), bool)
        out.append(pw[keep])
    return np.concatenate(out).astype(np.float32) if out else np.zeros((0, 3), np.float32)


def pointcloud2(points: np.ndarray, stamp_ns: int) -> dict:
    """A ``sensor_msgs/PointCloud2`` message (as a dict for ``mcap_ros2``'s encoder)."""
    pts = np.ascontiguousarray(points, np.float32)
    return {"header": {"stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000},
                       "frame_id": "world"},
            "height": 1, "width": len(pts), "fields": FIELDS, "is_bigendian": False, "point_step": 12,
            "row_step": 12 * len(pts), "data": pts.tobytes(), "is_dense": True}


__all__ = ["protected_points", "pointcloud2"]
