"""Benchmark scenes: a synthetic tabletop seen by several full-size depth cameras."""
from __future__ import annotations

import numpy as np

from pointfence.kernels import PipelineParams, Workspace
from pointfence.service.sources.synthetic import SyntheticSource, default_camera, look_at

#: the tabletop workspace every frames benchmark hashes (world frame, m)
TABLE_WORKSPACE = Workspace((-0.6, -0.6, -0.05), (0.6, 0.6, 0.3))


def tabletop_rig(n_cameras: int, scene: str = "sphere", width: int = 640, height: int = 480, seed: int = 0):
    """``n_cameras`` cameras 0.6 m from the scene at evenly spaced azimuths, 50 deg elevation,
    and one rendered frame from each. Returns (cameras, frames)."""
    cams, frames = [], []
    for i in range(n_cameras):
        az = 2 * np.pi * i / max(n_cameras, 1)
        el = np.deg2rad(50.0)
        eye = 0.6 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        cam = default_camera(f"cam{i}", width=width, height=height).with_pose(look_at(eye, (0, 0, 0)))
        cam = type(cam)(**{**cam.__dict__, "name": f"cam{i}"})
        src = SyntheticSource(scene, cam, seed=seed + i)
        frames.append(src.read())
        cams.append(cam)
    return cams, frames


def tabletop_params(cell_size: float = 0.03) -> PipelineParams:
    return PipelineParams(workspace=TABLE_WORKSPACE, cell_size=cell_size)
