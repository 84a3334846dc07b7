"""Uniform grid geometry of the spatial hash (world frame, metres)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .params import PipelineParams


@dataclass(frozen=True)
class Grid:
    """Cells of edge ``h`` covering the workspace from ``origin``; ``dims`` = (nx, ny, nz).

    A cell's linear index is ``(iz * ny + iy) * nx + ix``.
    """

    origin: tuple
    h: float
    dims: tuple

    @classmethod
    def from_params(cls, params: PipelineParams) -> "Grid":
        return cls(tuple(params.workspace.min), float(params.cell_size), params.grid_dims())

    @property
    def n_cells(self) -> int:
        return self.dims[0] * self.dims[1] * self.dims[2]

    def cell_coords(self, points: np.ndarray) -> np.ndarray:
        """Integer cell coordinates (N, 3) of float32 points, clamped to the grid.

        Computed as floor((p - origin) * (1 / h)) in float32, the same arithmetic as the device kernels.
        """
        p = np.asarray(points, dtype=np.float32)[:, :3]
        o = np.asarray(self.origin, dtype=np.float32)
        c = np.floor((p - o) * self.inv_h).astype(np.int64)
        return np.clip(c, 0, np.asarray(self.dims) - 1)

    def linear(self, coords: np.ndarray) -> np.ndarray:
        nx, ny, _ = self.dims
        return (coords[:, 2] * ny + coords[:, 1]) * nx + coords[:, 0]

    @property
    def inv_h(self) -> np.float32:
        """1 / h in float32: cells are found by multiplying, on every backend."""
        return np.float32(1.0) / np.float32(self.h)

    def as_float4(self) -> np.ndarray:
        """(origin.x, origin.y, origin.z, 1 / h) for the device kernels."""
        return np.array([*self.origin, self.inv_h], dtype=np.float32)

    def as_int4(self) -> np.ndarray:
        return np.array([*self.dims, 0], dtype=np.int32)
