"""Fixed-radius neighbours in the spatial hash, NumPy reference.

For each query the cells within ``span`` of its cell are scanned in (z, y, x) order and
every point with squared float32 distance <= radius^2 is taken, the same test as the
device kernels.
"""
from __future__ import annotations

import numpy as np

from ..neighbors import Neighbors, search_span
from ..snapshot import HostSnapshot

F = np.float32


def query_cells(snap: HostSnapshot, q: np.ndarray, span: int) -> np.ndarray:
    """Snapshot indices of the points in the cells within ``span`` of query q, in scan order."""
    g = snap.grid
    n = np.asarray(g.dims)
    c = np.floor((q - np.asarray(g.origin, dtype=F)) * g.inv_h)
    c = np.clip(c, -(span + 1), n + span).astype(np.int64)
    lo = np.maximum(c - span, 0)
    hi = np.minimum(c + span, n - 1)
    if np.any(lo > hi):
        return np.zeros(0, dtype=np.int64)
    parts = []
    for iz in range(lo[2], hi[2] + 1):
        for iy in range(lo[1], hi[1] + 1):
            base = (iz * n[1] + iy) * n[0]
            a, b = snap.cell_start[base + lo[0]], snap.cell_start[base + hi[0] + 1]
            parts.append(np.arange(a, b))
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


def neighbors(snap: HostSnapshot, queries: np.ndarray, radius: float, max_neighbors: int, protected_only: bool = False) -> Neighbors:
    B = queries.shape[0]
    K = max_neighbors
    out = Neighbors(
        count=np.zeros(B, np.int32),
        index=np.full((B, K), -1, np.int32),
        nearest=np.full(B, -1, np.int32),
        nearest_dist=np.full(B, np.inf, F),
    )
    span = search_span(radius, snap.grid.h)
    r2 = F(radius) * F(radius)
    for b in range(B):
        cand = query_cells(snap, queries[b], span)
        if protected_only:
            cand = cand[snap.protected[cand] != 0]
        d = snap.points[cand, :3] - queries[b]
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        hit = cand[d2 <= r2]
        d2h = d2[d2 <= r2]
        out.count[b] = hit.size
        out.index[b, : min(K, hit.size)] = hit[:K]
        if hit.size:
            j = int(np.argmin(d2h))
            out.nearest[b] = hit[j]
            out.nearest_dist[b] = np.sqrt(d2h[j])
    return out


def brute_force(points: np.ndarray, queries: np.ndarray, radius: float, protected=None) -> list:
    """Neighbour index sets by testing every point (for tests): list of sorted int arrays."""
    r2 = F(radius) * F(radius)
    out = []
    for q in np.asarray(queries, dtype=F):
        d = points[:, :3] - q
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        hit = d2 <= r2
        if protected is not None:
            hit &= protected != 0
        out.append(np.flatnonzero(hit))
    return out
