"""The fixed-radius neighbour query on Warp: one thread block a query, its cells spread over
the block's threads.

A query scans the cells within ``span`` of its cell in the reference's order (rows (z, y) in
turn, each row's cells x0..x1 one contiguous range of the sorted points, so scan order is
ascending sorted index; kernels/reference/neighbors.py). Each row's range is split into one
contiguous piece per warp; a warp tests 32 consecutive candidates at a time and ranks its hits
with a ballot, so the hits keep scan order without a barrier. A row costs one barrier: the
exclusive scan of the warps' hit counts, which gives each warp where its hits go in the
result row (only while fewer than K have been written: the write pass tests the candidates
again, from L1). Count and nearest need no order: each thread keeps its own (squared
distance, index) minimum, reduced over the block once at the end, ties going to the smaller
index as in the reference's ``argmin``. Squared distances are rounded as the reference rounds
them (no fused multiply-adds), so the hits, the nearest and its distance are the reference's bit
for bit. Points are read from ``sorted_pts`` (coalesced, the
same floats as ``pts[order[i]]``); ``order`` is read only for ``protected_only``.

The block size is a constant of the generated code (``neighbor_kernel(bd)``); Warp's CPU
device runs one thread a block, where every collective is the identity.
"""
from __future__ import annotations

import warp as wp

from .frames import GridArgs
from .primitives import bits_float, float_bits

_KERNELS: dict = {}


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    const unsigned b = __ballot_sync(0xffffffffu, flag);
    return wp::vec2i(__popc(b & ((1u << (threadIdx.x & 31)) - 1u)), __popc(b));
#else
    return wp::vec2i(0, flag != 0 ? 1 : 0);
#endif
""")
def warp_rank(flag: int) -> wp.vec2i:
    """(hits among the lanes before this one, hits of the warp) for this lane's ``flag``; every
    lane of the warp calls it together."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __shared__ int wsc[2][32];
    const int w = threadIdx.x >> 5;
    if ((threadIdx.x & 31) == 0) wsc[par][w] = cnt;
    __syncthreads();
    int before = 0, total = 0;
    for (int k = 0; k < (bd >> 5); ++k) {
        const int s = wsc[par][k];
        if (k < w) before += s;
        total += s;
    }
    return wp::vec2i(before, total);
#else
    return wp::vec2i(0, cnt);
#endif
""")
def warps_scan(cnt: int, par: int, bd: int) -> wp.vec2i:
    """(hits of the warps before this thread's, hits of the block) from each warp's ``cnt`` (the
    same in every lane of a warp); ``par`` alternates between calls (one barrier a call)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __shared__ int amin[32][2];
    int k0 = key[0], k1 = key[1];
    for (int m = 16; m >= 1; m >>= 1) {
        const int y0 = __shfl_xor_sync(0xffffffffu, k0, m);
        const int y1 = __shfl_xor_sync(0xffffffffu, k1, m);
        if (y0 < k0 || (y0 == k0 && y1 < k1)) { k0 = y0; k1 = y1; }
    }
    const int t = threadIdx.x;
    if ((t & 31) == 0) { amin[t >> 5][0] = k0; amin[t >> 5][1] = k1; }
    __syncthreads();
    int r0 = amin[0][0], r1 = amin[0][1];
    for (int w = 1; w < (bd >> 5); ++w) {
        const int y0 = amin[w][0], y1 = amin[w][1];
        if (y0 < r0 || (y0 == r0 && y1 < r1)) { r0 = y0; r1 = y1; }
    }
    return wp::vec2i(r0, r1);
#else
    return key;
#endif
""")
def block_argmin(key: wp.vec2i, bd: int) -> wp.vec2i:
    """The block's smallest (squared distance bits, index) pair, lexicographically (distance
    bits of non-negative floats order as the floats do); the same in every thread."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return __fadd_rn(__fadd_rn(__fmul_rn(dx, dx), __fmul_rn(dy, dy)), __fmul_rn(dz, dz));
#else
    return dx * dx + dy * dy + dz * dz;
