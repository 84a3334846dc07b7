"""Scenes and helpers for the proxy and force tests: small synthetic cameras, real frames."""
from __future__ import annotations

import numpy as np

from pointfence.kernels import DepthFrame, PipelineParams, RadiusModel, Selection, Workspace
from pointfence.kernels.haptics import HapticParams, HapticScene, haptic_pipeline_params
from pointfence.service.sources import SyntheticSource, default_camera

from kernel_cases import SHARED

WS = Workspace((-0.15, -0.15, -0.12), (0.15, 0.15, 0.2))


def small_camera(height_m=0.3, w=160, h=120, name="cam0"):
    """160x120 camera looking straight down from ``height_m``: about 2 mm between points at 0.3 m."""
    return default_camera(name, eye=(0.0, 0.0, height_m), width=w, height=h)


def synthetic_scene(scene: str, params: HapticParams | None = None, positions=((0.0, 0.0, 0.05),), backend="opencl",
                    camera=None, pipeline_params=None, **options):
    """(HapticScene, SyntheticSource) for a synthetic scene seen by a small camera.

    Kinect depth noise and holes are on; disparity quantisation is off by default because at
    160x120 its depth steps (1-2 mm at 0.3-0.4 m) would be 4x coarser than a 640x480 sensor's.
    """
    cam = camera if camera is not None else small_camera()
    options.setdefault("quantize", False)
    src = SyntheticSource(scene, cam, **options)
    params = params if params is not None else HapticParams()
    pp = pipeline_params if pipeline_params is not None else haptic_pipeline_params(params, PipelineParams(workspace=WS))
    hs = HapticScene([cam], np.asarray(positions, float), params, pp, backend=backend)
    return hs, src


def apc_frame(index=49):
    """(camera, frame) of a close-range apc_shelfbin frame (about 0.25-0.45 m)."""
    from pointfence.service.sources import RecordedSource

    src = RecordedSource(SHARED / "apc_shelfbin_50f", loop=False)
    depth, _, _ = src.load(index)
    return src.camera, DepthFrame(src.camera.name, depth, 0.0)


def apc_pipeline_params(params: HapticParams | None = None):
    return haptic_pipeline_params(params, PipelineParams(workspace=Workspace((-0.3, -0.3, 0.1), (0.3, 0.3, 0.7))))


def fixture_params(r_base=0.02, adaptive=False, k_sigma=3.0, r_max=0.02, selection=None):
    return PipelineParams(workspace=WS, selection=selection if selection is not None else Selection("mask"),
                          radius=RadiusModel(r_base=r_base, adaptive=adaptive, k_sigma=k_sigma, r_max=r_max),
                          cell_size=0.03)


def min_clearance(x, points, radii):
    """min_i |x - P_i| - r_i by brute force (float64)."""
    d = np.linalg.norm(points[:, :3].astype(np.float64) - np.asarray(x, np.float64), axis=1)
    return float(np.min(d - radii)) if len(points) else np.inf
