"""Block-wide and bit-level device primitives of the Warp proxy kernels (native CUDA code).

On CUDA a proxy is spread over the threads of one block; these are the block's collective
operations (barrier, reductions, scan: warp shuffles, then one barrier over the warps' partial
results, every thread reading the same partials in the same order), small shared arrays, and
fast math. Warp's CPU device runs one thread a block: there each collective is the identity and
the shared arrays are static ones.

Square roots, reciprocals and divisions use the hardware's approximations (within 2 ulp, no
branch), not IEEE-rounded sequences whose slow-path branches split the step into basic blocks
that cannot overlap: 2.6 -> 2.1 us a step on an H100. A 2-ulp error in a distance of 10 mm is
2 nm, far inside the clip's 1 um margin (kernels/warp/points.py).
"""
from __future__ import annotations

import warp as wp

#: hash rows (z, y) one gather may list: a gather reaching further scans the hash directly
ROWS_CAP = wp.constant(128)


# --- block-wide primitives (native; Warp's CPU device runs one thread per block) -------------

@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __syncthreads();
#endif
""")
def block_sync(): ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __shared__ float red[2][32][4];
    float x0 = v[0], x1 = v[1], x2 = v[2], x3 = v[3];
    for (int m = 16; m >= 1; m >>= 1) {
        const float y0 = __shfl_xor_sync(0xffffffffu, x0, m);
        const float y1 = __shfl_xor_sync(0xffffffffu, x1, m);
        const float y2 = __shfl_xor_sync(0xffffffffu, x2, m);
        const float y3 = __shfl_xor_sync(0xffffffffu, x3, m);
        x0 = (mins & 1) ? (y0 < x0 ? y0 : x0) : x0 + y0;
        x1 = (mins & 2) ? (y1 < x1 ? y1 : x1) : x1 + y1;
        x2 = (mins & 4) ? (y2 < x2 ? y2 : x2) : x2 + y2;
        x3 = (mins & 8) ? (y3 < x3 ? y3 : x3) : x3 + y3;
    }
    const int t = threadIdx.x;
    if ((t & 31) == 0) {
        red[par][t >> 5][0] = x0; red[par][t >> 5][1] = x1; red[par][t >> 5][2] = x2; red[par][t >> 5][3] = x3;
    }
    __syncthreads();
    float r0 = red[par][0][0], r1 = red[par][0][1], r2 = red[par][0][2], r3 = red[par][0][3];
    for (int w = 1; w < (bd >> 5); ++w) {
        const float y0 = red[par][w][0], y1 = red[par][w][1], y2 = red[par][w][2], y3 = red[par][w][3];
        r0 = (mins & 1) ? (y0 < r0 ? y0 : r0) : r0 + y0;
        r1 = (mins & 2) ? (y1 < r1 ? y1 : r1) : r1 + y1;
        r2 = (mins & 4) ? (y2 < r2 ? y2 : r2) : r2 + y2;
        r3 = (mins & 8) ? (y3 < r3 ? y3 : r3) : r3 + y3;
    }
    return wp::vec4(r0, r1, r2, r3);
#else
    return v;
#endif
""")
def block_reduce4(v: wp.vec4, mins: int, par: int, bd: int) -> wp.vec4:
    """Block-wide reduction of v, per component a sum or (bit c of ``mins``) a minimum; every
    thread gets the same bits. ``par`` alternates between calls (double-buffered partials, so
    one barrier a call suffices)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __shared__ float redm[2][32];
    float x = v;
    for (int m = 16; m >= 1; m >>= 1) {
        const float y = __shfl_xor_sync(0xffffffffu, x, m);
        x = y < x ? y : x;
    }
    const int t = threadIdx.x;
    if ((t & 31) == 0) redm[par][t >> 5] = x;
    __syncthreads();
    float r = redm[par][0];
    for (int w = 1; w < (bd >> 5); ++w) {
        const float y = redm[par][w];
        r = y < r ? y : r;
    }
    return r;
#else
    return v;
#endif
""")
def block_min(v: float, par: int, bd: int) -> float:
    """Block-wide minimum (same for every thread); ``par`` as for ``block_reduce4``."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __shared__ int scn[2][32];
    const int t = threadIdx.x, l = t & 31, w = t >> 5;
    int x = v;
    for (int d = 1; d < 32; d <<= 1) {
        const int y = __shfl_up_sync(0xffffffffu, x, d);
        if (l >= d) x += y;
    }
    if (l == 31) scn[par][w] = x;
    __syncthreads();
    int before = 0, total = 0;
    for (int k = 0; k < (bd >> 5); ++k) {
        const int s = scn[par][k];
        if (k < w) before += s;
        total += s;
    }
    return wp::vec2i(before + x - v, total);
#else
    return wp::vec2i(0, v);
#endif
""")
def block_scan(v: int, par: int, bd: int) -> wp.vec2i:
    """(exclusive prefix of v over the block's threads in thread order, block total)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __shared__ float4 bc[4];
    if (op == 1) bc[k] = make_float4(v[0], v[1], v[2], v[3]);
    else { const float4 b = bc[k]; return wp::vec4(b.x, b.y, b.z, b.w); }
    return v;
#else
    static float bc[16];   // (a plain array: no static initialiser to run)
    if (op == 1) { bc[4 * k] = v[0]; bc[4 * k + 1] = v[1]; bc[4 * k + 2] = v[2]; bc[4 * k + 3] = v[3]; }
    return wp::vec4(bc[4 * k], bc[4 * k + 1], bc[4 * k + 2], bc[4 * k + 3]);
#endif
""")
def shared4(op: int, k: int, v: wp.vec4) -> wp.vec4:
    """Slot k of a small shared array: op 1 writes v, op 0 reads."""
    ...


