"""Frame pipeline and spatial hash, NumPy reference (SPEC 1).

Per pixel: depth (at the near end of its step with ``Camera.near_reading``) -> validity ->
deprojection through the camera's ray table -> world transform -> noise covariance and its
largest eigenvalue -> fixture radius -> protected selection -> workspace crop -> cell. Then a
stable counting sort of the surviving points by cell.

Positions are computed in float32 in the same operation order as the device kernels so that
backends agree to rounding; the eigenvalue is computed exactly (float64 eigvalsh).
"""
from __future__ import annotations

import numpy as np

from ..grid import Grid
from ..params import PipelineParams
from ..rig import Rig
from ..snapshot import HostSnapshot

F = np.float32


def deproject(rig: Rig, frames: list, packed: np.ndarray) -> dict:
    """World points and attributes of every pixel of the rig (before cropping), float32."""
    depth = np.concatenate([f.depth.reshape(-1) for f in frames]).astype(np.uint32)
    cam = np.repeat(np.arange(len(rig), dtype=np.int64), np.diff(rig.offsets))
    P = packed[cam]  # (n_pixels, CAM_FLOATS) float32
    max_code = rig.ints[cam, 2].astype(np.uint32)
    z = depth.astype(F) * P[:, 16]
    z = z - np.maximum(P[:, 12], P[:, 13] * z * z)          # the near end of the reading's step (Camera.near_bias)
    valid = (depth != 0) & (depth != max_code) & (z >= P[:, 17]) & (z <= P[:, 18])
    rx, ry = rig.rays[:, 0], rig.rays[:, 1]
    xc, yc, zc = rx * z, ry * z, z
    x = P[:, 0] * xc + P[:, 1] * yc + P[:, 2] * zc + P[:, 9]
    y = P[:, 3] * xc + P[:, 4] * yc + P[:, 5] * zc + P[:, 10]
    w = P[:, 6] * xc + P[:, 7] * yc + P[:, 8] * zc + P[:, 11]
    return dict(xyz=np.stack([x, y, w], axis=1), z=z, valid=valid, cam=cam, P=P)


def sigma_max(z: np.ndarray, rays: np.ndarray, P: np.ndarray) -> np.ndarray:
    """sqrt(lambda_max) of each point's position covariance, m.

    Camera-frame covariance: C = sigma_z^2 r r^T + s_l^2 (I - e_z e_z^T), with r = (x/z, y/z, 1)
    the pixel's ray, sigma_z = a + b z^2 the axial noise and s_l = lateral_px z / min(fx, fy)
    the lateral footprint noise (isotropic in the image plane). Rotating C into the world
    frame (R C R^T) leaves its eigenvalues unchanged, so lambda_max is taken here, exactly.
    """
    z = z.astype(np.float64)
    sz = P[:, 19].astype(np.float64) + P[:, 20].astype(np.float64) * z * z
    sl = P[:, 21].astype(np.float64) * z
    r = np.stack([rays[:, 0], rays[:, 1], np.ones(len(z))], axis=1).astype(np.float64)
    C = (sz * sz)[:, None, None] * r[:, :, None] * r[:, None, :]
    C[:, 0, 0] += sl * sl
    C[:, 1, 1] += sl * sl
    return np.sqrt(np.linalg.eigvalsh(C)[:, -1]).astype(F)


def build_snapshot(rig: Rig, frames: list, params: PipelineParams, grid: Grid, seq: int = 0, packed=None) -> HostSnapshot:
    """Run the whole pipeline on validated frames (rig order) and return the sorted snapshot."""
    if packed is None:
        packed = rig.pack(frames, params.lateral_px)
    d = deproject(rig, frames, packed)
    xyz = d["xyz"]
    lo = np.asarray(params.workspace.min, dtype=F)
    hi = np.asarray(params.workspace.max, dtype=F)
    keep = d["valid"] & np.all(xyz >= lo, axis=1) & np.all(xyz < hi, axis=1)
    idx = np.flatnonzero(keep)

    pts = xyz[idx]
    sig = sigma_max(d["z"][idx], rig.rays[idx], d["P"][idx])
    rm = params.radius
    if rm.adaptive:
        rf = np.minimum(F(rm.r_base) + F(rm.k_sigma) * sig, F(rm.r_max))
    else:
        rf = np.full(idx.size, F(rm.r_base))
    prot = _select(params, frames, rig, idx, pts)

    cell = grid.linear(grid.cell_coords(pts))
    order = np.argsort(cell, kind="stable")
    counts = np.bincount(cell, minlength=grid.n_cells)
    cell_start = np.zeros(grid.n_cells + 1, dtype=np.int32)
    np.cumsum(counts, out=cell_start[1:])
    per_cam = np.bincount(d["cam"][idx], minlength=len(rig))
    return HostSnapshot(
        points=np.column_stack([pts, rf]).astype(F)[order],
        sigma=sig[order],
        camera=d["cam"][idx][order].astype(np.uint8),
        protected=prot[order].astype(np.uint8),
        pixel=idx[order].astype(np.int32),
        cell_start=cell_start,
        grid=grid,
        timestamps=tuple(float(f.timestamp) for f in frames),
        seq=seq,
        per_camera=tuple(int(n) for n in per_cam),
    )


def _select(params: PipelineParams, frames, rig: Rig, idx: np.ndarray, pts: np.ndarray) -> np.ndarray:
    sel = params.selection
    if sel.kind == "all":
        return np.ones(idx.size, dtype=bool)
    if sel.kind == "box":
        lo, hi = np.asarray(sel.box_min, dtype=F), np.asarray(sel.box_max, dtype=F)
        return np.all(pts >= lo, axis=1) & np.all(pts <= hi, axis=1)
    if sel.kind == "color":
        rgb = np.concatenate([_per_pixel(f, "color", 3) for f in frames])[idx]
        return np.all(rgb >= np.asarray(sel.color_lo), axis=1) & np.all(rgb <= np.asarray(sel.color_hi), axis=1)
    mask = np.concatenate([_per_pixel(f, "mask", 1) for f in frames])[idx, 0]
    return mask != 0


def _per_pixel(frame, attr: str, channels: int) -> np.ndarray:
    """A frame's colour or mask as (pixels, channels) uint8; a camera without one selects nothing."""
    a = getattr(frame, attr)
    n = frame.depth.size
    if a is None:
        # Outside every colour range / mask: nothing from this camera is protected.
        return np.full((n, channels), 0 if attr == "mask" else -1, dtype=np.int16)
    return np.asarray(a).reshape(n, channels).astype(np.int16)
