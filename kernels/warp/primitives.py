"""Block-wide and bit-level device primitives of the Warp proxy kernels (native CUDA code).

On CUDA a proxy is spread over the threads of one block; these are the block's collective
operations (barrier, reductions, scan: within each warp shuffles, or one REDUX instruction for
a minimum; then one barrier over the warps' partial results, every thread reading the same
partials in the same order), small shared arrays, and fast math. Warp's CPU device runs one
thread a block: there each collective is the identity and the shared arrays are static ones.

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


# A minimum over the block is taken on integer keys that order like the floats (a float's bits,
# the negative ones' other bits flipped; x + 0 makes -0 into +0): one warp instruction
# (__reduce_min_sync, REDUX on sm_80 and later) instead of five dependent shuffles, and the same
# value as a float minimum (neither NaN nor -0 reaches one). Sums keep the shuffle tree and the
# warps' partials in warp order, so they are the same bits as before.
_MIN_KEY = """
    auto min_key = [](float x) -> int {
        const int i = __float_as_int(x + 0.0f);
        return i >= 0 ? i : i ^ 0x7fffffff;
    };
    auto key_float = [](int k) -> float { return __int_as_float(k >= 0 ? k : k ^ 0x7fffffff); };
    auto warp_min = [](int k) -> int {
#if __CUDA_ARCH__ >= 800
        return __reduce_min_sync(0xffffffffu, k);
#else
        for (int m = 16; m >= 1; m >>= 1) { const int y = __shfl_xor_sync(0xffffffffu, k, m); k = y < k ? y : k; }
        return k;
#endif
    };
"""


@wp.func_native("""
#if defined(__CUDA_ARCH__)
""" + _MIN_KEY + """
    __shared__ float red[2][32][4];
    float x[4] = {v[0], v[1], v[2], v[3]};
    for (int c = 0; c < 4; ++c)
        if ((mins >> c) & 1) x[c] = __int_as_float(warp_min(min_key(x[c])));
    for (int m = 16; m >= 1; m >>= 1)
        for (int c = 0; c < 4; ++c)
            if (!((mins >> c) & 1)) x[c] += __shfl_xor_sync(0xffffffffu, x[c], m);
    const int t = threadIdx.x;
    if ((t & 31) == 0) {
        red[par][t >> 5][0] = x[0]; red[par][t >> 5][1] = x[1]; red[par][t >> 5][2] = x[2]; red[par][t >> 5][3] = x[3];
    }
    __syncthreads();
    float r[4] = {red[par][0][0], red[par][0][1], red[par][0][2], red[par][0][3]};
    for (int w = 1; w < (bd >> 5); ++w)
        for (int c = 0; c < 4; ++c) {
            const float y = red[par][w][c];
            if ((mins >> c) & 1) r[c] = __int_as_float(min(__float_as_int(y), __float_as_int(r[c])));
            else r[c] += y;
        }
    for (int c = 0; c < 4; ++c)
        if ((mins >> c) & 1) r[c] = key_float(__float_as_int(r[c]));
    return wp::vec4(r[0], r[1], r[2], r[3]);
#else
    return v;
#endif
""")
def block_reduce4(v: wp.vec4, mins: int, par: int, bd: int) -> wp.vec4:
    """Block-wide reduction of v, per component a sum or (bit c of ``mins``) a minimum; every
    thread gets the same bits (the sums: a shuffle tree in each warp, then the warps' partials in
    warp order). ``par`` alternates between calls (double-buffered partials, so one barrier a
    call suffices)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
""" + _MIN_KEY + """
    __shared__ int redm[2][32];
    const int k = warp_min(min_key(v));
    const int t = threadIdx.x;
    if ((t & 31) == 0) redm[par][t >> 5] = k;
    __syncthreads();
    int r = redm[par][0];
    for (int w = 1; w < (bd >> 5); ++w) r = min(r, redm[par][w]);
    return key_float(r);
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