@wp.func_native(f"""
#if defined(__CUDA_ARCH__)
    __shared__ int rt[2 * {ROWS_CAP}];
#else
    static int rt[2 * {ROWS_CAP}];
#endif
    if (op == 1) {{ rt[2 * r] = a; rt[2 * r + 1] = b; }}
    return wp::vec2i(rt[2 * r], rt[2 * r + 1]);
""")
def rows(op: int, r: int, a: int, b: int) -> wp.vec2i:
    """Row r of a gather's row table (first and end index into the sorted points): op 1 writes."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __shared__ int bci[12];
    if (op == 1) { bci[4 * k] = v[0]; bci[4 * k + 1] = v[1]; bci[4 * k + 2] = v[2]; bci[4 * k + 3] = v[3]; }
    return wp::vec4i(bci[4 * k], bci[4 * k + 1], bci[4 * k + 2], bci[4 * k + 3]);
#else
    static int bci[12];
    if (op == 1) { bci[4 * k] = v[0]; bci[4 * k + 1] = v[1]; bci[4 * k + 2] = v[2]; bci[4 * k + 3] = v[3]; }
    return wp::vec4i(bci[4 * k], bci[4 * k + 1], bci[4 * k + 2], bci[4 * k + 3]);
#endif
""")
def sharedi4(op: int, k: int, v: wp.vec4i) -> wp.vec4i:
    """Slot k (0 to 2) of a small shared integer array: op 1 writes v, op 0 reads."""
    ...



@wp.func_native("""
    union { float f; int i; } u;
    u.f = f;
    return u.i;
""")
def float_bits(f: float) -> int:
    """The bits of f."""
    ...


@wp.func_native("""
    union { float f; int i; } u;
    u.i = i;
    return u.f;
""")
def bits_float(i: int) -> float:
    """The float with bits i."""
    ...



@wp.func_native("""
#if defined(__CUDA_ARCH__)
    float r;
    asm("rsqrt.approx.ftz.f32 %0, %1;" : "=f"(r) : "f"(fmaxf(x, 1.17549435e-38f)));
    return r;
#else
    return 1.0f / sqrtf(x);
#endif
""")
def rsqrt_fast(x: float) -> float:
    """1 / sqrt(x) for x >= 2^-126 without a branch (CUDA's MUFU.RSQ: within 2 ulp; the bits of
    rsqrtf there, without its scaling of subnormal x); finite for x below (the callers take it
    only where x > 0, and a squared length of 0 < x < 2^-126 m^2 is a distance below 1e-19 m)."""
    ...




@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return __fmul_rn(a, b);
#else
    return a * b;
#endif
""")
def mul_rn(a: float, b: float) -> float:
    """a b rounded on its own: never fused into an add that follows it (the compiler's choice
    would depend on the code around it, and the result's last bit with it)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return __fdividef(a, b);
#else
    return a / b;
#endif
""")
def div_fast(a: float, b: float) -> float:
    """a / b without a branch (within 2 ulp for |b| below 2^126)."""
    ...

