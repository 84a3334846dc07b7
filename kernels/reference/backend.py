"""The NumPy reference backend."""
from __future__ import annotations

import platform

import numpy as np

from ..backend import Backend, FramePipeline
from ..double_buffer import DoubleBuffer
from ..motion import cell_moments, expand
from ..snapshot import HostSnapshot
from . import neighbors as nb
from .pipeline import build_snapshot


def empty_snapshot(grid) -> HostSnapshot:
    f = np.float32
    return HostSnapshot(
        points=np.zeros((0, 4), f), sigma=np.zeros(0, f), camera=np.zeros(0, np.uint8),
        protected=np.zeros(0, np.uint8), pixel=np.zeros(0, np.int32),
        cell_start=np.zeros(grid.n_cells + 1, np.int32), grid=grid,
    )


class NumpyPipeline(FramePipeline):
    def __init__(self, backend, cameras, params):
        super().__init__(cameras, params)
        self.backend = backend
        self.buffers = DoubleBuffer([empty_snapshot(self.grid), empty_snapshot(self.grid)])

    def _build_steps(self, frames, packed):
        yield                   # (no device: the whole build runs in the second part)
        snap = build_snapshot(self.rig, frames, self.params, self.grid, seq=self.seq + 1, packed=packed)
        cell_v, snap.vmax = self._estimate_motion(lambda: cell_moments(snap.points, snap.cell_start, self.grid), snap.timestamps)
        snap.velocity = expand(cell_v, snap.cell_start, snap.points, self.grid)
        b = self.buffers.back()
        self.buffers.slots[b] = snap
        self.buffers.publish(b)
        return snap.n_points, snap.per_camera

    def _neighbors(self, q, radius, max_neighbors, protected_only):
        with self.buffers.read() as snap:
            return nb.neighbors(snap, q, radius, max_neighbors, protected_only)

    def host_snapshot(self) -> HostSnapshot:
        with self.buffers.read() as snap:
            return snap

    def proxies(self, positions, params=None):
        """A batch of proxies on this pipeline (``pointfence.kernels.proxy``)."""
        from .proxy import NumpyProxies

        return NumpyProxies(self, positions, params)


class NumpyBackend(Backend):
    """Reference implementation on the host CPU (clear and exact, not fast)."""

    name = "numpy"

    def __init__(self, device: str | None = None):
        pass

    @property
    def device_name(self) -> str:
        return f"host CPU ({platform.processor() or platform.machine()}), NumPy {np.__version__}"

    def pipeline(self, cameras, params) -> NumpyPipeline:
        return NumpyPipeline(self, cameras, params)
