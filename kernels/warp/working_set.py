"""A proxy's working set in shared memory: gathered once, read by every step of the tick.

At the start of a tick (and when the proxy has wandered further than its skin from where the
set was gathered) the block gathers the points within ``reach + skin`` of the proxy into shared
memory: the cells that the set's bounding box touches are listed once (the row table), the
block scans their points with every thread taking every ``bd``-th candidate, counts the ones
within range, and an exclusive scan of the counts gives each thread where to write its points,
so the set's order does not depend on timing. The skin is ``WarpTuning.gather_skin`` (wider
than HapticParams.skin: a gather costs more on a GPU than the points it adds to each step), or
HapticParams.skin for a set that would not fit in ``cap`` points; a set that does not fit even
then is not gathered (-1) and the steps scan the hash (kernels/warp/points.py). Results do not
depend on the working set.

The evaluation pass also notes the points close enough to shorten a step (clearance below
``ProxyArgs.rclip``); the clip passes scan only those (the same step lengths, see
kernels/warp/steps.py). Where a thread holds at most 31 of the set's points (every CUDA block
size) it keeps them as a bit mask of its own points, and clips them itself: the evaluation
loop has no collective in it, and takes two points an iteration. Elsewhere (Warp's CPU device,
one thread a block) each warp lists its near points in shared memory. A minimum is exact in any
order, so both give the same step lengths. ``cap`` and the block size ``bd`` are constants of the generated code,
so ``make_working_set`` makes one set of functions per pair.
"""
from __future__ import annotations

from typing import NamedTuple

import warp as wp

from .args import ProxyArgs
from .frames import GridArgs
from .points import away_point, cell_of, clip_point, eval_point_e, point_at
from .primitives import ROWS_CAP, block_scan, block_sync, rows


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return __ffs(m) - 1;
#else
    return __builtin_ctz((unsigned)m);
#endif
""")
def lowest_bit(m: int) -> int:
    """Index of the lowest set bit of m (m != 0)."""
    ...


@wp.func
def next_row(k: int, r: int, rs: int, ab: wp.vec2i):
    """Advance a thread's cursor over the row table to the row holding candidate k (rs: the
    first candidate of row r, ab: row r's index range); return (r, rs, ab)."""
    while k >= rs + ab[1] - ab[0]:
        rs = rs + ab[1] - ab[0]
        r = r + 1
        ab = rows(0, r, 0, 0)
    return r, rs, ab


@wp.func
def in_set(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
           a: ProxyArgs, i: int, X0: wp.vec3, r2: float):
    """(whether sorted point i belongs to the working set around X0, the point at p + v dt):
    within reach + skin, and protected in fixture mode (the reference's gather)."""
    keep = int(0)
    q = wp.vec4(0.0)
    if i >= 0:
        if a.fixture == 0 or order[i] < 0:
            q = point_at(spts, svel, i, dt)
            dx = q[0] - X0[0]
            dy = q[1] - X0[1]
            dz = q[2] - X0[2]
            if dx * dx + dy * dy + dz * dz <= r2:
                keep = 1
    return keep, q



class WorkingSet(NamedTuple):
    """The working-set device functions for one (cap, bd), and the near lists' layout: ``wl``
    threads a warp (32 on CUDA, the block's one thread on the CPU), ``nj`` entries a warp."""

    ws: object        # ws(op, i, q): point i of the set in shared memory; op 1 writes q
    ws_eval: object   # step 1 over the set: normal sum, smallest clearance, the near points
    ws_clip: object   # step 3 over the near points: this thread's step limit
    ws_away: object   # the push away from the points at the limit, over the set
    gather: object    # gather the set around X0: (points or -1, next par, skin used)
    pad: object       # pad(n, lane): the far points after a set of n points (every thread)
    wl: int
    nj: int


