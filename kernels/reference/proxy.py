"""Batched proxy movement of one haptic tick, NumPy reference (SPEC 2 and 3).

The algorithm is described in ``pointfence.kernels.proxy``. Here every step is vectorised
over the B proxies and their working sets: per tick each proxy gathers the points within
``reach + skin`` of its position into a padded (B, K) working set (regathered for a proxy
that wanders further than ``skin``), then the steps run on those arrays until every proxy has
converged or spent the step budget. Results do not depend on the working sets (they always
hold every point within reach), only speed does.

Arithmetic is float32 in the OpenCL kernel's operation order, and the normal sums are taken in
its order too (``lane_sum``), so the reference and OpenCL agree bit for bit; Warp's block
reductions sum in another order and agree to rounding.
"""
from __future__ import annotations

import numpy as np

from ..motion import extra_span
from ..neighbors import search_span
from ..params_haptics import HapticParams
from ..proxy import CONTACT, ENTRENCHED, FREE, LANES, WS_CAPACITY, ProxyBatch
from ..snapshot import HostSnapshot

F = np.float32
INF = F(np.inf)


class WorkingSet:
    """Padded per-proxy point sets: xyz (B, K, 3), rho (B, K) and valid (B, K)."""

    def __init__(self, xyz, rho, valid):
        self.xyz, self.rho, self.valid = xyz, rho, valid

    @classmethod
    def empty(cls, B: int) -> "WorkingSet":
        return cls(np.zeros((B, 0, 3), F), np.zeros((B, 0), F), np.zeros((B, 0), bool))

    def take(self, rows) -> "WorkingSet":
        return WorkingSet(self.xyz[rows], self.rho[rows], self.valid[rows])

    def put(self, rows, other: "WorkingSet") -> "WorkingSet":
        """A copy with ``rows`` replaced by ``other`` (re-padded to the larger K)."""
        K = max(self.xyz.shape[1], other.xyz.shape[1])
        out = self.padded(K)
        o = other.padded(K)
        out.xyz[rows], out.rho[rows], out.valid[rows] = o.xyz, o.rho, o.valid
        return out

    def padded(self, K: int) -> "WorkingSet":
        B, k = self.rho.shape
        if k == K:
            return WorkingSet(self.xyz.copy(), self.rho.copy(), self.valid.copy())
        xyz = np.zeros((B, K, 3), F)
        rho = np.zeros((B, K), F)
        valid = np.zeros((B, K), bool)
        xyz[:, :k], rho[:, :k], valid[:, :k] = self.xyz, self.rho, self.valid
        return WorkingSet(xyz, rho, valid)


def pack_rows(owner: np.ndarray, idx: np.ndarray, B: int, points: np.ndarray, rho: np.ndarray) -> WorkingSet:
    """Working set from (owner proxy, point index) pairs sorted by owner; ``points`` (M, 3+)
    and ``rho`` (M,) are indexed by ``idx``."""
    counts = np.bincount(owner, minlength=B) if owner.size else np.zeros(B, np.int64)
    K = int(counts.max()) if B else 0
    first = np.zeros(B + 1, np.int64)
    np.cumsum(counts, out=first[1:])
    col = np.arange(owner.size) - first[owner]
    xyz = np.zeros((B, K, 3), F)
    r = np.zeros((B, K), F)
    valid = np.zeros((B, K), bool)
    xyz[owner, col] = points[idx, :3]
    r[owner, col] = rho[idx]
    valid[owner, col] = True
    return WorkingSet(xyz, r, valid)


