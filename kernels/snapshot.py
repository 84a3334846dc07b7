"""The scene snapshot: every camera's points of one instant, sorted into the spatial hash."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .grid import Grid


@dataclass
class HostSnapshot:
    """A snapshot's arrays on the host, sorted by cell (counting-sort order).

    Attributes:
        points: float32 (N, 4): world x, y, z (m) and fixture radius r_f (m).
        sigma: float32 (N,): sqrt of the largest eigenvalue of the position covariance, m.
        camera: uint8 (N,): index of the camera in the rig.
        protected: uint8 (N,): 1 where the point carries a forbidden-region sphere.
        pixel: int32 (N,): source pixel, ``camera_offset + v * width + u`` over the rig.
        cell_start: int32 (n_cells + 1,): points of cell c are ``cell_start[c]:cell_start[c+1]``.
        grid: the grid geometry.
        timestamps: capture time of each camera's frame, s.
        seq: snapshot counter.
    """

    points: np.ndarray
    sigma: np.ndarray
    camera: np.ndarray
    protected: np.ndarray
    pixel: np.ndarray
    cell_start: np.ndarray
    grid: Grid
    timestamps: tuple = ()
    seq: int = 0
    per_camera: tuple = field(default=())

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    def cell_of(self) -> np.ndarray:
        """The cell index of every point (from cell_start), int64 (N,)."""
        counts = np.diff(self.cell_start)
        return np.repeat(np.arange(counts.size), counts)
