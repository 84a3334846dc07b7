"""Haptic rendering and forbidden-region fixtures from depth frames, without the service.

>>> from pointfence.kernels.haptics import HapticScene, HapticParams
>>> scene = HapticScene(cameras, positions=[[0, 0, 0.05]])          # one proxy, rendering mode
>>> scene.ingest(frames)                                            # at 30 Hz, one per camera
>>> forces = scene.step(hips)                                       # at 1 kHz: one kernel launch
>>> scene.proxies, scene.normals, scene.states, scene.forces        # (B, 3), (B, 3), (B,), (B, 3)

``HapticParams(mode="fixture")`` renders forbidden-region fixtures around the protected
points (``PipelineParams.selection``, radii from ``PipelineParams.radius``) instead.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import numpy as np

from .camera import Camera
from .errors import InputError
from .forces import ForceRenderer
from .params import PipelineParams
from .params_haptics import HapticParams
from .proxy import CONTACT, ENTRENCHED, FREE, STATE_NAMES, ProxyBatch, check_points3, fixture_r_max
from .registry import get_backend

__all__ = ["HapticScene", "HapticParams", "haptic_pipeline_params", "FREE", "CONTACT", "ENTRENCHED", "STATE_NAMES"]


def haptic_pipeline_params(params: HapticParams | None = None, pipeline_params: PipelineParams | None = None) -> PipelineParams:
    """``pipeline_params`` (default ``PipelineParams()``) with the hash cell size set to the
    proxy's reach plus its working-set skin, so that one proxy gathers from 3 x 3 x 3 cells."""
    p = params if params is not None else HapticParams()
    pp = pipeline_params if pipeline_params is not None else PipelineParams()
    return replace(pp, cell_size=p.reach(fixture_r_max(pp)) + p.skin)


class HapticScene:
    """A frame pipeline, a batch of proxies on it and their force renderer.

    Args:
        cameras: the rig (``Camera`` objects with ``T_world_cam``).
        positions: initial proxy centres (B, 3), m; or use ``n_proxies`` to start B proxies at
            the origin (call ``reset`` before the first ``step``).
        params: ``HapticParams`` (rendering mode, table 2.1 defaults).
        pipeline_params: ``PipelineParams`` (workspace, protected selection, fixture radii); by
            default the cell size is set by ``haptic_pipeline_params``.
        backend, device: compute backend ("opencl" by default, "numpy" for the reference).
    """

    def __init__(self, cameras: Sequence[Camera], positions=None, params: HapticParams | None = None,
                 pipeline_params: PipelineParams | None = None, backend: str | None = None, device: str | None = None,
                 n_proxies: int | None = None):
        self.params = params if params is not None else HapticParams()
        if not isinstance(self.params, HapticParams):
            raise InputError(f"params = {self.params!r}; expected HapticParams")
        if pipeline_params is None:
            pipeline_params = haptic_pipeline_params(self.params)
        if positions is None:
            if n_proxies is None:
                n_proxies = 1
            if not isinstance(n_proxies, (int, np.integer)) or n_proxies < 0:
                raise InputError(f"n_proxies = {n_proxies!r}; expected an integer >= 0")
            positions = np.zeros((int(n_proxies), 3))
        self.backend = get_backend(backend, device)
        self.pipeline = self.backend.pipeline(cameras, pipeline_params)
        self.batch: ProxyBatch = self.pipeline.proxies(positions, self.params)
        self.renderer = ForceRenderer(len(self.batch), self.params)

    # --- frames and ticks ------------------------------------------------------------------
    def ingest(self, frames):
        """Build the next snapshot from one frame per camera (see ``FramePipeline.ingest``)."""
        return self.pipeline.ingest(frames)

    def reset(self, positions) -> None:
        """Place the proxies at ``positions`` (B, 3) (their number may change); forces restart."""
        self.batch.reset(positions)
        self.renderer.resize(len(self.batch))

    def step(self, hips, now: float | None = None, dt: float | None = None) -> np.ndarray:
        """One haptic tick: move all proxies towards ``hips`` (B, 3) (one kernel launch) and
        render their forces. Returns ``forces`` (B, 3), N. Non-finite HIPs raise InputError.
        ``now`` (the tick's time on the frames' clock) or ``dt`` drive motion prediction when
        ``PipelineParams.motion`` enables it (``ProxyBatch.step``)."""
        h = check_points3(hips, "hips", len(self.batch))
        self.batch.step(h, now, dt)
        return self.renderer.update(self.batch.positions, h, self.batch.states)

    # --- results of the last tick -------------------------------------------------------------
    @property
    def proxies(self) -> np.ndarray:
        """Proxy centres (B, 3), m."""
        return self.batch.positions

    @property
    def normals(self) -> np.ndarray:
        """Estimated surface normals (B, 3) (eq. 2.1); zero where no point is within reach."""
        return self.batch.normals

    @property
    def states(self) -> np.ndarray:
        """FREE (0), CONTACT (1) or ENTRENCHED (2) per proxy."""
        return self.batch.states

    @property
    def forces(self) -> np.ndarray:
        """Forces on the HIPs (B, 3), N (spring, contact damping, FIR, saturation)."""
        return self.renderer.forces

    @property
    def steps(self) -> np.ndarray:
        return self.batch.steps

    @property
    def converged(self) -> np.ndarray:
        return self.batch.converged

    @property
    def nearest(self) -> np.ndarray:
        """Smallest clearance to the points within the normal band (m, +inf if none)."""
        return self.batch.nearest

    def __len__(self) -> int:
        return len(self.batch)