def gather_hash(snap: HostSnapshot, X0: np.ndarray, radius: float, fixture: bool, r1: float,
                dt: float = 0.0, extra: float = 0.0) -> WorkingSet:
    """Points of the snapshot within ``radius`` of each X0 (B, 3), vectorised over B.

    The cells within ``search_span(radius + extra, h)`` of each proxy's cell are scanned (the
    same cells as ``reference.neighbors.query_cells`` and the device kernels); fixture mode keeps
    only protected points and uses their r_f as rho, rendering mode all points with rho = r1.
    With ``dt`` > 0 and a snapshot velocity, every point is taken at p + v dt (float32, the
    device kernels' arithmetic); ``extra`` >= |v| dt bounds how far a point moved.
    """
    B = X0.shape[0]
    if B == 0 or snap.n_points == 0:
        return WorkingSet.empty(B)
    g = snap.grid
    n = np.asarray(g.dims, np.int64)
    span = search_span(radius + extra, g.h)
    c = np.floor((X0 - np.asarray(g.origin, F)) * g.inv_h)
    c = np.clip(c, -(span + 1), n + span).astype(np.int64)
    lo = np.maximum(c - span, 0)
    hi = np.minimum(c + span, n - 1)
    off = np.arange(-span, span + 1)
    dz, dy = np.meshgrid(off, off, indexing="ij")
    iz = c[:, None, 2] + dz.reshape(-1)[None]
    iy = c[:, None, 1] + dy.reshape(-1)[None]
    ok = (iz >= lo[:, None, 2]) & (iz <= hi[:, None, 2]) & (iy >= lo[:, None, 1]) & (iy <= hi[:, None, 1])
    ok &= (lo[:, None, 0] <= hi[:, None, 0])
    owner = np.broadcast_to(np.arange(B)[:, None], ok.shape)[ok]
    base = (iz[ok] * n[1] + iy[ok]) * n[0]
    a = snap.cell_start[base + lo[owner, 0]].astype(np.int64)
    e = snap.cell_start[base + hi[owner, 0] + 1].astype(np.int64)
    L = e - a
    tot = int(L.sum())
    if tot == 0:
        return WorkingSet.empty(B)
    rows = np.repeat(np.arange(L.size), L)
    first = np.zeros(L.size, np.int64)
    np.cumsum(L[:-1], out=first[1:])
    idx = a[rows] + (np.arange(tot) - first[rows])
    own = owner[rows]
    if fixture:
        keep = snap.protected[idx] != 0
        idx, own = idx[keep], own[keep]
    P = snap.points[idx, :3]
    if dt > 0 and snap.velocity is not None:
        P = (P + snap.velocity[idx] * F(dt)).astype(F)
    d = P - X0[own]
    d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
    keep = d2 <= F(radius) * F(radius)
    idx, own, P = idx[keep], own[keep], P[keep]
    rho = snap.points[idx, 3] if fixture else np.full(idx.size, F(r1), F)
    return pack_rows(own, np.arange(idx.size), B, P, rho)