#endif
""")
def dist2(dx: float, dy: float, dz: float) -> float:
    """dx^2 + dy^2 + dz^2 rounded after every operation, in the reference's order (CUDA would
    otherwise fuse the products into the sums, and a point within rounding of the radius could
    go the other way)."""
    ...


@wp.func
def is_hit(spts: wp.array(dtype=wp.vec4), order: wp.array(dtype=int), i: int, q: wp.vec3, r2: float,
           protected_only: int):
    """(whether sorted point i is a neighbour of q, its squared distance): within the radius in
    float32, as the reference tests it, and protected where asked."""
    hit = int(0)
    d2 = float(0.0)
    if protected_only == 0 or order[i] < 0:
        p = spts[i]
        dx = p[0] - q[0]
        dy = p[1] - q[1]
        dz = p[2] - q[2]
        d2 = dist2(dx, dy, dz)
        if d2 <= r2:
            hit = 1
    return hit, d2


def neighbor_kernel(bd: int):
    """The query kernel for blocks of ``bd`` threads (a multiple of 32 on CUDA, 1 on the CPU
    device), made on first use."""
    k = _KERNELS.get(bd)
    if k is None:
        k = _KERNELS[bd] = _make_kernel(bd)
    return k


def _make_kernel(bd: int):
    BD = bd
    WL = 32 if BD >= 32 else 1   # lanes a warp
    NW = BD // WL                # warps a block
    # a register cap that lets a block of BD threads run (65,536 registers an SM)
    opts = {"cuda_max_registers": (65536 // BD) & ~7} if BD > 256 else {}

    @wp.kernel(enable_backward=False, module="unique", **opts)
    def neighbor_query(spts: wp.array(dtype=wp.vec4), order: wp.array(dtype=int), start: wp.array(dtype=int),
                       g: GridArgs, queries: wp.array(dtype=wp.vec3), radius: float, span: int, K: int,
                       protected_only: int, res: wp.array(dtype=int)):
        """Query b of B (one block) into ``res``: ``res[b]`` the count, ``res[B + b]`` the nearest
        hit (-1 if none), ``res[2 B + b]`` the bits of its distance (m, float32; inf if none),
        and the first min(count, K) hits in scan order from ``res[3 B + b K]`` on; the rest of
        the row is not written (the host pads it: ``WarpPipeline._neighbors``)."""
        b, lane = wp.tid()
        B = queries.shape[0]
        row = 3 * B + b * K
        w = lane // WL
        l = lane % WL
        q = queries[b]
        cx = int(wp.clamp(wp.floor((q[0] - g.origin[0]) * g.inv_h), float(-span - 1), float(g.nx + span)))
        cy = int(wp.clamp(wp.floor((q[1] - g.origin[1]) * g.inv_h), float(-span - 1), float(g.ny + span)))
        cz = int(wp.clamp(wp.floor((q[2] - g.origin[2]) * g.inv_h), float(-span - 1), float(g.nz + span)))
        x0 = wp.max(cx - span, 0)
        x1 = wp.min(cx + span, g.nx - 1)
        y0 = wp.max(cy - span, 0)
        y1 = wp.min(cy + span, g.ny - 1)
        z0 = wp.max(cz - span, 0)
        z1 = wp.min(cz + span, g.nz - 1)
        r2 = radius * radius
        n = int(0)          # hits so far (block-wide, the same in every thread)
        best = wp.vec2i(float_bits(3.0e38), 2147483647)
        par = int(0)
        if x0 <= x1:
            for iz in range(z0, z1 + 1):
                for iy in range(y0, y1 + 1):
                    base = (iz * g.ny + iy) * g.nx
                    a = start[base + x0]
                    e = start[base + x1 + 1]
                    # this warp's piece of the row: [s, f)
                    per = (e - a + NW - 1) // NW
                    s = wp.min(a + w * per, e)
                    f = wp.min(s + per, e)
                    cnt = int(0)
                    for k0 in range(s, f, WL):   # the same trip count in every lane of a warp
                        i = k0 + l
                        hit = int(0)
                        d2 = float(0.0)
                        if i < f:
                            hit, d2 = is_hit(spts, order, i, q, r2, protected_only)
                        if hit != 0:
                            key = wp.vec2i(float_bits(d2), i)
                            if key[0] < best[0] or (key[0] == best[0] and key[1] < best[1]):
                                best = key
                        cnt += warp_rank(hit)[1]
                    sc = warps_scan(cnt, par, BD)
                    par = 1 - par
                    at = n + sc[0]
                    if cnt > 0 and at < K:   # write pass: this warp's hits in scan order
                        for k0 in range(s, f, WL):
                            i = k0 + l
                            hit = int(0)
                            d2 = float(0.0)
                            if i < f:
                                hit, d2 = is_hit(spts, order, i, q, r2, protected_only)
                            rk = warp_rank(hit)
                            if hit != 0 and at + rk[0] < K:
                                res[row + at + rk[0]] = i
                            at += rk[1]
                    n += sc[1]
        best = block_argmin(best, BD)
        if lane == 0:
            res[b] = n
            if n > 0:
                res[B + b] = best[1]
                res[2 * B + b] = float_bits(wp.sqrt(bits_float(best[0])))
            else:
                res[B + b] = -1
                res[2 * B + b] = float_bits(float(wp.inf))

    return neighbor_query
