"""The batched proxy: what every backend's proxy kernel provides (SPEC 2 and 3).

A ``ProxyBatch`` holds B proxies whose state persists between haptic ticks. One call to
``step(hips)`` runs the whole proxy movement of one tick for all of them (one kernel launch on
device backends) against the pipeline's current snapshot and fills preallocated host arrays:

* ``positions`` float32 (B, 3): proxy centres X_p (m, world frame);
* ``normals`` float32 (B, 3): estimated surface normal (eq. 2.1), zero where no point is near;
* ``states`` int32 (B,): ``FREE`` (0), ``CONTACT`` (1) or ``ENTRENCHED`` (2);
* ``steps`` int32 (B,): proxy steps taken this tick;
* ``converged`` bool (B,): the tick ended because the next step was shorter than the
  tolerance or would turn back against the previous slide (False: the step budget ran out
  first);
* ``nearest`` float32 (B,): the smallest clearance e_i = |X_p - P_i| - rho_i among the points
  within the normal band (rho_i = r1 in rendering mode, r_f(i) in fixture mode); +inf if none.
  In rendering mode the distance from the centre to the nearest point is ``nearest + r1``.

Algorithm (identical in the NumPy reference and the device kernels), per step:

1. Evaluate at X_p: clearances e_i, state (entrenched if min e < 0, contact if min e < r2 - r1,
   else free) and the normal n = normalize(sum (X_p - P_i) / |X_p - P_i|) over e_i < r3 - r1.
2. Direction u and length L with v = X_hip - X_p (dissertation 2.2.4):
   free -> along v, L = |v|; contact with v.n > 0 (HIP outside) -> along v, L = |v|;
   contact with v.n <= 0 (HIP inside) -> along v projected on the plane of n, L = its length
   (the HIP's projection, never past it); entrenched -> along n, L = (r2 - r1)/2 - min e, so
   the push-out never overshoots the contact band (with no normal, along v). L <= delta.
3. Clipping. The step has a limit F on the clearances: F = (r2 - r1)/2 for a free step (the
   proxy lands in the contact band), F = -slack for the others (sliding may dig at most
   ``slack`` deep before step 1 pushes the proxy out again), and F = min e where the proxy is
   *buried* (min e < -slack - margin, which only the scene moving into the proxy, or a reset,
   can cause). With b_i = u.(X_p - P_i) (< 0: the step approaches P_i), each point is, at the
   step's start, either
   - clear (e_i >= F + margin): the step is shortened so that its clearance does not drop
     below F + margin anywhere along the step (swept sphere of radius rho_i + F + margin), or
   - at the limit (e_i < F + margin): it may not be approached at all (b_i < 0 -> no step).
   ``margin`` (1 um) absorbs float32 rounding: a clipped step ends a margin above the limit, and
   clearances within a margin of it all count as at the limit, so no decision turns on the
   last bit of a clearance (the reference, OpenCL and Warp take the same branches).
   If the push-out along n is blocked (step below ``tolerance``), the step goes by the contact
   rule's direction instead (along v with v.n > 0, else along v projected on the plane of n);
   if the proxy is buried and that is blocked too, it goes along the direction away from the
   points at the limit, normalize(sum (X_p - P_i)/|X_p - P_i|) over e_i < F + margin, with
   the push-out's length. All three use the same limit.
   Guarantees, whatever delta is: a step never carries the proxy through a surface; in a
   static scene a proxy whose clearances are all >= -slack keeps them >= -slack, i.e. no point
   comes closer than ``r1 - slack`` to its centre (``r_f - slack`` for fixtures), up to float32
   rounding of the position (< 1e-7 m near 1 m, inside the margin); and a step never leaves
   min e below min(-slack, min e at its start), so a buried proxy is never pushed deeper. It gets
   out along n, by the contact rule, or away from its deepest points; it can only be held
   where those points surround its centre (the scene closed a pocket narrower than the proxy
   around it), and then rests at the pocket's widest place until the scene or the HIP frees it.
4. If the clipped step is shorter than ``tolerance``, the tick has converged. It has also
   converged if the step is a slide or free step (not a push-out along n, nor away from the
   deepest points) whose direction turns back against the previous such step of the tick:
   cosine below ``turn_back_cos`` (-0.5). The proxy is then rocking across a crease of the
   cloud or under a noisy normal, and further steps would only rock it (``HapticParams``).
   Else move.

Decisions that remain thresholds on computed values (the states at e = 0 and e = r2 - r1, the
normal band e < r3 - r1, ``tolerance``) can still part two backends when a step happens to end
within rounding of one of them; no proxy rests on one by construction.

The state, normal and clearance reported are those at the final position.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod

import numpy as np

from .errors import InputError
from .params_haptics import HapticParams

FREE, CONTACT, ENTRENCHED = 0, 1, 2
#: points per proxy working set on device backends (more in reach: the kernel scans the hash)
WS_CAPACITY = 4096
#: vector width of the device kernels' point loops (the reference sums in the same order); 8
#: floats fill an AVX register, and 16 left the OpenCL loops short of registers (10 % slower)
LANES = 8
STATE_NAMES = ("free", "contact", "entrenched")


def check_points3(a, what: str, n: int | None = None) -> np.ndarray:
    """Validate (B, 3) finite positions (m); return C-contiguous float32."""
    x = np.asarray(a)
    if x.ndim == 1 and x.shape[0] == 3:
        x = x[None]
    if x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"{what} shape {x.shape}; expected (B, 3) world positions in metres")
    if not np.issubdtype(x.dtype, np.number):
        raise InputError(f"{what} dtype {x.dtype}; expected floating point")
    if n is not None and x.shape[0] != n:
        raise InputError(f"{what}: {x.shape[0]} positions for {n} proxies; expected one per proxy "
                         "(use reset(positions) to change the number of proxies)")
    x = np.ascontiguousarray(x, dtype=np.float32)
    bad = ~np.all(np.isfinite(x), axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"{what}[{i}] = {x[i].tolist()} is not finite; expected finite positions in metres")
    return x


_add_reduce = np.add.reduce


def _finite_rows(a, n: int) -> bool:
    """Whether ``a`` is already a finite float (n, 3) array (checked without a temporary array)."""
    if not (type(a) is np.ndarray and a.shape == (n, 3) and a.dtype.kind == "f"):
        return False
    # (a finite array whose sum overflows takes the slow path, which accepts it.) A tick's few
    # rows are summed as Python floats: the first NumPy reduction of a tick runs through code
    # the frame threads have pushed out of the caches, several times the cost of the sum;
    # np.add.reduce, not a.sum(), for many rows (the method's Python wrapper costs more)
    if n <= _FEW:
        s = 0.0
        for x, y, z in a.tolist():
            s += x + y + z
        return math.isfinite(s)
    return math.isfinite(_add_reduce(a, None))


#: rows up to which ``_finite_rows`` sums in Python
_FEW = 16


def fixture_r_max(pipeline_params) -> float:
    """The largest fixture radius any point of the pipeline's snapshots can carry (m)."""
    r = pipeline_params.radius
    return float(r.r_max if r.adaptive else r.r_base)


