"""Scenes and rigs for kernel tests: random depth frames and real frames from ../shared/data."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pointfence.kernels import Camera, DepthFrame, PipelineParams, RadiusModel, Selection, Workspace

SHARED = Path(__file__).parents[1].parent / "shared" / "data"


def device_backends() -> list:
    """The accelerated backends to test against the reference: opencl always, warp when installed."""
    out = ["opencl"]
    try:
        import warp  # noqa: F401
    except ImportError:
        pass
    else:
        out.append("warp")
    return out


def contracts_fma(backend: str) -> bool:
    """CUDA compiles a*b+c into fused multiply-adds, so positions differ from the reference in
    the last bit and a point within rounding of a cell boundary may land in the next cell."""
    if backend != "warp":
        return False
    from pointfence.kernels import get_backend

    return get_backend("warp").device.is_cuda


def pose(tx=0.0, ty=0.0, tz=0.0, yaw=0.0, pitch=0.0) -> np.ndarray:
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Rx
    T[:3, 3] = [tx, ty, tz]
    return T


def random_rig(rng, n_cams=3, w=160, h=120, distort=True):
    """Small cameras at different poses (one with lens distortion) and smooth random depth."""
    cams, frames = [], []
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    for i in range(n_cams):
        dist = (0.08, -0.03, 0.001, -0.0015, 0.002) if (distort and i == 1) else (0.0,) * 5
        cam = Camera(f"cam{i}", w, h, 140.0 + 5 * i, 142.0, w / 2 - 0.5, h / 2 + 0.3, depth_scale=0.001,
                     T_world_cam=pose(0.05 * i, -0.02 * i, 0.01, yaw=0.1 * i, pitch=0.05 * i), dist=dist,
                     z_min=0.2, z_max=2.0)
        d = 700 + 150 * np.sin(u / (9.0 + i)) + 90 * np.cos(v / 7.0) + rng.normal(0, 3, (h, w))
        d[rng.random((h, w)) < 0.1] = 0
        d[rng.random((h, w)) < 0.01] = 65535
        d[rng.random((h, w)) < 0.01] = 2500  # beyond z_max
        color = rng.integers(0, 256, (h, w, 3)).astype(np.uint8)
        mask = (rng.random((h, w)) < 0.3).astype(np.uint8)
        frames.append(DepthFrame(cam.name, d.astype(np.uint16), 0.01 * i, color=color, mask=mask))
        cams.append(cam)
    return cams, frames


def params_for(selection="all", adaptive=True, cell=0.02):
    sel = {
        "all": Selection(),
        "box": Selection("box", box_min=(-0.2, -0.2, 0.5), box_max=(0.2, 0.1, 0.8)),
        "color": Selection("color", color_lo=(100, 0, 50), color_hi=(255, 128, 255)),
        "mask": Selection("mask"),
    }[selection]
    return PipelineParams(
        workspace=Workspace((-0.6, -0.5, 0.3), (0.6, 0.5, 1.2)),
        selection=sel,
        radius=RadiusModel(r_base=0.004, adaptive=adaptive, k_sigma=3.0, r_max=0.012),
        cell_size=cell,
    )


def read_png16(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path)).astype(np.uint16)


def kitchen_rig(frame_ids=(150, 170)):
    """Two 7-Scenes kitchen frames with their camera-to-world poses: a two-camera rig."""
    root = SHARED / "7scenes_kitchen_50f"
    cams, frames = [], []
    for i, fid in enumerate(frame_ids):
        T = np.loadtxt(root / f"frame-{fid:06d}.pose.txt")
        # The stored poses carry 8 significant digits; re-orthonormalise the rotation.
        U, _, Vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = U @ Vt
        cam = Camera(f"kinect{i}", 640, 480, 585.0, 585.0, 320.0, 240.0, T_world_cam=T)
        cams.append(cam)
        frames.append(DepthFrame(cam.name, read_png16(root / f"frame-{fid:06d}.depth.png"), fid / 30.0))
    return cams, frames


def kitchen_params(cams, cell=0.03):
    return PipelineParams(workspace=Workspace((-3, -3, -3), (3, 3, 3)), cell_size=cell,
                          radius=RadiusModel(r_base=0.01, adaptive=True, r_max=0.03))