def make_working_set(cap: int, bd: int) -> WorkingSet:
    """The working-set functions for sets of up to ``cap`` points and blocks of ``bd`` threads."""
    BD = bd
    # a "warp" of the near lists: 32 threads on CUDA, the one thread of a block on the CPU
    WL = 32 if BD >= 32 else 1
    # near-list entries per warp: every point a warp's threads hold
    NJ = WL * ((cap + BD - 1) // BD)
    # near points as a bit mask a thread (each thread clips its own points) where a thread holds
    # at most 31 points (the CUDA blocks), else the warp's near list (the CPU device's one thread
    # a block, unless the set is that small)
    MASK = (cap + BD - 1) // BD <= 31
    # the set in shared memory is padded with far points up to a multiple of 2 BD (the mask
    # evaluation takes two points an iteration, the second without a bounds test)
    PAD = -(-cap // (2 * BD)) * (2 * BD)
    ws_src = f"""
#if defined(__CUDA_ARCH__)
    __shared__ float4 ws[{PAD}];
    if (op == 1) ws[i] = make_float4(q[0], q[1], q[2], q[3]);
    else {{ const float4 b = ws[i]; return wp::vec4(b.x, b.y, b.z, b.w); }}
    return q;
#else
    static float ws[4 * {PAD}];
    if (op == 1) {{ ws[4 * i] = q[0]; ws[4 * i + 1] = q[1]; ws[4 * i + 2] = q[2]; ws[4 * i + 3] = q[3]; }}
    return wp::vec4(ws[4 * i], ws[4 * i + 1], ws[4 * i + 2], ws[4 * i + 3]);
#endif
"""

    @wp.func_native(ws_src)
    def ws(op: int, i: int, q: wp.vec4) -> wp.vec4:
        """Working-set point i in shared memory: op 1 writes q, op 0 reads."""
        ...

    @wp.func
    def pad(n: int, lane: int):
        """Far points (1e18 m away: clearance 1.7e18 m, contributing nothing) after the set's n
        points, up to the next multiple of 2 BD."""
        for k in range(n + lane, -(-n // (2 * BD)) * (2 * BD), BD):
            ws(1, k, wp.vec4(1.0e18, 1.0e18, 1.0e18, 0.0))

    nl_src = f"""
#if defined(__CUDA_ARCH__)
    __shared__ unsigned short nl[{BD * ((cap + BD - 1) // BD)}];
    if (op == 1) {{
        const unsigned b = __ballot_sync(0xffffffffu, flag);
        if (flag) nl[base + cnt + __popc(b & ((1u << (threadIdx.x & 31)) - 1u))] = (unsigned short)k;
        return cnt + __popc(b);
    }}
    return nl[base + cnt];
#else
    static unsigned short nl[{BD * ((cap + BD - 1) // BD)}];
    if (op == 1) {{
        if (flag) nl[base + cnt] = (unsigned short)k;
        return cnt + (flag != 0 ? 1 : 0);
    }}
    return nl[base + cnt];
#endif
"""

    @wp.func_native(nl_src)
    def near(op: int, base: int, cnt: int, flag: int, k: int) -> int:
        """The warp's near list from ``base`` on: op 1 appends k where flag is set (every thread of
        the warp calls it together, ``cnt`` the list's length so far; returns the new length),
        op 0 reads entry ``cnt``."""
        ...

    # passes over the working set in shared memory
    @wp.func
    def ws_eval_list(X: wp.vec3, a: ProxyArgs, n: int, lane: int, wbase: int):
        """Normal sum and smallest clearance of this thread's points (every BD-th), and the warp's
        list of the points with clearance below rclip (its length)."""
        ns = wp.vec3(0.0)
        me = float(wp.inf)
        cnt = int(0)
        for k0 in range(0, n, BD):   # the same trip count in every thread of a warp
            k = k0 + lane
            e = float(wp.inf)
            if k < n:
                ns, me, e = eval_point_e(X, ws(0, k, wp.vec4(0.0)), a, ns, me)
            fl = int(0)
            if e < a.rclip:
                fl = 1
            cnt = near(1, wbase, cnt, fl, k)
        return ns, me, cnt

    @wp.func
    def ws_clip_list(X: wp.vec3, u: wp.vec3, a: ProxyArgs, off: float, cnt: int, lane: int, wbase: int) -> float:
        """This thread's share of the step limit, over the warp's near list (the other points
        cannot shorten any step: kernels/warp/steps.py)."""
        tm = float(wp.inf)
        for i in range(lane % WL, cnt, WL):
            tm = clip_point(X, u, ws(0, near(0, wbase, i, 0, 0), wp.vec4(0.0)), a, off, tm)
        return tm

    @wp.func
    def ws_eval_mask(X: wp.vec3, a: ProxyArgs, n: int, lane: int, wbase: int):
        """Normal sum and smallest clearance of this thread's points (lane, lane + BD, ...:
        summed in that order), and the bit mask of its points with clearance below rclip (bit j:
        point lane + j BD). Two points an iteration, the second's load and square root in flight
        with the first's; no collective in the loop."""
        ns = wp.vec3(0.0)
        me = float(wp.inf)
        m = int(0)
        j = int(0)
        for k0 in range(lane, n, 2 * BD):   # (k0 + BD: a point of the set or of its padding)
            q0 = ws(0, k0, wp.vec4(0.0))
            q1 = ws(0, k0 + BD, wp.vec4(0.0))
            ns, me, e0 = eval_point_e(X, q0, a, ns, me)
            ns, me, e1 = eval_point_e(X, q1, a, ns, me)
            m = m | (wp.where(e0 < a.rclip, 1, 0) << j) | (wp.where(e1 < a.rclip, 2, 0) << j)
            j += 2
        return ns, me, m

    @wp.func
    def ws_clip_mask(X: wp.vec3, u: wp.vec3, a: ProxyArgs, off: float, m: int, lane: int, wbase: int) -> float:
        """This thread's share of the step limit, over its points in the mask (the other points
        cannot shorten any step: kernels/warp/steps.py)."""
        tm = float(wp.inf)
        while m != 0:   # two points at a time (the second is the first again where one is left)
            j0 = lowest_bit(m)
            m = m & (m - 1)
            j1 = j0
            if m != 0:
                j1 = lowest_bit(m)
                m = m & (m - 1)
            q0 = ws(0, lane + j0 * BD, wp.vec4(0.0))
            q1 = ws(0, lane + j1 * BD, wp.vec4(0.0))
            tm = clip_point(X, u, q1, a, off, clip_point(X, u, q0, a, off, tm))
        return tm

    ws_eval, ws_clip = (ws_eval_mask, ws_clip_mask) if MASK else (ws_eval_list, ws_clip_list)

    @wp.func
    def ws_away(X: wp.vec3, a: ProxyArgs, off: float, n: int, lane: int, bd: int) -> wp.vec3:
        av = wp.vec3(0.0)
        for k in range(lane, n, bd):
            av = away_point(X, ws(0, k, wp.vec4(0.0)), a, off, av)
        return av

    @wp.func
    def count_pass(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float,
                   order: wp.array(dtype=int), a: ProxyArgs, X0: wp.vec3, r2: float, total: int, lane: int,
                   bd: int):
        """Count this thread's candidates (every bd-th of the row table's) that belong to the
        working set; (count, bit j set where the thread's j-th candidate does, j < 64). Two
        candidates an iteration, so that two loads are in flight."""
        cnt = int(0)
        mask = wp.uint64(0)
        j = int(0)
        r = int(0)
        rs = int(0)
        ab = rows(0, 0, 0, 0)
        k = lane
        while k < total:
            r, rs, ab = next_row(k, r, rs, ab)
            k0, q0 = in_set(spts, svel, dt, order, a, ab[0] + k - rs, X0, r2)
            i1 = int(-1)
            if k + bd < total:
                r, rs, ab = next_row(k + bd, r, rs, ab)
                i1 = ab[0] + k + bd - rs
            k1, q1 = in_set(spts, svel, dt, order, a, i1, X0, r2)
            if k0 != 0 and j < 64:
                mask = mask | (wp.uint64(1) << wp.uint64(j))
            if k1 != 0 and j + 1 < 64:
                mask = mask | (wp.uint64(1) << wp.uint64(j + 1))
            cnt += k0 + k1
            k += 2 * bd
            j += 2
        return cnt, mask

    @wp.func
    def write_pass(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float,
                   order: wp.array(dtype=int), a: ProxyArgs, X0: wp.vec3, r2: float, total: int, lane: int,
                   bd: int, mask: wp.uint64, at: int):
        """Write this thread's working-set points from index ``at`` on, in candidate order: the
        first 64 candidates by ``count_pass``'s mask (only those in the set are loaded again),
        any further ones tested again."""
        j = int(0)
        r = int(0)
        rs = int(0)
        ab = rows(0, 0, 0, 0)
        k = lane
        while k < total:
            if j < 64:
                if ((mask >> wp.uint64(j)) & wp.uint64(1)) != wp.uint64(0):
                    r, rs, ab = next_row(k, r, rs, ab)
                    ws(1, at, point_at(spts, svel, ab[0] + k - rs, dt))
                    at += 1
            else:
                r, rs, ab = next_row(k, r, rs, ab)
                k0, q0 = in_set(spts, svel, dt, order, a, ab[0] + k - rs, X0, r2)
                if k0 != 0:
                    ws(1, at, q0)
                    at += 1
            k += bd
            j += 1

    @wp.func  # (one call site, kernels/warp/steps.py's run_steps: inlined there)
    def gather(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
               start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X0: wp.vec3, grad: float, lane: int,
               bd: int, par: int):
        """Gather the working set around X0 into shared memory, from the cells that the box of
        radius ``grad`` around X0 touches; return (its size, or -1 where it does not fit and the
        steps scan the hash instead; the next reduction's ``par``; the skin it was gathered with:
        ``a.skin``, or ``a.skin_min`` where the larger set does not fit)."""
        lo = cell_of(X0 - wp.vec3(grad), g)
        hi = cell_of(X0 + wp.vec3(grad), g)
        x0 = wp.max(lo[0], 0)
        x1 = wp.min(hi[0], g.nx - 1)
        y0 = wp.max(lo[1], 0)
        z0 = wp.max(lo[2], 0)
        nyr = wp.max(wp.min(hi[1], g.ny - 1) - y0 + 1, 0)
        nzr = wp.max(wp.min(hi[2], g.nz - 1) - z0 + 1, 0)
        nrows = int(0)
        if x0 <= x1:
            nrows = nyr * nzr
        if nrows > ROWS_CAP:
            return -1, par, a.skin
        for r in range(lane, nrows, bd):
            base = ((z0 + r // nyr) * g.ny + y0 + r % nyr) * g.nx
            rows(1, r, start[base + x0], start[base + x1 + 1])
        block_sync()
        total = int(0)
        for r in range(nrows):
            ab = rows(0, r, 0, 0)
            total += ab[1] - ab[0]
        r2 = a.gather_r * a.gather_r
        skin = a.skin
        # pass 1: how many of this thread's candidates (every bd-th) belong to the set
        cnt, mask = count_pass(spts, svel, dt, order, a, X0, r2, total, lane, bd)
        sc = block_scan(cnt, par, bd)
        par = 1 - par
        if sc[1] > cap and a.skin_min < a.skin:   # too many points: the smaller skin
            r2 = a.gather_r_min * a.gather_r_min
            skin = a.skin_min
            cnt, mask = count_pass(spts, svel, dt, order, a, X0, r2, total, lane, bd)
            sc = block_scan(cnt, par, bd)
            par = 1 - par
        if sc[1] > cap:
            return -1, par, skin
        # pass 2: the same candidates again, each thread writing its points from its offset on
        write_pass(spts, svel, dt, order, a, X0, r2, total, lane, bd, mask, sc[0])
        pad(sc[1], lane)
        block_sync()
        return sc[1], par, skin

    return WorkingSet(ws, ws_eval, ws_clip, ws_away, gather, pad, WL, NJ)