class ProxyBatch(ABC):
    """B proxies on one frame pipeline; see the module docstring.

    Create with ``pipeline.proxies(positions, params)``. ``reset(positions)`` moves the proxies
    (and changes their number); ``step(hips)`` runs one tick. Invalid HIPs (NaN, inf, wrong
    shape) raise ``InputError`` before anything moves.
    """

    def __init__(self, pipeline, positions, params: HapticParams | None = None):
        self.pipeline = pipeline
        self.params = params if params is not None else HapticParams()
        if not isinstance(self.params, HapticParams):
            raise InputError(f"params = {self.params!r}; expected HapticParams")
        self.r_max = fixture_r_max(pipeline.params)
        self.reach = self.params.reach(self.r_max)
        self.n = 0
        self._cap = 0
        self._now = self._dt_request = None
        self.last_dt = 0.0
        self.reset(positions)

    # --- host arrays -------------------------------------------------------------------------
    def _alloc(self, n: int):
        if n <= self._cap:
            return
        cap = max(n, 2 * self._cap, 1)
        (self._positions, self._normals, self._nearest, self._states, self._steps,
         self._converged) = self._result_arrays(cap)
        self._nearest.fill(np.inf)
        self._cap = cap
        self._grow(cap)

    def _result_arrays(self, cap: int) -> tuple:
        """Backend hook: the batch's result arrays for ``cap`` proxies, where the backend wants
        them (its kernels may write them in place): positions and normals (cap, 3) float32,
        nearest clearances (cap,) float32, states and steps (cap,) int32, converged (cap,) bool."""
        return (np.zeros((cap, 3), np.float32), np.zeros((cap, 3), np.float32), np.zeros(cap, np.float32),
                np.zeros(cap, np.int32), np.zeros(cap, np.int32), np.zeros(cap, bool))

    def _grow(self, cap: int) -> None:
        """Backend hook: (re)allocate per-proxy storage for ``cap`` proxies."""

    @property
    def positions(self) -> np.ndarray:
        return self._positions[: self.n]

    @property
    def normals(self) -> np.ndarray:
        return self._normals[: self.n]

    @property
    def states(self) -> np.ndarray:
        return self._states[: self.n]

    @property
    def steps(self) -> np.ndarray:
        return self._steps[: self.n]

    @property
    def converged(self) -> np.ndarray:
        return self._converged[: self.n]

    @property
    def nearest(self) -> np.ndarray:
        return self._nearest[: self.n]

    def __len__(self) -> int:
        return self.n

    # --- API ---------------------------------------------------------------------------------
    def reset(self, positions) -> None:
        """Place the proxies at ``positions`` (B, 3) (free motion, zero normal); B may change."""
        x = check_points3(positions, "proxy positions")
        n = x.shape[0]
        self._alloc(n)
        self.n = n
        self._positions[:n] = x
        self._normals[:n] = 0
        self._states[:n] = FREE
        self._steps[:n] = 0
        self._converged[:n] = True
        self._nearest[:n] = np.inf
        self._upload_positions()

    def step(self, hips, now: float | None = None, dt: float | None = None) -> None:
        """Run one haptic tick: move every proxy towards its HIP (B, 3) under the point constraints.

        With motion prediction on (``PipelineParams.motion``), the points are taken where they
        will be ``dt`` seconds after the snapshot (``kernels/motion.py``): ``now`` is the tick's
        time on the frames' clock (dt = now - snapshot time + latency), or ``dt`` is given
        directly; both are clamped to the model's horizon. Without either, dt = 0. The dt used
        is left in ``last_dt``."""
        # the tick's fast path takes a finite float (B, 3) array as it is (the backend converts it
        # while copying it into its own HIP buffer): no array is allocated per tick
        h = hips if _finite_rows(hips, self.n) else check_points3(hips, "hips", self.n)
        if now is not None and not np.isfinite(now):
            raise InputError(f"now = {now!r}; expected a finite time in seconds (the frames' clock)")
        self._now, self._dt_request = now, dt
        self._step(h)

    def _tick_dt(self, t_snapshot: float, vmax: float) -> float:
        """dt of this tick for a snapshot taken at ``t_snapshot`` whose fastest point moves at ``vmax``."""
        self.last_dt = self.pipeline.params.motion.tick_dt(self._now, t_snapshot, vmax, self._dt_request)
        return self.last_dt

    def close(self) -> None:
        """Release what the backend holds between ticks (Warp's resident kernel); the batch can
        still step afterwards."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @abstractmethod
    def _upload_positions(self) -> None: ...

    @abstractmethod
    def _step(self, hips: np.ndarray) -> None: ...
