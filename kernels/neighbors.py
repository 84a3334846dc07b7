"""Results and input checks of the fixed-radius neighbour primitive shared by all backends."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError


@dataclass
class Neighbors:
    """Fixed-radius neighbours of B query points in one snapshot.

    Attributes:
        count: int32 (B,): number of points within the radius (may exceed max_neighbors).
        index: int32 (B, max_neighbors): snapshot indices of the first ``min(count, K)``
            neighbours in cell-scan order, -1 after.
        nearest: int32 (B,): index of the nearest point within the radius, -1 if none.
        nearest_dist: float32 (B,): its distance, m (inf if none).
    """

    count: np.ndarray
    index: np.ndarray
    nearest: np.ndarray
    nearest_dist: np.ndarray

    @property
    def truncated(self) -> np.ndarray:
        return self.count > self.index.shape[1]


def check_queries(queries, radius: float, max_neighbors: int) -> np.ndarray:
    """Validate neighbour-query inputs; return queries as C-contiguous float32 (B, 3)."""
    q = np.asarray(queries)
    if q.ndim == 1 and q.shape[0] == 3:
        q = q[None]
    if q.ndim != 2 or q.shape[1] != 3:
        raise InputError(f"queries shape {q.shape}; expected (B, 3) world positions in metres")
    if not np.issubdtype(q.dtype, np.number):
        raise InputError(f"queries dtype {q.dtype}; expected floating point")
    q = np.ascontiguousarray(q, dtype=np.float32)
    bad = ~np.all(np.isfinite(q), axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"query {i} = {q[i].tolist()} is not finite; expected finite positions in metres")
    if not isinstance(radius, (int, float, np.floating)) or not math.isfinite(radius) or radius <= 0:
        raise InputError(f"radius = {radius!r}; expected a finite length > 0 m")
    if not isinstance(max_neighbors, (int, np.integer)) or max_neighbors < 1:
        raise InputError(f"max_neighbors = {max_neighbors!r}; expected an integer >= 1")
    return q


def search_span(radius: float, h: float) -> int:
    """Cells to search on each side of the query's cell so that no point within radius is missed."""
    return max(1, int(math.ceil(radius / h)))
