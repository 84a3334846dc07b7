"""Uniform grid geometry of the spatial hash (world frame, metres)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Grid:
    """Cells of edge ``h`` covering the workspace from ``origin``; ``dims`` = (nx, ny, nz).

    A cell's linear index is ``(iz * ny + iy) * nx + ix``.
    """

    origin: tuple
    h: float
    dims: tuple

    @classmethod
    def covering(cls, lo, hi, h: float) -> "Grid":
        """The grid of cells of edge ``h`` (m) from corner ``lo`` that covers the box up to ``hi``
        (world frame, m): at least one cell on every axis."""
        ext = (np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)) / h - 1e-9
        return cls(tuple(float(x) for x in lo), float(h), tuple(int(max(1, math.ceil(x))) for x in ext))

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
