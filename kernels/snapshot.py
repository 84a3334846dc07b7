"""The scene snapshot: every camera's points of one instant, sorted into the spatial hash."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .grid import Grid


@dataclass
class HostSnapshot:
    """A snapshot's arrays on the host, sorted by cell and, within a cell, by rig pixel (camera,
    then pixel: the reference's stable counting sort). Every backend gives this same order on
    every build, so the same frames give the same snapshot bit for bit (positions to rounding
    across backends) and a proxy's sums over a cell's points round the same way every run.

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
        velocity: float32 (N, 3) or None: each point's estimated velocity, m/s (None: all 0;
            ``kernels/motion.py``).
        vmax: at least the largest speed in ``velocity``, m/s (a bound over each cell's box).
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
    velocity: Optional[np.ndarray] = None
    vmax: float = 0.0

    @property
    def time(self) -> float:
        """The time the snapshot shows: its oldest frame's timestamp (s)."""
        return float(min(self.timestamps)) if self.timestamps else 0.0

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    def cell_of(self) -> np.ndarray:
        """The cell index of every point (from cell_start), int64 (N,)."""
        counts = np.diff(self.cell_start)
        return np.repeat(np.arange(counts.size), counts)
