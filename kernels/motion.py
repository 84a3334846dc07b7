"""Motion of the point cloud between snapshots, and fixtures placed where the surface is now
(dissertation 6.2: a fixture lags a surface moving at v by v * T; 2.4 / fig. 2.15: at 30 Hz the
proxy pops through a surface that advances more than its radius between two frames).

Every snapshot carries a velocity per point (m/s, world frame, in the snapshot's cell-sorted
order). It is estimated per grid cell from two consecutive snapshots and shared by the cell's
points:

* per cell, the number of points and the sums of their positions and of their products (one
  pass over the sorted points, on the device for device backends);
* per occupied cell c, those moments summed over the block of (2 r + 1)^3 cells around c,
  in the new and in the previous snapshot (summed-area tables: 8 look-ups per block); the
  block's centroid displacement over the time between the snapshots is c's velocity. With a
  block reaching further than the surface moves in one frame (r * cell size > v / rate), the
  moved surface stays inside the block, so a surface patch translating along its normal gives
  its exact normal velocity (the component that matters to a proxy resting on it; sliding
  along itself shows no motion, which is also what a proxy feels). r = 1, 2, ... up to
  ``capture`` / cell size: the smallest block whose counts agree is used. Where the block's
  points are planar only the displacement along its normal is kept: sliding along a surface
  is not observable from its points, and the centroid's sideways jitter as pixel rays enter
  and leave a block would tear the predicted surface apart at cell borders;
* where the block is planar in both snapshots, as thick (the noise across the plane) in both
  within a factor ``THICKNESS_RATIO`` (a flat patch that folds or steps fits a thicker tilted
  plane, not a turned one), its motion is affine, not one velocity: a point
  p of the new plane (normal n1, centroid c1) moves along n1 by its distance to the previous
  plane (normal n0, centroid c0) per ``gap``: v(p) = n1 (n0 . (p - c0)) / gap = v_c + W (p - c1),
  v_c = n1 (n0 . (c1 - c0)) / gap, W = n1 (n0 - (n0 . n1) n1)^T / gap (the in-plane gradient of
  the normal velocity: a turning surface, e.g. a platform rocking about a hinge, advances
  faster far from the hinge; W's norm is the surface's turning rate, rad/s). A translating
  plane (n0 = n1) gives W = 0, the velocity above. Each hash cell carries the field as its
  velocity at its lower corner and W (``CELL_MOTION`` floats), each point gets
  v + W (p - corner) (``expand``, the device kernels ``expand_velocity``);
* the estimate is dropped (velocity 0, "unknown") where either block holds fewer than
  ``min_points`` points, where the two counts differ by more than ``count_ratio`` (the block
  gained or lost surface: an edge, an occlusion, a hole), where it exceeds ``v_max`` anywhere
  in the motion cell (no physical motion the block can capture), where the block turns faster
  than ``w_max`` (a block whose contents changed, not a turning surface), and where the
  snapshots are further apart than ``max_gap``; cells slower than ``v_min`` everywhere (depth
  noise) are set to 0;
* an occupied cell left unknown takes the mean motion of its measured neighbours (the 26
  cells around it), each neighbour's field evaluated at the cell's own centroid, where at
  least ``min_neighbours`` of them were measured and they agree (every one within
  ``coherence`` times their mean speed, + ``v_min``, of the mean): a cell that lost its
  estimate to a hole or to the surface crossing cells, inside a patch moving as one rigid
  body (translating or turning: each neighbour's affine field extrapolates to the same
  velocity). Elsewhere it stays at 0: a cell that cannot predict behaves as a fixture that
  does not try;
* a cell measured in this estimate and the last one, whose two fields agree at its new centroid
  within ``smooth_gate`` (a fraction of the larger speed, + ``v_min``), takes their weighted
  mean (``smoothing``: the new estimate's weight; the mean carries on, an exponential mean over
  the frames the cell keeps its motion). One estimate's error is its block's centroid noise
  over one frame gap (on real surfaces sliding through a block, 10-30 % of the speed from one
  pair of frames to the next); a change of motion beyond the gate is taken at once.

Each motion cell carries a state (``CELL_NONE``, ``CELL_PROPAGATED``, ``CELL_MEASURED``);
``summary()`` counts them and gives the measured speeds (for the service's status, computed
once per snapshot, never in the tick).

The proxy kernels evaluate each point at ``p + v dt`` with one ``dt`` per tick:
``dt = clamp(now - t_snapshot + latency, 0, latency + max_age)``, where ``t_snapshot`` is the
oldest frame timestamp of the snapshot, ``now`` the tick's time on the frames' clock and
``latency`` the camera latency T that the timestamps do not include (a camera that stamps
frames on arrival: T is the capture-to-arrival delay). Within a tick the predicted scene is
static, so every clipping rule of ``kernels/proxy.py`` holds against the predicted points;
between ticks the predicted scene moves (the "scene moved into the proxy" case those rules
already handle). The hash search grows by ``vmax * dt`` cells so that moved points are found;
with zero velocity (or ``dt = 0``) the kernels do exactly what they did without prediction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .grid import Grid


@dataclass(frozen=True)
class MotionModel:
    """Motion estimation and prediction settings (all SI: m, s, m/s).

    enabled: estimate velocities and predict (False: every velocity is 0, dt is 0).
    latency: camera latency T not included in the frame timestamps, s.
    max_age: how far past its timestamp a snapshot is extrapolated at most (s); beyond it a
        stale snapshot stays where it was last predicted (dt <= latency + max_age).
    capture: the longest displacement between two snapshots that is measured (m): blocks grow
        up to this half-width.
    cell: edge of the motion grid's cells (m), rounded to a multiple of the hash cell size.
    min_points: fewest points per block for an estimate.
    planarity: a block whose smallest covariance eigenvalue is below this times the middle one
        is a surface patch: only its normal velocity is kept.
    count_ratio: largest ratio between the block's point counts in the two snapshots.
    v_min: speeds below this are depth noise and are set to 0.
    v_max: estimates above this are discarded (0).
    max_gap: snapshots further apart than this give no estimate (0).
    min_neighbours: fewest measured neighbours (of 26) whose agreed velocity an unknown
        cell takes (0: never propagate).
    coherence: the measured neighbours agree when each is within this fraction of their mean
        speed (+ v_min) of their mean velocity.
    w_max: blocks whose planar fit turns faster than this (rad/s) between the snapshots are
        discarded (0).
    smoothing: weight of a cell's new estimate against its previous one (1: none). A cell
        measured in two estimates in a row takes ``smoothing * new + (1 - smoothing) * previous``
        (fields, each at the cell's new centroid) where the two agree within ``smooth_gate``.
    smooth_gate: the two estimates agree when they differ by at most this fraction of the
        larger speed (+ ``v_min``); otherwise the surface changed its motion and the new
        estimate is taken as it is.
    """

    enabled: bool = False
    latency: float = 0.0
    max_age: float = 0.1
    capture: float = 0.05
    cell: float = 0.025
    min_points: int = 12
    planarity: float = 0.1
    count_ratio: float = 1.5
    v_min: float = 0.01
    v_max: float = 2.0
    max_gap: float = 0.2
    min_neighbours: int = 3
    coherence: float = 0.25
    w_max: float = 20.0
    smoothing: float = 0.5
    smooth_gate: float = 0.15

    def __post_init__(self):
        for key in ("latency", "max_age", "capture", "cell", "planarity", "count_ratio", "v_min", "v_max", "max_gap",
                    "coherence", "w_max", "smoothing", "smooth_gate"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise InputError(f"motion {key} = {v!r}; expected a finite number >= 0")
        if self.count_ratio < 1:
            raise InputError(f"motion count_ratio = {self.count_ratio}; expected >= 1")
        if not 0 < self.smoothing <= 1:
            raise InputError(f"motion smoothing = {self.smoothing}; expected a weight in (0, 1] (1: no smoothing)")
        if self.v_min > self.v_max:
            raise InputError(f"motion v_min = {self.v_min} > v_max = {self.v_max} m/s")
        for key, lo in (("min_points", 1), ("min_neighbours", 0)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise InputError(f"motion {key} = {v!r}; expected an integer >= {lo}")
        if not isinstance(self.enabled, bool):
            raise InputError(f"motion enabled = {self.enabled!r}; expected true or false")

    @property
    def horizon(self) -> float:
        """Largest prediction time dt (s)."""
        return self.latency + self.max_age

    def tick_dt(self, now, t_snapshot: float, vmax: float, dt=None) -> float:
        """The prediction time of one tick (s), 0 when nothing moves or prediction is off.

        ``dt`` given: used as is (clamped to [0, horizon]); else from ``now`` (the tick's time
        on the frames' clock): now - t_snapshot + latency. ``now`` None: 0."""
        if not self.enabled or vmax <= 0:
            return 0.0
        if dt is None:
            if now is None:
                return 0.0
            dt = float(now) - float(t_snapshot) + self.latency
        if not math.isfinite(dt):
            raise InputError(f"prediction time dt = {dt!r}; expected a finite number of seconds")
        return float(min(max(dt, 0.0), self.horizon))


#: motion cell states: no estimate (velocity 0), a measured neighbourhood's velocity, measured
CELL_NONE, CELL_PROPAGATED, CELL_MEASURED = 0, 1, 2


def snapshot_time(timestamps) -> float:
    """The time a snapshot is taken to show: its oldest frame's timestamp (s)."""
    return float(min(timestamps)) if len(timestamps) else 0.0


#: cell moments per cell: count, sums of x, y, z, sums of xx, xy, xz, yy, yz, zz, in coordinates
#: relative to the cell's lower corner (the device kernels sum small numbers in float32)
N_MOMENTS = 10
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def cell_corners(grid: Grid) -> np.ndarray:
    """Lower corner of every cell (n_cells, 3), float64, in linear cell order."""
    nx, ny, nz = grid.dims
    c = np.arange(nx * ny * nz)
    ijk = np.stack([c % nx, (c // nx) % ny, c // (nx * ny)], axis=1)
    return np.asarray(grid.origin) + ijk * grid.h


def cell_moments(points_sorted: np.ndarray, cell_start: np.ndarray, grid: Grid) -> np.ndarray:
    """Per cell moments (n_cells, N_MOMENTS) float64 from cell-sorted points (see N_MOMENTS)."""
    counts = np.diff(cell_start).astype(np.int64)
    cell = np.repeat(np.arange(counts.size), counts)
    q = points_sorted[:, :3].astype(np.float64) - cell_corners(grid)[cell]
    out = np.zeros((counts.size, N_MOMENTS))
    out[:, 0] = counts
    for k in range(3):
        out[:, 1 + k] = np.bincount(cell, weights=q[:, k], minlength=counts.size)
    for j, (a, b) in enumerate(_PAIRS):
        out[:, 4 + j] = np.bincount(cell, weights=q[:, a] * q[:, b], minlength=counts.size)
    return out


def world_moments(local: np.ndarray, grid: Grid) -> np.ndarray:
    """Cell moments about the world origin from moments about each cell's corner (float64)."""
    return _to_world(np.asarray(local, np.float64), cell_corners(grid))


def _sat(moments: np.ndarray, dims: tuple) -> np.ndarray:
    """Summed-area table (nz + 1, ny + 1, nx + 1, C) of per-cell values (n_cells, C)."""
    nx, ny, nz = dims
    v = moments.reshape(nz, ny, nx, -1)
    t = np.zeros((nz + 1, ny + 1, nx + 1, v.shape[-1]))
    t[1:, 1:, 1:] = v.cumsum(0).cumsum(1).cumsum(2)
    return t


def _block(sat: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Sums over the cell boxes [lo, hi) (M, 3 as x, y, z) from a summed-area table."""
    x0, y0, z0 = lo[:, 0], lo[:, 1], lo[:, 2]
    x1, y1, z1 = hi[:, 0], hi[:, 1], hi[:, 2]
    return (sat[z1, y1, x1] - sat[z0, y1, x1] - sat[z1, y0, x1] - sat[z1, y1, x0]
            + sat[z0, y0, x1] + sat[z0, y1, x0] + sat[z1, y0, x0] - sat[z0, y0, x0])


class MotionEstimator:
    """Per-cell velocities from consecutive snapshots' cell moments (``cell_moments``, about
    each cell's corner); see the module docstring.

    The estimate runs on a motion grid of about ``cell`` m: k x k x k hash cells per motion cell
    (k = round(cell / hash cell size), at least 1), so a fine rendering hash does not multiply
    the work. Blocks of half-width 1, 2, ... up to ``ceil(capture / motion cell)`` motion cells
    are tried in turn per occupied motion cell; the smallest one whose two counts agree gives
    the estimate (a small block mixes in the fewest other surfaces; a larger one captures a
    longer displacement). Every hash cell takes its motion cell's velocity.
    """

    def __init__(self, model: MotionModel, grid: Grid):
        self.model = model
        self.grid = grid
        self.k = max(1, int(round(model.cell / grid.h)))
        nx, ny, nz = grid.dims
        k = self.k
        self.dims = (-(-nx // k), -(-ny // k), -(-nz // k))
        c = np.arange(nx * ny * nz)
        ijk = np.stack([c % nx, (c // nx) % ny, c // (nx * ny)], axis=1)
        cc = ijk // k
        self._coarse = (cc[:, 2] * self.dims[1] + cc[:, 1]) * self.dims[0] + cc[:, 0]
        self._corners = np.asarray(grid.origin) + ijk * grid.h
        self.max_block = max(1, int(math.ceil(model.capture / (k * grid.h) - 1e-9)))
        self._prev = None  # (time, summed-area table)
        self._last = None  # the last estimate's measured cells: (motion cells, v at centroid, W, centroid)
        self._smoothed = 0  # measured cells the last estimate averaged with the one before
        nc = self.dims[0] * self.dims[1] * self.dims[2]
        self.state = np.zeros(nc, np.uint8)      # per motion cell: CELL_NONE / _PROPAGATED / _MEASURED
        self.cell_motion = None                  # the last estimate's cell motions (``update``), or None
        self._summary = _summary(np.zeros(0, np.uint8), np.zeros(0))
        o = np.array([(x, y, z) for z in (-1, 0, 1) for y in (-1, 0, 1) for x in (-1, 0, 1) if (x, y, z) != (0, 0, 0)])
        self._offsets = o

    def reset(self) -> None:
        self._prev = None
        self._last = None
        self.cell_motion = None
        self.state[:] = CELL_NONE
        self._summary = _summary(np.zeros(0, np.uint8), np.zeros(0))

    def confidence_of(self, cells: np.ndarray) -> np.ndarray:
        """The state (``CELL_*``) of the motion cell of each hash cell in ``cells``."""
        return self.state[self._coarse[np.asarray(cells, np.int64)]]

    def summary(self) -> dict:
        """The last estimate's cells (occupied motion cells measured / propagated / without an
        estimate, and why not measured) and measured speeds (max, median, m/s); computed in
        ``update``."""
        return dict(self._summary)

    def update(self, moments: np.ndarray, t: float):
        """Cell motions (n_cells, ``CELL_MOTION``) float32 for the snapshot with ``moments``
        (per hash cell, about the cell corners) taken at ``t`` (``pack_motion``: each cell's
        velocity at its lower corner, m/s, and its velocity gradient W, 1/s) and the largest
        speed (m/s) any point of an occupied cell can get; (None, 0.0) when there is no
        estimate (first snapshot, gap)."""
        m = self.model
        fine = np.flatnonzero(moments[:, 0] > 0)
        wm = _to_world(np.asarray(moments[fine], np.float64), self._corners[fine])
        nc = self.dims[0] * self.dims[1] * self.dims[2]
        coarse = np.zeros((nc, N_MOMENTS))
        np.add.at(coarse, self._coarse[fine], wm)
        sat = _sat(coarse, self.dims)
        prev, self._prev = self._prev, (float(t), sat)
        self.state[:] = CELL_NONE
        self.cell_motion = None
        self._summary = _summary(np.zeros(0, np.uint8), np.zeros(0))
        last, self._last = self._last, None
        if prev is None:
            return None, 0.0
        gap = float(t) - prev[0]
        if not (0 < gap <= m.max_gap):
            return None, 0.0
        occ = np.unique(self._coarse[fine])
        vc = np.zeros((occ.size, 3))
        W = np.zeros((occ.size, 3, 3))
        ref = coarse[occ, 1:4] / np.maximum(coarse[occ, :1], 1)   # each motion cell's centroid
        if occ.size:
            nx, ny, _ = self.dims
            c = np.stack([occ % nx, (occ // nx) % ny, occ // (nx * ny)], axis=1)
            upper = np.asarray(self.dims)
            todo = np.ones(occ.size, bool)
            few = np.zeros(occ.size, bool)      # at the largest block: too few points (else counts disagree)
            for r in range(1, self.max_block + 1):
                sel = np.flatnonzero(todo)
                if not sel.size:
                    break
                lo = np.maximum(c[sel] - r, 0)
                hi = np.minimum(c[sel] + r + 1, upper)
                b1, b0 = _block(sat, lo, hi), _block(prev[1], lo, hi)
                n1, n0 = b1[:, 0], b0[:, 0]
                enough = (n1 >= m.min_points) & (n0 >= m.min_points)
                ok = enough & (n1 <= m.count_ratio * n0) & (n0 <= m.count_ratio * n1)
                few[sel] = ~enough
                good = sel[ok]
                v_at, W[good] = _affine_flow(b1[ok], b0[ok], gap, m.planarity)
                # the field about the motion cell's own centroid (the block's is c1)
                c1 = b1[ok, 1:4] / b1[ok, :1]
                vc[good] = v_at + np.einsum("mij,mj->mi", W[good], ref[good] - c1)
                todo[good] = False
            span = self.k * self.grid.h
            speed = _box_speed(vc, W, ref, np.asarray(self.grid.origin) + c * span, span)
            turn = np.linalg.norm(W, axis=(1, 2))
            measured = ~todo & (speed <= m.v_max) & (turn <= m.w_max)
            vc[~measured] = 0.0
            W[~measured] = 0.0
            self._smooth(occ, measured, vc, W, ref, last)
            state = np.where(measured, CELL_MEASURED, CELL_NONE).astype(np.uint8)
            if m.min_neighbours > 0:
                self._propagate(occ, c, vc, W, ref, state)
            # a propagated field extrapolated over its cell obeys v_max as a measured one does
            box = _box_speed(vc, W, ref, np.asarray(self.grid.origin) + c * span, span)
            far = (state == CELL_PROPAGATED) & (box > m.v_max)
            state[far] = CELL_NONE
            slow = far | (box < m.v_min)
            vc[slow] = 0.0
            W[slow] = 0.0
            self.state[occ] = state
            self._summary = _summary(state, np.linalg.norm(vc[state == CELL_MEASURED], axis=1))
            self._summary.update(rejected_few_points=int(np.count_nonzero(todo & few)),
                                 rejected_counts=int(np.count_nonzero(todo & ~few)),
                                 rejected_v_max=int(np.count_nonzero(~todo & (speed > m.v_max))),
                                 rejected_w_max=int(np.count_nonzero(~todo & (speed <= m.v_max) & (turn > m.w_max))),
                                 cells_smoothed=self._smoothed,
                                 turn_max_radps=round(float(np.max(turn[state == CELL_MEASURED], initial=0.0)), 3))
        i = np.searchsorted(occ, self._coarse[fine])
        Wf = W[i]
        vf = vc[i] + np.einsum("mij,mj->mi", Wf, self._corners[fine] - ref[i])
        out = np.zeros((moments.shape[0], CELL_MOTION), np.float32)
        out[fine] = pack_motion(vf, Wf)
        vmax = float(np.max(_box_speed(vf, Wf, self._corners[fine], self._corners[fine], self.grid.h), initial=0.0))
        self.cell_motion = out
        return out, vmax

    def _smooth(self, occ, measured, vc, W, ref, last) -> None:
        """Cells measured in this estimate and the last one, whose two fields agree at the cell's
        new centroid, take their weighted mean (``smoothing``, ``smooth_gate``; the module
        docstring); in place on ``vc`` and ``W``. Keeps the measured cells' fields (the means
        where taken) for the next estimate."""
        m = self.model
        cells = occ[measured]
        self._smoothed = 0
        if last is not None and m.smoothing < 1.0 and cells.size and last[0].size:
            l_cells, l_v, l_W, l_ref = last
            pos = np.minimum(np.searchsorted(l_cells, cells), l_cells.size - 1)
            both = l_cells[pos] == cells
            i = np.flatnonzero(measured)[both]
            j = pos[both]
            old = l_v[j] + np.einsum("mij,mj->mi", l_W[j], ref[i] - l_ref[j])    # the last field at the new centroid
            new = vc[i]
            gate = m.smooth_gate * np.maximum(np.linalg.norm(new, axis=1), np.linalg.norm(old, axis=1)) + m.v_min
            agree = np.linalg.norm(new - old, axis=1) <= gate
            a = m.smoothing
            k = i[agree]
            vc[k] = a * new[agree] + (1.0 - a) * old[agree]
            W[k] = a * W[k] + (1.0 - a) * l_W[j[agree]]
            self._smoothed = int(k.size)
        self._last = (cells, vc[measured], W[measured], ref[measured])    # (copies: fancy indexing)

    def _propagate(self, occ, c, vc, W, ref, state) -> None:
        """Unknown occupied cells take their measured neighbours' mean motion where enough of
        them agree at the cell's centroid (see the module docstring); in place on ``vc``,
        ``W`` and ``state``."""
        m = self.model
        unknown = np.flatnonzero(state == CELL_NONE)
        if not unknown.size or not np.any(state == CELL_MEASURED):
            return
        nx, ny, nz = self.dims
        nb = c[unknown, None, :] + self._offsets[None]                      # (U, 26, 3)
        inside = np.all((nb >= 0) & (nb < np.asarray(self.dims)), axis=2)
        lin = (nb[..., 2] * ny + nb[..., 1]) * nx + nb[..., 0]
        pos = np.searchsorted(occ, np.where(inside, lin, 0))
        pos = np.minimum(pos, occ.size - 1)
        hit = inside & (occ[pos] == lin) & (state[pos] == CELL_MEASURED)
        w = hit.astype(np.float64)
        cnt = w.sum(1)
        # every neighbour's field at the unknown cell's centroid
        at = vc[pos] + np.einsum("uaij,uaj->uai", W[pos], ref[unknown, None, :] - ref[pos])   # (U, 26, 3)
        mean = (at * w[..., None]).sum(1) / np.maximum(cnt, 1)[:, None]
        dev = np.linalg.norm(at - mean[:, None], axis=2)
        spread = np.max(np.where(hit, dev, 0.0), axis=1)
        ok = (cnt >= m.min_neighbours) & (spread <= m.coherence * np.linalg.norm(mean, axis=1) + m.v_min)
        wmean = (W[pos] * w[..., None, None]).sum(1) / np.maximum(cnt, 1)[:, None, None]
        vc[unknown[ok]] = mean[ok]
        W[unknown[ok]] = wmean[ok]
        state[unknown[ok]] = CELL_PROPAGATED


def _summary(state: np.ndarray, measured_speed: np.ndarray) -> dict:
    """Counts of the occupied motion cells per state and the measured speeds (m/s); ``update``
    adds why the unmeasured ones were not (rejected_few_points: fewer than min_points in the
    largest block; rejected_counts: its counts disagree by more than count_ratio: an edge, a
    hole, the surface crossing cells; rejected_v_max; rejected_w_max: its plane turned faster
    than w_max) and the measured cells' fastest turning rate (turn_max_radps, rad/s)."""
    return {"cells_measured": int(np.count_nonzero(state == CELL_MEASURED)),
            "cells_propagated": int(np.count_nonzero(state == CELL_PROPAGATED)),
            "cells_unknown": int(np.count_nonzero(state == CELL_NONE)),
            "speed_max_mps": round(float(np.max(measured_speed, initial=0.0)), 4),
            "speed_median_mps": round(float(np.median(measured_speed)), 4) if measured_speed.size else 0.0,
            "rejected_few_points": 0, "rejected_counts": 0, "rejected_v_max": 0, "rejected_w_max": 0,
            "turn_max_radps": 0.0}


def _to_world(local: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Moments about the world origin from moments (M, N_MOMENTS) about the corners (M, 3)."""
    m = local.copy()
    n, s = m[:, 0], m[:, 1:4].copy()
    m[:, 1:4] = s + n[:, None] * corners
    for j, (a, b) in enumerate(_PAIRS):
        m[:, 4 + j] += corners[:, a] * s[:, b] + corners[:, b] * s[:, a] + n * corners[:, a] * corners[:, b]
    return m


def _planes(b: np.ndarray, planarity: float):
    """(centroids (M, 3), unit normals (M, 3), planar (M,), thickness (M,): the smallest
    covariance eigenvalue, m^2) of block moments (M, N_MOMENTS): planar where the smallest
    eigenvalue is below ``planarity`` times the middle one."""
    n = b[:, 0]
    cen = b[:, 1:4] / n[:, None]
    S = np.empty((len(b), 3, 3))
    for j, (a, k) in enumerate(_PAIRS):
        S[:, a, k] = S[:, k, a] = b[:, 4 + j] / n - cen[:, a] * cen[:, k]
    w, U = np.linalg.eigh(S)
    return cen, U[:, :, 0], w[:, 0] < planarity * w[:, 1], w[:, 0]


#: a planar block turns rigidly only if its thickness (smallest covariance eigenvalue: the depth
#: noise across the plane) stays within this factor, plus THICKNESS_FLOOR (m^2, (1 mm)^2):
#: a flat patch that becomes a step or a fold fits a tilted plane that is thicker, not turned
THICKNESS_RATIO = 2.0
THICKNESS_FLOOR = 1e-6


def _affine_flow(b1: np.ndarray, b0: np.ndarray, gap: float, planarity: float):
    """(velocity at the new block's centroid c1 (M, 3), gradient W (M, 3, 3)) from block
    moments (M, N_MOMENTS) of the new and previous snapshot: a point p moves at v + W (p - c1).

    Not planar now: the centroid displacement over ``gap``, W = 0. Planar now, not before: only
    its component along the new normal n1 (motion along a surface is not observable from its
    points, the aperture problem, and the centroid's sideways jitter as pixel rays enter and
    leave the block would tear the predicted surface apart between cells), W = 0. Planar in
    both: each point of the new plane moves along n1 by its distance to the previous plane per
    gap (the module docstring), W = n1 (n0 - (n0 . n1) n1)^T / gap, where also its thickness
    stayed (``THICKNESS_RATIO``; else a step or fold appeared in it: normal velocity only)."""
    c1, nrm1, planar1, th1 = _planes(b1, planarity)
    c0 = b0[:, 1:4] / b0[:, :1]
    nrm0 = np.zeros_like(nrm1)
    planar0 = np.zeros_like(planar1)
    th0 = np.zeros_like(th1)
    if planar1.any():                                 # the previous plane matters only where the new one is planar
        _, nrm0[planar1], planar0[planar1], th0[planar1] = _planes(b0[planar1], planarity)
    planar0 &= (th1 <= THICKNESS_RATIO * th0 + THICKNESS_FLOOR) & (th0 <= THICKNESS_RATIO * th1 + THICKNESS_FLOOR)
    v = (c1 - c0) / gap
    W = np.zeros((len(b1), 3, 3))
    flat = planar1 & ~planar0
    vn = np.einsum("ij,ij->i", v, nrm1)
    v[flat] = vn[flat, None] * nrm1[flat]
    both = planar1 & planar0
    n1 = nrm1[both]
    n0 = nrm0[both] * np.sign(np.einsum("ij,ij->i", nrm0[both], n1) + 1e-300)[:, None]  # eigenvector signs
    v[both] = n1 * np.einsum("ij,ij->i", n0, c1[both] - c0[both])[:, None] / gap
    tang = n0 - np.einsum("ij,ij->i", n0, n1)[:, None] * n1
    W[both] = n1[:, :, None] * tang[:, None, :] / gap
    return v, W


def _box_speed(v: np.ndarray, W: np.ndarray, ref: np.ndarray, lo: np.ndarray, size: float) -> np.ndarray:
    """Largest speed (M,) m/s of the affine fields v + W (p - ref) over the boxes [lo, lo +
    size]^3 (an affine field's largest norm over a box is at one of its 8 corners)."""
    base = v + (W @ (lo - ref)[:, :, None])[:, :, 0]
    col = W * size                                    # (M, 3, 3): the field's change along x, y, z
    out = np.zeros(len(v))
    for bx in (0, 1):
        for by in (0, 1):
            for bz in (0, 1):
                u = base + bx * col[:, :, 0] + by * col[:, :, 1] + bz * col[:, :, 2]
                out = np.maximum(out, np.einsum("mi,mi->m", u, u))
    return np.sqrt(out)


#: floats per hash cell of a cell motion: velocity at the cell's lower corner (x, y, z, 0) and the
#: three rows of its gradient W (each x, y, z, 0): four float4 for the device kernels
CELL_MOTION = 16


def pack_motion(v: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Cell motions (M, CELL_MOTION) float32 from velocities at the cell corners (M, 3, m/s)
    and gradients (M, 3, 3, 1/s)."""
    out = np.zeros((len(v), 4, 4), np.float32)
    out[:, 0, :3] = v
    out[:, 1:, :3] = W
    return out.reshape(len(v), CELL_MOTION)


def expand(cell_motion: np.ndarray | None, cell_start: np.ndarray, points_sorted: np.ndarray,
           grid: Grid) -> np.ndarray | None:
    """Per-point velocities (N, 3) float32 in cell-sorted order from the cell motions (n_cells,
    CELL_MOTION): v + W (p - corner), in float32 with the device kernels' order of operations
    (corner = origin + index * (1 / inv_h), each row's products summed x, y, then z)."""
    if cell_motion is None:
        return None
    counts = np.diff(cell_start).astype(np.int64)
    cell = np.repeat(np.arange(counts.size), counts)
    nx, ny, _ = grid.dims
    ijk = np.stack([cell % nx, (cell // nx) % ny, cell // (nx * ny)], axis=1).astype(np.float32)
    h = np.float32(1.0) / grid.inv_h
    d = np.asarray(points_sorted, np.float32)[:, :3] - (np.asarray(grid.origin, np.float32) + ijk * h)
    cm = np.asarray(cell_motion, np.float32).reshape(-1, 4, 4)[cell]
    out = np.empty((len(cell), 3), np.float32)
    for r in range(3):
        w = cm[:, 1 + r]
        out[:, r] = cm[:, 0, r] + ((w[:, 0] * d[:, 0] + w[:, 1] * d[:, 1]) + w[:, 2] * d[:, 2])
    return out


def extra_span(vmax: float, dt: float) -> float:
    """How much further (m) than the proxy's reach the hash must be searched this tick (with a
    1 um allowance for the float32 rounding of p + v dt; exactly 0 when nothing moves)."""
    e = float(vmax) * float(dt)
    return e + 1e-6 if e > 0 else 0.0