def lane_sum(c: np.ndarray, direct: np.ndarray, lanes: int) -> np.ndarray:
    """Sum contributions c (B, K, 3) in the device kernel's order.

    Working-set path: point j goes to vector lane j % lanes, each lane accumulates in order and
    the lanes are then added 0..lanes-1; direct hash path (``direct``): one running sum in
    snapshot order. Sequential float32 sums (cumsum), not numpy's pairwise ones.
    """
    B, K, _ = c.shape
    out = np.zeros((B, 3), F)
    if K == 0:
        return out
    if np.any(~direct):
        Kp = -(-K // lanes) * lanes
        cp = np.zeros((int(np.sum(~direct)), Kp, 3), F)
        cp[:, :K] = c[~direct]
        per_lane = np.cumsum(cp.reshape(cp.shape[0], Kp // lanes, lanes, 3), axis=1, dtype=F)[:, -1]
        out[~direct] = np.cumsum(per_lane, axis=1, dtype=F)[:, -1]
    if np.any(direct):
        out[direct] = np.cumsum(c[direct], axis=1, dtype=F)[:, -1]
    return out


def evaluate(X: np.ndarray, ws: WorkingSet, p: HapticParams, direct=None, lanes: int = LANES):
    """State, normal, smallest clearance and per-point arrays at X (B, 3) over working sets."""
    if direct is None:
        direct = np.zeros(X.shape[0], bool)
    w = X[:, None, :] - ws.xyz  # X - P, (B, K, 3)
    d2 = w[..., 0] * w[..., 0] + w[..., 1] * w[..., 1] + w[..., 2] * w[..., 2]
    d = np.sqrt(d2)
    e = d - ws.rho
    inb = ws.valid & (e < F(p.r3 - p.r1))
    min_e = np.min(np.where(inb, e, INF), axis=1, initial=INF)
    use = inb & (d > 0)
    with np.errstate(divide="ignore"):
        inv = np.where(use, F(1) / np.where(use, d, F(1)), F(0))
    ns = lane_sum(w * inv[..., None], direct, lanes)
    nn = np.sqrt(ns[:, 0] * ns[:, 0] + ns[:, 1] * ns[:, 1] + ns[:, 2] * ns[:, 2])
    has = nn > 0
    normal = np.where(has[:, None], ns / np.where(has, nn, F(1))[:, None], F(0)).astype(F)
    state = np.where(min_e < 0, ENTRENCHED, np.where(min_e < F(p.band), CONTACT, FREE)).astype(np.int32)
    return state, normal, min_e, w, d2


def direction(X, H, state, normal, min_e, p: HapticParams):
    """Step directions and length bounds from the movement rules.

    Returns (u, L, push, u2, L2): the first choice u (B, 3) with its bound L (B,) and ``push``
    (B,) where it is the push-out along n; where the push-out is blocked by the clipping test
    the step goes along (u2, L2) instead: along v with the HIP outside (v.n > 0), along v
    projected on the plane of n with it inside (rule 3/4 for entrenched).
    """
    v = (H - X).astype(F)
    vl = np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])
    vn = v[:, 0] * normal[:, 0] + v[:, 1] * normal[:, 1] + v[:, 2] * normal[:, 2]
    vp = v - vn[:, None] * normal
    vpl = np.sqrt(vp[:, 0] * vp[:, 0] + vp[:, 1] * vp[:, 1] + vp[:, 2] * vp[:, 2])
    has_n = np.any(normal != 0, axis=1)
    along_n = (state == ENTRENCHED) & has_n
    # the contact rules: along v (HIP outside or no normal) or along its projection
    rule_v = (state == FREE) | (vn > 0) | ~has_n
    u2 = np.zeros_like(v)
    L2 = np.zeros(X.shape[0], F)
    sv = rule_v & (vl > 0)
    u2[sv] = v[sv] / vl[sv, None]
    L2[sv] = vl[sv]
    sp = ~rule_v & (vpl > 0)
    u2[sp] = vp[sp] / vpl[sp, None]
    L2[sp] = vpl[sp]
    L2 = np.minimum(L2, F(p.step))
    u, L = u2.copy(), L2.copy()
    u[along_n] = normal[along_n]
    L[along_n] = push_length(min_e[along_n], p)
    return u, L, along_n, u2, L2


def push_length(min_e, p: HapticParams):
    """Length bound of a push-out: to the middle of the contact band, at most delta."""
    return np.minimum(F(p.band / 2) - min_e, F(p.step)).astype(F)


def floor_of(state, min_e, p: HapticParams):
    """(limit F, buried) per proxy: the clearance a step may not take a point below.

    F = (r2 - r1)/2 for a free step; -slack for the others, or min e where the proxy is buried
    (min e < -slack - margin: only the scene moving into the proxy puts it there), so that the
    deepest penetration never grows."""
    deep = F(-p.slack) - F(p.margin)
    buried = (state == ENTRENCHED) & (min_e < deep)
    lim = np.where(state == FREE, F(p.band / 2), np.where(buried, min_e, F(-p.slack))).astype(F)
    return lim, buried


def limit_c(w, d2, lim, ws: WorkingSet, p: HapticParams):
    """c_i = |X - P_i|^2 - (rho_i + F + margin)^2 (B, K): >= 0 for the clear points, < 0 for
    those at the limit (clearance below F + margin)."""
    rc = ws.rho + (lim + F(p.margin))[:, None]
    return d2 - rc * rc


def clip_step(u, L, c, w, ws: WorkingSet):
    """Longest step <= L along u under the clipping rule (kernels/proxy.py, step 3).

    ``c`` from ``limit_c``: a clear point (c >= 0) stops the step where its clearance reaches
    F + margin (swept sphere); a point at the limit (c < 0) may not be approached at all
    (b = u.(X - P) < 0 gives step 0)."""
    b = u[:, None, 0] * w[..., 0] + u[:, None, 1] * w[..., 1] + u[:, None, 2] * w[..., 2]
    disc = b * b - c
    ahead = ws.valid & (b < 0)
    hit = ahead & (c >= 0) & (disc > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_out = c / (-b + np.sqrt(np.maximum(disc, F(0))))
    t = np.where(hit, t_out, INF)
    t = np.where(ahead & (c < 0), F(0), t)
    tmin = np.min(t, axis=1, initial=INF)
    return np.maximum(np.minimum(L, tmin), F(0)).astype(F)


def away_direction(c, w, d2, ws: WorkingSet, direct, lanes: int):
    """Unit direction away from the points at the limit: normalize(sum (X - P_i)/|X - P_i|) over
    c_i < 0, summed in the order of the normal (zero if the sum vanishes)."""
    d = np.sqrt(d2)
    use = ws.valid & (c < 0) & (d > 0)
    with np.errstate(divide="ignore"):
        inv = np.where(use, F(1) / np.where(use, d, F(1)), F(0))
    s = lane_sum(w * inv[..., None], direct, lanes)
    nn = np.sqrt(s[:, 0] * s[:, 0] + s[:, 1] * s[:, 1] + s[:, 2] * s[:, 2])
    has = nn > 0
    return np.where(has[:, None], s / np.where(has, nn, F(1))[:, None], F(0)).astype(F)


def _sq(a: np.ndarray) -> np.ndarray:
    return a[:, 0] * a[:, 0] + a[:, 1] * a[:, 1] + a[:, 2] * a[:, 2]


def run_tick(X: np.ndarray, H: np.ndarray, gather, p: HapticParams, cap: int = WS_CAPACITY, lanes: int = LANES):
    """One tick for proxies X (B, 3) towards HIPs H (B, 3).

    ``gather(X0) -> WorkingSet`` returns every point within ``reach + skin`` of each X0 in
    snapshot order. A proxy whose working set holds more than ``cap`` points sums its normal
    sequentially (the device scans the hash directly then). Returns
    (X, normal, state, steps, converged, nearest).
    """
    X = X.astype(F).copy()
    H = H.astype(F)
    B = X.shape[0]
    X0 = X.copy()
    ws = gather(X0)
    count = ws.valid.sum(axis=1)
    steps = np.zeros(B, np.int32)
    conv = np.zeros(B, bool)
    normal = np.zeros((B, 3), F)
    state = np.zeros(B, np.int32)
    near = np.full(B, INF, F)
    active = np.arange(B)
    skin2 = F(p.skin) * F(p.skin)
    uprev = np.zeros((B, 3), F)   # direction of each proxy's last sliding or free step

    def regather():
        nonlocal ws
        out = active[_sq(X[active] - X0[active]) > skin2]
        if out.size:
            X0[out] = X[out]
            new = gather(X0[out])
            ws = ws.put(out, new)
            count[out] = new.valid.sum(axis=1)

    for _ in range(p.max_steps):
        if active.size == 0:
            break
        regather()
        wa = ws.take(active)
        Xa, Ha = X[active], H[active]
        direct = count[active] > cap
        st, nrm, me, w, d2 = evaluate(Xa, wa, p, direct, lanes)
        u, L, push, u2, L2 = direction(Xa, Ha, st, nrm, me, p)
        lim, buried = floor_of(st, me, p)
        c = limit_c(w, d2, lim, wa, p)
        s = clip_step(u, L, c, w, wa)
        along_n = push.copy()
        retry = push & (s < F(p.tolerance))
        if retry.any():  # push-out blocked: the contact rule's direction instead
            r = np.flatnonzero(retry)
            wr = wa.take(r)
            s2 = clip_step(u2[r], L2[r], c[r], w[r], wr)
            u[r], s[r] = u2[r], s2
            along_n[r] = False
            away = buried[r] & (s2 < F(p.tolerance))
            if away.any():  # buried and both blocked: away from the deepest points
                a = r[away]
                along_n[a] = True
                ua = away_direction(c[a], w[a], d2[a], wa.take(a), direct[a], lanes)
                u[a] = ua
                sa = clip_step(ua, L[a], c[a], w[a], wa.take(a))
                s[a] = np.where(np.any(ua != 0, axis=1), sa, F(0))
        done = s < F(p.tolerance)
        # a slide turning back against the previous one (rocking in a crease) ends the tick too
        up = uprev[active]
        cos = (u[:, 0] * up[:, 0] + u[:, 1] * up[:, 1]) + u[:, 2] * up[:, 2]
        slide = ~along_n & ~done
        done |= slide & (cos < F(p.turn_back_cos))
        keep = slide & ~done
        uprev[active[keep]] = u[keep]
        normal[active], state[active], near[active] = nrm, st, me
        conv[active[done]] = True
        mv = ~done
        X[active[mv]] = (Xa[mv] + s[mv, None] * u[mv]).astype(F)
        steps[active[mv]] += 1
        active = active[mv]
    if active.size:  # budget spent: report state and normal at the final position
        regather()
        st, nrm, me, _, _ = evaluate(X[active], ws.take(active), p, count[active] > cap, lanes)
        normal[active], state[active], near[active] = nrm, st, me
    return X, normal, state, steps, conv, near


class NumpyProxies(ProxyBatch):
    """Reference proxies on a frame pipeline (or directly on a ``HostSnapshot``)."""

    def __init__(self, pipeline, positions, params=None, snapshot: HostSnapshot | None = None,
                 ws_capacity: int = WS_CAPACITY, lanes: int = LANES):
        self._snapshot = snapshot
        self.ws_cap = int(ws_capacity)
        self.lanes = int(lanes)
        super().__init__(pipeline, positions, params)

    def _upload_positions(self):
        pass

    def snapshot(self) -> HostSnapshot:
        return self._snapshot if self._snapshot is not None else self.pipeline.host_snapshot()

    def _step(self, hips):
        snap = self.snapshot()
        p = self.params
        fixture = p.mode == "fixture"
        radius = self.reach + p.skin

        dt = self._tick_dt(snap.time, snap.vmax)
        extra = extra_span(snap.vmax, dt)

        def gather(X0):
            return gather_hash(snap, X0, radius, fixture, p.r1, dt, extra)

        n = self.n
        X, nrm, st, steps, conv, near = run_tick(self._positions[:n], hips, gather, p, self.ws_cap, self.lanes)
        self._positions[:n], self._normals[:n], self._states[:n] = X, nrm, st
        self._steps[:n], self._converged[:n], self._nearest[:n] = steps, conv, near
