"""Warp proxy batch: one launch per haptic tick for all proxies, one thread block per proxy.

Same algorithm as kernels/proxy.py (the NumPy reference and kernels/opencl/proxy.cl). On a
GPU a proxy is spread over the ``block_dim`` threads of its block. At the start of a tick the
block gathers its working set, the points within ``reach + skin`` of the proxy, into shared
memory: the cells that the set's bounding box touches are listed once, the block scans their
points with every thread taking every block_dim-th candidate, counts the ones within range, and
an exclusive scan of the counts gives each thread where to write its points, so the working
set's order does not depend on timing. The skin is ``GATHER_SKIN`` (wider than
HapticParams.skin: a gather costs more on a GPU than the points it adds to each step), or
HapticParams.skin for a set that would not fit in the shared buffer (``ws_capacity_for``); a
set that does not fit even then is scanned from the hash in global memory. The steps then read
on-chip memory only; a proxy that wanders further than its skin from where its set was gathered
gathers again (results do not depend on the skin). A launched tick of up to ``WS_CACHE_MAX``
proxies keeps each set in device memory for the next tick, keyed by the snapshot's build, dt,
the search span and where it was gathered, and copies a set that still holds instead of
gathering it (the resident kernel, kernels/warp/resident.py, keeps its sets in shared memory
itself). The normal sum, the smallest clearance and
the swept-sphere step limit are block-wide reductions (warp shuffles, then one barrier over the
warps' partial results; every thread reads the same partials in the same order). Every thread
then takes the same decision from the reduced values, so the step loop stays uniform across the
block. The evaluation also lists, per warp, the points close enough to shorten a step (clearance
below ``ProxyArgs.rclip``); the clip passes scan only those (the same step lengths, see the
kernel), and the kernel has one clip pass in its code for the up to three tries of a step. The
block size is a constant of each kernel's code.

Square roots, reciprocals and the clip's division use the hardware's approximations (within
2 ulp, no branch), not IEEE-rounded sequences whose slow-path branches split the step into
basic blocks that cannot overlap: 2.6 -> 2.1 us a step on an H100. A 2-ulp error in a distance
of 10 mm is 2 nm, far inside the clip's 1 um ``margin``, so no step ends closer to a point than
the reference allows; the results agree with the reference within its tests' tolerances.

On CUDA the tick is captured once per snapshot slot into a CUDA graph and replayed each tick.
For batches up to ``ZERO_COPY_MAX`` the graph is the kernel alone: it reads the HIPs, the
positions and the tick's arguments from pinned host memory and writes the results straight
into the batch's (pinned) host arrays, so a tick has no copy nodes and nothing to unpack. Larger
batches upload the HIPs and download the results with copies inside the graph. Nothing is
allocated per tick.
"""
from __future__ import annotations

import os

import numpy as np
import warp as wp

from ..errors import KernelError
from ..motion import extra_span
from ..neighbors import search_span
from ..proxy import ProxyBatch
from .frames import GridArgs

#: threads per proxy on CUDA (one block each) by batch size: (largest batch, threads). A small
#: batch spreads each proxy over many threads (latency); a large one over fewer, so that more
#: blocks run at once (throughput). H100 sweep, apc frame 49 (bench/RESULTS.md).
BLOCK_DIMS = ((64, 256), (4096, 128), (1 << 62, 32))
#: one size for every batch instead (POINTFENCE_WARP_BLOCK_DIM); Warp's CPU device runs one
#: thread per block
BLOCK_DIM = int(os.environ["POINTFENCE_WARP_BLOCK_DIM"]) if os.environ.get("POINTFENCE_WARP_BLOCK_DIM") else None
#: register cap of the tick kernel (POINTFENCE_WARP_MAXREG; 0: the largest that lets a block of
#: the launch's size run, 65,536 registers an SM, the compiler's choice up to 255)
MAXREG = int(os.environ.get("POINTFENCE_WARP_MAXREG", "0"))
#: points of a proxy's working set held in shared memory, by batch size: (largest batch,
#: points). 16 bytes a point; a small batch has an SM per proxy and takes what static shared
#: memory allows (48 KB a block), a large one leaves room for more blocks per SM. A proxy with
#: more points within reach + skin scans the hash from global memory instead.
WS_CAPS = ((64, 2496), (4096, 1536), (1 << 62, 768))
#: largest batch whose tick reads and writes pinned host memory directly (no copies in the graph;
#: POINTFENCE_WARP_ZERO_COPY_MAX)
ZERO_COPY_MAX = int(os.environ.get("POINTFENCE_WARP_ZERO_COPY_MAX", "4096"))
#: working-set skin on the GPU (m): a proxy gathers the points within reach + this (at least
#: HapticParams.skin) and gathers again when it has moved further; a set that does not fit in
#: shared memory is gathered with HapticParams.skin instead (results do not depend on the skin).
#: H100, bench query, HapticParams.skin 0.5 mm (bench/RESULTS.md, 2026-11-24, later): 1.5 mm.
GATHER_SKIN = float(os.environ.get("POINTFENCE_WARP_SKIN", "1.5e-3"))
#: largest batch whose launched tick keeps each proxy's working set in device memory from tick
#: to tick (16 bytes a point, ``ws_capacity_for(n)`` points a proxy: 25 MB for 1,024 proxies),
#: gathering again only where a set no longer holds (POINTFENCE_WARP_WS_CACHE_MAX; 0: never)
WS_CACHE_MAX = int(os.environ.get("POINTFENCE_WARP_WS_CACHE_MAX", "4096"))
#: hash rows (z, y) one gather may list: a gather reaching further scans the hash directly
ROWS_CAP = wp.constant(128)


def resident_max() -> int:
    """Largest batch that runs on the resident kernel (kernels/warp/resident.RESIDENT_MAX; 0 on a
    host without x86's store order, ``resident.HOST_STORE_ORDER``)."""
    return _resident_mod.RESIDENT_MAX if _resident_mod.HOST_STORE_ORDER else 0


def block_dim_for(n: int) -> int:
    """Threads per proxy for a batch of ``n`` proxies on CUDA."""
    if BLOCK_DIM:
        return BLOCK_DIM
    return next(bd for most, bd in BLOCK_DIMS if n <= most)


def maxreg_for(bd: int) -> int:
    """Register cap for blocks of ``bd`` threads (0: none): the kernel needs about 220 registers
    a thread, more than a block of 512 or 1,024 threads can have."""
    if MAXREG:
        return MAXREG
    return 0 if bd <= 256 else (65536 // bd) & ~7


def ws_capacity_for(n: int) -> int:
    """Working-set points in shared memory per proxy for a batch of ``n`` proxies."""
    return next(c for most, c in WS_CAPS if n <= most)


@wp.struct
class ProxyArgs:
    r1: float
    band: float  # r2 - r1
    nreach: float  # r3 - r1
    step: float
    tol: float
    slack: float
    margin: float
    turn_back: float  # turn_back_cos
    skin: float  # regather when the proxy is further than this from where its set was gathered
    gather_r: float  # reach + skin: the working set's radius
    skin_min: float  # the same for a set that does not fit with ``skin`` (HapticParams.skin)
    gather_r_min: float
    rclip: float  # no step can be shortened by a point with clearance >= rclip (see the kernel)
    fixture: int
    max_steps: int
    span: int  # cells searched on each side (reach, without motion)


@wp.struct
class TickArgs:
    """Per-tick values, read by the kernel from pinned host memory (or copied in the graph)."""

    dt: float  # prediction time: points are taken at p + v dt (kernels/motion.py)
    span: int  # cells searched on each side: reach plus the motion's extra reach
    grad: float  # a gather's reach in the hash: reach + skin plus the motion's extra reach
    build: int  # the snapshot's build number (slot.seq): the working-set cache's key


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


# --- the resident kernel's mailbox and inbox (kernels/warp/resident.py) ---------------------

#: words of the mailbox, an int32 array in pinned host memory: the host sets STOP to make the
#: kernel leave; the kernel writes DONE (the number of the tick it finished last) and ALIVE (0
#: once it has left). The native code reads STOP and writes DONE as words 0 and 1.
MB_STOP, MB_DONE, MB_ALIVE = (wp.constant(i) for i in range(3))
MB_WORDS = 16
#: the inbox, pinned host memory in 16-byte chunks of (tag, three words): chunk 0 (tag, snapshot
#: build, dt bits, search span), chunk 1 (tag, gather radius bits, 0, 0), then one chunk
#: (tag, HIP x, y, z) a proxy. The host writes a tick's words, then the tick's number into every
#: tag; the kernel reads every chunk at once, one 16-byte load each, and takes the tick when all
#: tags carry the same new number (a chunk is read whole, and x86 makes a tag visible only after
#: the words written before it): one round trip over the bus, no fence.
IN_HEAD = wp.constant(2)
#: most proxies of a resident kernel (the inbox's chunks: two a lane of one warp)
RESIDENT_CAP = 62


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __shared__ int tin[12];   // chunks 0 .. 2 of the tick block 0 took: the header, proxy 0's HIP
    if (op == 0) return wp::vec4i(tin[4 * i], tin[4 * i + 1], tin[4 * i + 2], tin[4 * i + 3]);
    // op 1, warp 0 of block 0: poll every chunk (one 16-byte load each, all in flight together)
    // and the mailbox's STOP word until every tag carries the same number, other than ``last``
    const int* ib = (const int*)inbox.data;
    const volatile int* m = (const volatile int*)mb.data;
    const int nch = n + 2;   // 2: IN_HEAD
    int a0 = 0, a1 = 0, a2 = 0, a3 = 0, b0 = 0, b1 = 0, b2 = 0, b3 = 0, s;
    unsigned long long t0, t;
    asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(t0));
    for (;;) {
        if (lane < nch)
            asm volatile("ld.volatile.v4.s32 {%0,%1,%2,%3}, [%4];"
                         : "=r"(a0), "=r"(a1), "=r"(a2), "=r"(a3) : "l"(ib + 4 * lane) : "memory");
        if (lane + 32 < nch)
            asm volatile("ld.volatile.v4.s32 {%0,%1,%2,%3}, [%4];"
                         : "=r"(b0), "=r"(b1), "=r"(b2), "=r"(b3) : "l"(ib + 4 * (lane + 32)) : "memory");
        const int stop = __shfl_sync(0xffffffffu, m[0], 0);   // MB_STOP
        const int tag = __shfl_sync(0xffffffffu, a0, 0);
        const bool same = (lane >= nch || a0 == tag) && (lane + 32 >= nch || b0 == tag);
        if (__all_sync(0xffffffffu, same) && tag != last) { s = tag; break; }
        if (stop != 0) { s = -1; break; }
        asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(t));
        if (__shfl_sync(0xffffffffu, (t - t0 > (unsigned long long)idle_ns) ? 1 : 0, 0)) { s = -2; break; }
    }
    if (s > 0) {
        if (lane < 3) { tin[4 * lane] = a0; tin[4 * lane + 1] = a1; tin[4 * lane + 2] = a2; tin[4 * lane + 3] = a3; }
        if (n > 1) {   // every chunk to the other blocks, through device memory
            if (lane < nch) stage.data[lane] = wp::vec4i(a0, a1, a2, a3);
            if (lane + 32 < nch) stage.data[lane + 32] = wp::vec4i(b0, b1, b2, b3);
        }
    } else if (lane == 0) {
        tin[0] = s;
    }
    return wp::vec4i(s, 0, 0, 0);
#else
    return wp::vec4i(-1, 0, 0, 0);
#endif
""")
def tick_in(op: int, i: int, inbox: wp.array(dtype=wp.int32), mb: wp.array(dtype=wp.int32),
            stage: wp.array(dtype=wp.vec4i), n: int, last: int, idle_ns: int, lane: int) -> wp.vec4i:
    """The resident kernel's tick inputs. op 1 (warp 0 of block 0, every lane): wait for the host's
    next tick in the inbox; keep chunks 0 to 2 in shared memory (their tag word 0: the tick's
    number, -1 when asked to stop, -2 after ``idle_ns`` without a tick) and, for ``n`` > 1, put
    every chunk into ``stage`` for the other blocks. op 0: chunk ``i`` (0 to 2) of the tick taken."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    int x, y, z, w;
    asm volatile("ld.volatile.v4.s32 {%0,%1,%2,%3}, [%4];"
                 : "=r"(x), "=r"(y), "=r"(z), "=r"(w) : "l"(stage.data + i) : "memory");
    return wp::vec4i(x, y, z, w);
#else
    return stage.data[i];
#endif
""")
def staged4(stage: wp.array(dtype=wp.vec4i), i: int) -> wp.vec4i:
    """Chunk i of the staged inputs (read past the SM's cache: block 0 wrote it)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __threadfence_system();   // (the host wrote any new positions before the tick's tags)
    const volatile float* x = (const volatile float*)pos.data;
    for (int i = lane; i < n; i += bd)
        stage.data[2 + n + i] = wp::vec4i(0, __float_as_int(x[3 * i]), __float_as_int(x[3 * i + 1]),
                                          __float_as_int(x[3 * i + 2]));   // 2: IN_HEAD; words 1-3, as a HIP's
#endif
""")
def positions_in(pos: wp.array(dtype=wp.vec3), stage: wp.array(dtype=wp.vec4i), n: int, lane: int, bd: int):
    """Block 0 stages every proxy's position from the batch's host array (chunks IN_HEAD + n on,
    words 1 to 3 as an inbox chunk's), the block's threads reading together: for a tick that
    follows another kernel's or a reset."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __threadfence_system();   // this block's results are in host memory before it counts itself done
    if (n > 1) {
        // counts 0 .. n - 1 and wraps to 0 by itself: no reset, and no overflow in a long run
        if (atomicInc((unsigned int*)count.data, (unsigned int)(n - 1)) != (unsigned int)(n - 1)) return;
        __threadfence_system();   // every block's results before DONE
    }
    ((volatile int*)mb.data)[1] = s;   // MB_DONE
#endif
""")
def tick_done(count: wp.array(dtype=wp.int32), mb: wp.array(dtype=wp.int32), n: int, s: int):
    """A block's results are written: the last of the ``n`` blocks tells the host tick ``s`` is done."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    ((volatile int*)mb.data)[i] = v;
#else
    mb.data[i] = v;
#endif
""")
def mailbox_set(mb: wp.array(dtype=wp.int32), i: int, v: int):
    """Write word i of the mailbox (no fence: ALIVE announces nothing but the kernel's leaving)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __threadfence();
    ((volatile int*)cmd.data)[0] = s;
#endif
""")
def command_put(cmd: wp.array(dtype=wp.int32), s: int):
    """Block 0 passes the host's command (a tick's sequence number, or <= 0: leave) to the others."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    volatile int* c = (volatile int*)cmd.data;
    for (;;) {
        const int s = c[0];
        if (s != last) { __threadfence(); return s; }
        __nanosleep(32);
    }
#else
    return -1;
#endif
""")
def command_wait(cmd: wp.array(dtype=wp.int32), last: int) -> int:
    """Wait for block 0's next command (other than ``last``)."""
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


@wp.func
def bits_vec3(c: wp.vec4i) -> wp.vec3:
    """Words 1 to 3 of an inbox chunk as a vector."""
    return wp.vec3(bits_float(c[1]), bits_float(c[2]), bits_float(c[3]))


# --- per-point work, shared by the working-set and the hash paths ---------------------------

@wp.func
def point_at(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), i: int, dt: float) -> wp.vec4:
    """Sorted point i where the tick predicts it: p + v dt (dt = 0: untouched)."""
    q = spts[i]
    if dt > 0.0:
        v = svel[i]
        q = wp.vec4(q[0] + v[0] * dt, q[1] + v[1] * dt, q[2] + v[2] * dt, q[3])
    return q


@wp.func
def clearance_radius(p: wp.vec4, a: ProxyArgs) -> float:
    if a.fixture != 0:
        return p[3]
    return a.r1


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return rsqrtf(x);
#else
    return 1.0f / sqrtf(x);
#endif
""")
def rsqrt_fast(x: float) -> float:
    """1 / sqrt(x) without a branch (CUDA's MUFU.RSQ: within 2 ulp)."""
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


@wp.func
def unit_len(v: wp.vec3):
    """(v / |v|, |v|), zero for v = 0."""
    l2 = wp.dot(v, v)
    inv = rsqrt_fast(l2)
    if l2 > 0.0:
        return v * inv, l2 * inv
    return wp.vec3(0.0), float(0.0)


@wp.func
def eval_point_e(X: wp.vec3, q: wp.vec4, a: ProxyArgs, ns: wp.vec3, me: float):
    """Step 1 for one point: its share of the normal sum and of the smallest clearance, and
    its clearance."""
    dv = wp.vec3(X[0] - q[0], X[1] - q[1], X[2] - q[2])
    d2 = dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]
    inv = rsqrt_fast(d2)
    d = float(0.0)
    if d2 > 0.0:
        d = d2 * inv
    e = d - clearance_radius(q, a)
    if e < a.nreach:
        me = wp.min(me, e)
        if d2 > 0.0:
            ns = ns + dv * inv
    return ns, me, e


@wp.func
def eval_point(X: wp.vec3, q: wp.vec4, a: ProxyArgs, ns: wp.vec3, me: float):
    """Step 1 for one point: its share of the normal sum and of the smallest clearance."""
    ns, me, e = eval_point_e(X, q, a, ns, me)
    return ns, me


@wp.func
def clip_point(X: wp.vec3, u: wp.vec3, q: wp.vec4, a: ProxyArgs, off: float, tm: float) -> float:
    """Step 3 for one point (kernels/proxy.py); off = F + margin: a clear point stops the step
    where its clearance reaches off (swept sphere), a point at the limit (clearance below off)
    may not be approached at all."""
    dx = X[0] - q[0]
    dy = X[1] - q[1]
    dz = X[2] - q[2]
    d2 = dx * dx + dy * dy + dz * dz
    b = u[0] * dx + u[1] * dy + u[2] * dz
    rc = clearance_radius(q, a) + off
    c = d2 - rc * rc
    disc = b * b - c
    if c >= 0.0 and b < 0.0 and disc > 0.0:
        tm = wp.min(tm, div_fast(c, -b + disc * rsqrt_fast(disc)))
    elif c < 0.0 and b < 0.0:
        tm = 0.0
    return tm


@wp.func
def away_point(X: wp.vec3, q: wp.vec4, a: ProxyArgs, off: float, ns: wp.vec3) -> wp.vec3:
    """This point's share of sum (X - P)/|X - P| over the points at the limit (clearance below off)."""
    dv = wp.vec3(X[0] - q[0], X[1] - q[1], X[2] - q[2])
    d2 = dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]
    inv = rsqrt_fast(d2)
    rc = clearance_radius(q, a) + off
    if d2 - rc * rc < 0.0 and d2 > 0.0:
        ns = ns + dv * inv
    return ns


@wp.func
def results_out(p: int, X: wp.vec3, nrm: wp.vec3, min_e: float, st: int, steps: int, conv: int,
                pos: wp.array(dtype=wp.vec3), nrm_out: wp.array(dtype=wp.vec3), near_out: wp.array(dtype=float),
                state_out: wp.array(dtype=wp.int32), steps_out: wp.array(dtype=wp.int32),
                conv_out: wp.array(dtype=wp.bool)):
    """Proxy p's tick results into the batch's arrays (one thread)."""
    pos[p] = X
    nrm_out[p] = nrm
    near_out[p] = min_e
    state_out[p] = st
    steps_out[p] = steps
    conv_out[p] = conv != 0


@wp.func
def set_holds(key: wp.vec4i, X0: wp.vec3, skin: float, build: int, dtb: int, span: int, X: wp.vec3) -> bool:
    """Whether a working set gathered around X0 with ``skin`` for ``key`` (build, dt bits, span)
    still serves a proxy at X in a tick of (build, dtb, span): the conditions under which
    ``run_steps`` keeps a set."""
    dx = X[0] - X0[0]
    dy = X[1] - X0[1]
    dz = X[2] - X0[2]
    return key[0] == build and key[1] == dtb and key[2] == span and dx * dx + dy * dy + dz * dz <= skin * skin


@wp.func
def cell_of(X: wp.vec3, g: GridArgs) -> wp.vec3i:
    """Cell of X, clamped to one cell outside the grid (a cell range's end)."""
    cx = int(wp.clamp(wp.floor((X[0] - g.origin[0]) * g.inv_h), -1.0, float(g.nx)))
    cy = int(wp.clamp(wp.floor((X[1] - g.origin[1]) * g.inv_h), -1.0, float(g.ny)))
    cz = int(wp.clamp(wp.floor((X[2] - g.origin[2]) * g.inv_h), -1.0, float(g.nz)))
    return wp.vec3i(cx, cy, cz)


@wp.func
def cell_box(X: wp.vec3, g: GridArgs, span: int) -> wp.vec3i:
    """Cell of X, clamped to span + 1 cells outside the grid (the reference's clamp)."""
    cx = int(wp.clamp(wp.floor((X[0] - g.origin[0]) * g.inv_h), float(-span - 1), float(g.nx + span)))
    cy = int(wp.clamp(wp.floor((X[1] - g.origin[1]) * g.inv_h), float(-span - 1), float(g.ny + span)))
    cz = int(wp.clamp(wp.floor((X[2] - g.origin[2]) * g.inv_h), float(-span - 1), float(g.nz + span)))
    return wp.vec3i(cx, cy, cz)


# --- the hash path: a thread's share of each pass over the cells within reach ---------------

@wp.func(inline=False)  # cold path: kept out of the step loop's code
def hash_eval(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
              start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3, c: wp.vec3i, span: int,
              lane: int, bd: int):
    ns = wp.vec3(0.0)
    me = float(wp.inf)
    x0 = wp.max(c[0] - span, 0)
    x1 = wp.min(c[0] + span, g.nx - 1)
    if x0 <= x1:
        for iz in range(wp.max(c[2] - span, 0), wp.min(c[2] + span, g.nz - 1) + 1):
            for iy in range(wp.max(c[1] - span, 0), wp.min(c[1] + span, g.ny - 1) + 1):
                base = (iz * g.ny + iy) * g.nx
                for i in range(start[base + x0] + lane, start[base + x1 + 1], bd):
                    if a.fixture != 0 and order[i] >= 0:
                        continue
                    ns, me = eval_point(X, point_at(spts, svel, i, dt), a, ns, me)
    return ns, me


@wp.func(inline=False)  # cold path: kept out of the step loop's code
def hash_clip(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
              start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3, u: wp.vec3, off: float,
              c: wp.vec3i, span: int, lane: int, bd: int) -> float:
    tm = float(wp.inf)
    x0 = wp.max(c[0] - span, 0)
    x1 = wp.min(c[0] + span, g.nx - 1)
    if x0 <= x1:
        for iz in range(wp.max(c[2] - span, 0), wp.min(c[2] + span, g.nz - 1) + 1):
            for iy in range(wp.max(c[1] - span, 0), wp.min(c[1] + span, g.ny - 1) + 1):
                base = (iz * g.ny + iy) * g.nx
                for i in range(start[base + x0] + lane, start[base + x1 + 1], bd):
                    if a.fixture != 0 and order[i] >= 0:
                        continue
                    tm = clip_point(X, u, point_at(spts, svel, i, dt), a, off, tm)
    return tm


@wp.func(inline=False)  # cold path: kept out of the step loop's code
def hash_away(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
              start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3, off: float, c: wp.vec3i,
              span: int, lane: int, bd: int) -> wp.vec3:
    ns = wp.vec3(0.0)
    x0 = wp.max(c[0] - span, 0)
    x1 = wp.min(c[0] + span, g.nx - 1)
    if x0 <= x1:
        for iz in range(wp.max(c[2] - span, 0), wp.min(c[2] + span, g.nz - 1) + 1):
            for iy in range(wp.max(c[1] - span, 0), wp.min(c[1] + span, g.ny - 1) + 1):
                base = (iz * g.ny + iy) * g.nx
                for i in range(start[base + x0] + lane, start[base + x1 + 1], bd):
                    if a.fixture != 0 and order[i] >= 0:
                        continue
                    ns = away_point(X, point_at(spts, svel, i, dt), a, off, ns)
    return ns


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


def _tick_kernel(cap: int, maxreg: int = 0, bd: int = 1, resident: bool = False):
    """The tick kernel with a shared working set of ``cap`` points, a register cap and ``bd``
    threads a block (a constant of the kernel's code; 1 on Warp's CPU device): one kernel per
    triple; ``resident``: its resident form (kernels/warp/resident.py), CUDA only."""
    key = (cap, maxreg, bd)
    pair = _KERNELS.get(key) or _KERNELS.setdefault(key, _make_tick_kernel(cap, maxreg, bd))
    return pair[1] if resident else pair[0]


_KERNELS: dict = {}


def _make_tick_kernel(cap: int, maxreg: int = 0, bd: int = 1):
    BD = bd
    # a "warp" of the near lists: 32 threads on CUDA, the one thread of a block on the CPU
    WL = 32 if BD >= 32 else 1
    # near-list entries per warp: every point a warp's threads hold
    NJ = WL * ((cap + BD - 1) // BD)
    ws_src = f"""
#if defined(__CUDA_ARCH__)
    __shared__ float4 ws[{cap}];
    if (op == 1) ws[i] = make_float4(q[0], q[1], q[2], q[3]);
    else {{ const float4 b = ws[i]; return wp::vec4(b.x, b.y, b.z, b.w); }}
    return q;
#else
    static float ws[4 * {cap}];
    if (op == 1) {{ ws[4 * i] = q[0]; ws[4 * i + 1] = q[1]; ws[4 * i + 2] = q[2]; ws[4 * i + 3] = q[3]; }}
    return wp::vec4(ws[4 * i], ws[4 * i + 1], ws[4 * i + 2], ws[4 * i + 3]);
#endif
"""

    @wp.func_native(ws_src)
    def ws(op: int, i: int, q: wp.vec4) -> wp.vec4:
        """Working-set point i in shared memory: op 1 writes q, op 0 reads."""
        ...

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
    def ws_eval(X: wp.vec3, a: ProxyArgs, n: int, lane: int, wbase: int):
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
    def ws_clip(X: wp.vec3, u: wp.vec3, a: ProxyArgs, off: float, cnt: int, lane: int, wbase: int) -> float:
        """This thread's share of the step limit, over the warp's near list (the other points
        cannot shorten any step, see the kernel)."""
        tm = float(wp.inf)
        for i in range(lane % WL, cnt, WL):
            tm = clip_point(X, u, ws(0, near(0, wbase, i, 0, 0), wp.vec4(0.0)), a, off, tm)
        return tm

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

    @wp.func(inline=False)  # one copy for the first gather and the regathers
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
        block_sync()
        return sc[1], par, skin

    opts = {"cuda_max_registers": maxreg} if maxreg else {}

    @wp.func
    def run_steps(spts: wp.array(dtype=wp.vec4), svel: wp.array(dtype=wp.vec4), dt: float, order: wp.array(dtype=int),
                  start: wp.array(dtype=int), g: GridArgs, a: ProxyArgs, X: wp.vec3, H: wp.vec3, span: int,
                  grad: float, lane: int, wbase: int, X0: wp.vec3, n_ws: int, par: int, skin: float):
        """One tick's steps of a proxy at X towards H over its working set (gathered around X0:
        ``n_ws`` points, -1 for the hash path); returns (X, normal, nearest, state, steps,
        converged, and the working set's X0, n_ws, par, skin for the next tick)."""
        # A step's limit F is at most band / 2 (slack >= 0) and its length at most a.step, so a
        # point with clearance e >= band / 2 + margin + step cannot shorten it: the step reaches
        # that point's swept sphere (radius rho + F + margin) no sooner than e - F - margin >= step
        # >= L. ProxyArgs.rclip adds 1e-4 step and 1 um, which keep float32 rounding of e and of
        # the hit time out of the decision (as kernels/opencl/proxy.cl): the clip scans only each
        # warp's list of the points below rclip (ws_eval) and gets the very same step length.
        steps = int(0)
        conv = int(0)
        st = int(0)
        nrm = wp.vec3(0.0)
        min_e = float(wp.inf)
        uprev = wp.vec3(0.0)  # direction of the last sliding or free step
        for it in range(a.max_steps + 1):
            if it > 0:
                dx = X[0] - X0[0]
                dy = X[1] - X0[1]
                dz = X[2] - X0[2]
                if dx * dx + dy * dy + dz * dz > skin * skin:  # wandered off its working set
                    X0 = X
                    n_ws, par, skin = gather(spts, svel, dt, order, start, g, a, X0, grad, lane, BD, par)
            c = wp.vec3i(0)
            if n_ws < 0:
                c = cell_box(X, g, span)

            # 1. clearances, normal sum, smallest clearance within the normal band
            ns = wp.vec3(0.0)
            me = float(wp.inf)
            nnear = int(0)
            if n_ws >= 0:
                ns, me, nnear = ws_eval(X, a, n_ws, lane, wbase)
            else:
                ns, me = hash_eval(spts, svel, dt, order, start, g, a, X, c, span, lane, BD)
            rd = block_reduce4(wp.vec4(ns[0], ns[1], ns[2], me), 8, par, BD)
            par = 1 - par
            nsum = wp.vec3(rd[0], rd[1], rd[2])
            min_e = rd[3]
            st = 0
            if min_e < 0.0:
                st = 2
            elif min_e < a.band:
                st = 1
            nrm, nn = unit_len(nsum)
            if it == a.max_steps:
                break

            # 2. direction and length (dissertation 2.2.4)
            v = H - X
            vn = wp.dot(v, nrm)
            vp = v - vn * nrm
            has_n = nn > 0.0
            # contact rules (3/4): along v with the HIP outside or no normal, else along vp
            u2 = wp.vec3(0.0)
            L2 = float(0.0)
            if st == 0 or vn > 0.0 or not has_n:
                u2, L2 = unit_len(v)
            else:
                u2, L2 = unit_len(vp)
            L2 = wp.min(L2, a.step)
            u = u2
            Lp = wp.min(0.5 * a.band - min_e, a.step)
            # limit F: mid-band for a free step, -slack otherwise, min e where buried (the deepest
            # penetration never grows); off = F + margin
            buried = st == 2 and min_e < -a.slack - a.margin
            lim = -a.slack
            if st == 0:
                lim = 0.5 * a.band
            elif buried:
                lim = min_e
            off = lim + a.margin

            # 3. clipping (block-wide minimum). Up to three tries, one clip pass in the code for
            # all of them (a smaller kernel: fewer instruction-cache misses): the push-out along n,
            # then (blocked) the contact rule's direction, then (buried and blocked again) away
            # from the deepest points.
            push = st == 2 and has_n
            along_n = push
            Lc = L2
            if push:
                u = nrm
                Lc = Lp
            s = float(0.0)
            attempt = int(0)
            while attempt < 3:
                tm = float(wp.inf)
                if n_ws >= 0:
                    tm = ws_clip(X, u, a, off, nnear, lane, wbase)
                else:
                    tm = hash_clip(spts, svel, dt, order, start, g, a, X, u, off, c, span, lane, BD)
                t = block_min(tm, par, BD)
                par = 1 - par
                s = wp.max(wp.min(Lc, t), 0.0)
                if s >= a.tol:
                    break
                if attempt == 0:
                    if not push:
                        break
                    along_n = False  # push-out blocked: the contact rule's direction instead
                    u = u2
                    Lc = L2
                elif attempt == 1:
                    if not buried:
                        break
                    along_n = True  # both blocked: away from the deepest points
                    av = wp.vec3(0.0)
                    if n_ws >= 0:
                        av = ws_away(X, a, off, n_ws, lane, BD)
                    else:
                        av = hash_away(spts, svel, dt, order, start, g, a, X, off, c, span, lane, BD)
                    ra = block_reduce4(wp.vec4(av[0], av[1], av[2], 0.0), 0, par, BD)
                    par = 1 - par
                    asum = wp.vec3(ra[0], ra[1], ra[2])
                    au, al = unit_len(asum)
                    s = 0.0
                    if not (al > 0.0):
                        break
                    u = au
                    Lc = Lp
                attempt += 1
            if s < a.tol:
                conv = 1
                break
            if not along_n:  # a slide turning back against the previous one: rocking in a crease
                if u[0] * uprev[0] + u[1] * uprev[1] + u[2] * uprev[2] < a.turn_back:
                    conv = 1
                    break
                uprev = u
            X = X + s * u
            steps += 1

        return X, nrm, min_e, st, steps, conv, X0, n_ws, par, skin

    @wp.kernel(enable_backward=False, module="unique", **opts)
    def proxy_tick(spts: wp.array(dtype=wp.vec4), order: wp.array(dtype=int), start: wp.array(dtype=int),
                   g: GridArgs, a: ProxyArgs, pos: wp.array(dtype=wp.vec3), hips: wp.array(dtype=wp.vec3), bd: int,
                   svel: wp.array(dtype=wp.vec4), tick: wp.array(dtype=TickArgs), nrm_out: wp.array(dtype=wp.vec3),
                   near_out: wp.array(dtype=float), state_out: wp.array(dtype=wp.int32),
                   steps_out: wp.array(dtype=wp.int32), conv_out: wp.array(dtype=wp.bool), caching: int,
                   wsc: wp.array(dtype=wp.vec4), wsk: wp.array(dtype=wp.vec4), wsi: wp.array(dtype=wp.vec4i)):
        """One tick of proxy p (a block of ``bd`` threads). ``caching``: whether the working sets
        persist from tick to tick in ``wsc`` (``cap`` points a proxy), with each proxy's
        (X0 m, skin m) in ``wsk`` and (build, dt bits, span, points or -1) in ``wsi``."""
        p, lane = wp.tid()
        # one thread reads the proxy's inputs (pinned host memory on the zero-copy path) and
        # shares them with the block
        if lane == 0:
            tk = tick[0]
            x = pos[p]
            hh = hips[p]
            shared4(1, 0, wp.vec4(x[0], x[1], x[2], 0.0))
            shared4(1, 1, wp.vec4(hh[0], hh[1], hh[2], 0.0))
            shared4(1, 2, wp.vec4(tk.dt, float(tk.span), tk.grad, 0.0))
            sharedi4(1, 0, wp.vec4i(tk.build, 0, 0, 0))
        block_sync()
        xv = shared4(0, 0, wp.vec4(0.0))
        hv = shared4(0, 1, wp.vec4(0.0))
        tv = shared4(0, 2, wp.vec4(0.0))
        X = wp.vec3(xv[0], xv[1], xv[2])
        H = wp.vec3(hv[0], hv[1], hv[2])
        dt = tv[0]
        span = int(tv[1])
        grad = tv[2]
        build = sharedi4(0, 0, wp.vec4i(0))[0]
        dtb = float_bits(dt)
        wbase = (lane // WL) * NJ
        # the working set of the proxy's last tick, from the cache in device memory, where it
        # still holds; else gathered anew
        X0 = X
        n_ws = int(-2)
        skin = a.skin
        par = int(0)
        hit = int(0)
        if caching != 0:
            ci = wsi[p]
            ck = wsk[p]
            if set_holds(ci, wp.vec3(ck[0], ck[1], ck[2]), ck[3], build, dtb, span, X):
                hit = 1
                X0 = wp.vec3(ck[0], ck[1], ck[2])
                skin = ck[3]
                n_ws = ci[3]
                for k in range(lane, n_ws, BD):
                    ws(1, k, wsc[p * cap + k])
                block_sync()
        if hit == 0:
            n_ws, par, skin = gather(spts, svel, dt, order, start, g, a, X0, grad, lane, BD, par)
        Xs = X0
        X, nrm, min_e, st, steps, conv, X0, n_ws, par, skin = run_steps(
            spts, svel, dt, order, start, g, a, X, H, span, grad, lane, wbase, X0, n_ws, par, skin)
        # (run_steps gathers again only at a position further than the skin from Xs)
        if caching != 0 and (hit == 0 or X0[0] != Xs[0] or X0[1] != Xs[1] or X0[2] != Xs[2]):
            for k in range(lane, n_ws, BD):
                wsc[p * cap + k] = ws(0, k, wp.vec4(0.0))
            if lane == 0:
                wsi[p] = wp.vec4i(build, dtb, span, n_ws)
                wsk[p] = wp.vec4(X0[0], X0[1], X0[2], skin)
        if lane == 0:
            results_out(p, X, nrm, min_e, st, steps, conv, pos, nrm_out, near_out, state_out, steps_out, conv_out)

    @wp.kernel(enable_backward=False, module="unique", **opts)
    def proxy_resident(spts: wp.array(dtype=wp.vec4), order: wp.array(dtype=int), start: wp.array(dtype=int),
                       svel: wp.array(dtype=wp.vec4), g: GridArgs, a: ProxyArgs, inbox: wp.array(dtype=wp.int32),
                       mb: wp.array(dtype=wp.int32), cmd: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                       n: int, last0: int, idle_ns: int, pos: wp.array(dtype=wp.vec3),
                       nrm_out: wp.array(dtype=wp.vec3), near_out: wp.array(dtype=float),
                       state_out: wp.array(dtype=wp.int32), steps_out: wp.array(dtype=wp.int32),
                       conv_out: wp.array(dtype=wp.bool), stage: wp.array(dtype=wp.vec4i)):
        """The resident form of ``proxy_tick`` on one snapshot slot (kernels/warp/resident.py):
        the blocks stay on their SMs and run a tick each time the host posts one in the inbox; a
        proxy's working set stays in shared memory from tick to tick while it holds, and its
        position in a register while the kernel ran the batch's previous tick (tick numbers are
        consecutive then; after another kernel's tick or a reset block 0 stages the positions from
        the host). Host memory is read by block 0 alone (reads from many blocks at once queue on
        the bus): it passes the tick on to the others through device memory. Each block writes
        its results into the host arrays; the last to finish writes the tick's number into the
        mailbox. The slot's arrays are kernel parameters and the tick-to-tick bookkeeping lives in
        shared memory, so that the step loop has the registers of ``proxy_tick``'s."""
        p, lane = wp.tid()
        wbase = (lane // WL) * NJ
        par = int(0)
        X = wp.vec3(0.0)
        X0 = wp.vec3(0.0)
        n_ws = int(-2)      # no working set yet
        skin = float(0.0)
        if lane == 0:
            # (build, dt bits, span) the set was gathered for, and the last tick number seen;
            # the last tick this kernel ran (none yet)
            sharedi4(1, 2, wp.vec4i(-1, -1, -1, last0))
            sharedi4(1, 1, wp.vec4i(-1, 0, 0, 0))
        block_sync()
        while True:
            s = int(0)
            last = sharedi4(0, 2, wp.vec4i(0))[3]
            ran = sharedi4(0, 1, wp.vec4i(0))[0]
            if p == 0:   # block 0 alone polls the host and passes the tick on; the others follow
                if lane < 32:
                    tick_in(1, 0, inbox, mb, stage, n, last, idle_ns, lane)
                block_sync()
                s = tick_in(0, 0, inbox, mb, stage, n, last, idle_ns, lane)[0]
                if s > 0 and s != ran + 1:
                    positions_in(pos, stage, n, lane, BD)
                    block_sync()
                if n > 1 and lane == 0:
                    command_put(cmd, s)
            else:
                if lane == 0:
                    sharedi4(1, 0, wp.vec4i(command_wait(cmd, last), 0, 0, 0))
                block_sync()
                s = sharedi4(0, 0, wp.vec4i(0))[0]
            if s <= 0:
                break
            hd = wp.vec4i(0)
            hg = wp.vec4i(0)
            hh = wp.vec4i(0)
            if p == 0:
                hd = tick_in(0, 0, inbox, mb, stage, n, last, idle_ns, lane)
                hg = tick_in(0, 1, inbox, mb, stage, n, last, idle_ns, lane)
                hh = tick_in(0, 2, inbox, mb, stage, n, last, idle_ns, lane)
            else:
                hd = staged4(stage, 0)
                hg = staged4(stage, 1)
                hh = staged4(stage, IN_HEAD + p)
            if s != ran + 1:
                X = bits_vec3(staged4(stage, IN_HEAD + n + p))
            build = hd[1]
            dtb = hd[2]
            span = hd[3]
            dt = bits_float(dtb)
            grad = bits_float(hg[1])
            H = bits_vec3(hh)
            fresh = n_ws == -2 or not set_holds(sharedi4(0, 2, wp.vec4i(0)), X0, skin, build, dtb, span, X)
            block_sync()   # every thread has read the bookkeeping before lane 0 updates it
            if lane == 0:
                sharedi4(1, 2, wp.vec4i(build, dtb, span, s))
                sharedi4(1, 1, wp.vec4i(s, 0, 0, 0))
            # (block 0 takes the next tick only after the host has seen this one done, and a
            # block counts itself done after reductions that every one of its threads reached
            # with its inputs read)
            if fresh:
                X0 = X
                n_ws, par, skin = gather(spts, svel, dt, order, start, g, a, X0, grad, lane, BD, par)
            X, nrm, min_e, st, steps, conv, X0, n_ws, par, skin = run_steps(
                spts, svel, dt, order, start, g, a, X, H, span, grad, lane, wbase, X0, n_ws, par, skin)
            if lane == 0:
                results_out(p, X, nrm, min_e, st, steps, conv, pos, nrm_out, near_out, state_out, steps_out, conv_out)
                tick_done(count, mb, n, s)
        if p == 0 and lane == 0:
            mailbox_set(mb, MB_ALIVE, 0)

    return proxy_tick, proxy_resident


class WarpProxies(ProxyBatch):
    """Proxies on a ``WarpPipeline``; create with ``pipeline.proxies(positions, params)``.

    The batch's host arrays (``positions``, ``normals``, ...) are pinned memory on CUDA that the
    tick's kernel writes into (directly, or by copies for batches over ``ZERO_COPY_MAX``). On
    CUDA a batch of up to ``resident.RESIDENT_MAX`` proxies runs its ticks on resident kernels
    (kernels/warp/resident.py); ``close()`` lets them go (the next tick brings one back)."""

    def __init__(self, pipeline, positions, params=None, block_dim: int | None = None, resident: bool = True,
                 ws_cache: bool = True):
        """``block_dim``: threads per proxy on CUDA (None: by batch size, ``block_dim_for``);
        ``resident``: whether small batches may run on a resident kernel (CUDA); ``ws_cache``:
        whether launched ticks of up to ``WS_CACHE_MAX`` proxies keep the working sets in device
        memory between ticks (else they gather every proxy's set every tick)."""
        self.dev = pipeline.device
        self._ws_cache_allowed = bool(ws_cache)
        self._resident_allowed = bool(resident) and self.dev.is_cuda
        self._resident = [None, None]   # one resident kernel per snapshot slot
        self.cuda = self.dev.is_cuda
        if self.cuda and block_dim is not None and (block_dim % 32 or not 32 <= block_dim <= 1024):
            raise ValueError(f"block_dim = {block_dim}; expected a multiple of 32 from 32 to 1024")
        if self.cuda and BLOCK_DIM and (BLOCK_DIM % 32 or not 32 <= BLOCK_DIM <= 1024):
            raise ValueError(f"POINTFENCE_WARP_BLOCK_DIM = {BLOCK_DIM}; expected a multiple of 32 from 32 to 1024")
        self._block_dim_request = block_dim
        self._tick_no = 0   # the resident ticks' number (kernels/warp/resident.py)
        self.stream = pipeline.query_stream
        self._graphs = {}
        self._last = (None, 0, None)   # (slot, n, graph) of the last tick
        super().__init__(pipeline, positions, params)
        p = self.params
        a = self.args = ProxyArgs()
        a.r1, a.band, a.nreach, a.step = p.r1, p.band, p.r3 - p.r1, p.step
        a.tol, a.slack, a.fixture, a.max_steps = p.tolerance, p.slack, int(p.mode == "fixture"), p.max_steps
        a.margin = p.margin
        a.turn_back = p.turn_back_cos
        a.skin_min = p.skin
        a.gather_r_min = self.reach + p.skin
        self.skin = a.skin = max(p.skin, GATHER_SKIN)
        a.gather_r = self.reach + a.skin
        a.rclip = 0.5 * p.band + p.margin + p.step * 1.0001 + 1.0e-6
        h = pipeline.grid.h
        a.span = search_span(self.reach, h)
        self._h = h
        self._tick = wp.zeros(1, dtype=TickArgs, device=self.dev)
        self._tick_host = wp.zeros(1, dtype=TickArgs, device="cpu", pinned=self.cuda)
        self._tick_view = self._device_view(self._tick_host, TickArgs, 1)
        self._tick_np = self._tick_host.numpy()
        self._tick_dt_set = None
        self._tick_build = None   # the build number in the tick's arguments
        self._set_tick(0.0, 0.0)
        self._prepare_resident()

    # --- storage ---------------------------------------------------------------------------
    def _device_view(self, host, dtype, length):
        """The pinned host array ``host`` as an array of the CUDA device (the same memory, read
        and written by kernels over the bus); the array itself on the CPU device."""
        if not self.cuda:
            return host
        return wp.array(ptr=host.ptr, dtype=dtype, shape=length, device=self.dev)

    def _alloc(self, n: int):
        if n <= self._cap:
            return
        cap = max(n, 2 * self._cap, 1)
        pinned = self.cuda
        host = {}
        for name, dtype in (("positions", wp.vec3), ("normals", wp.vec3), ("nearest", wp.float32),
                            ("states", wp.int32), ("steps", wp.int32), ("converged", wp.bool), ("hips", wp.vec3)):
            host[name] = (wp.zeros(cap, dtype=dtype, device="cpu", pinned=pinned), dtype)
        self._host = host
        self._positions = host["positions"][0].numpy()
        self._normals = host["normals"][0].numpy()
        self._nearest = host["nearest"][0].numpy()
        self._nearest.fill(np.inf)
        self._states = host["states"][0].numpy()
        self._steps = host["steps"][0].numpy()
        self._converged = host["converged"][0].numpy()
        self._hips_np = host["hips"][0].numpy()
        self._cap = cap
        self._grow(cap)

    def _grow(self, cap: int):
        self.close()   # a resident kernel holds the old arrays
        self._resident = [None, None]
        # zero-copy views of the host arrays, and device arrays for batches that copy
        self._views = {k: self._device_view(a, dt, cap) for k, (a, dt) in self._host.items()}
        if self.cuda:
            self._dev = {k: wp.zeros(cap, dtype=dt, device=self.dev) for k, (a, dt) in self._host.items()}
        self._graphs.clear()
        self._last = (None, 0, None)
        self._ws_cache = {}

    def _cache_for(self, n: int):
        """(caching, points, proxy states, proxy keys) for a launched tick of ``n`` proxies: the
        working-set cache of the capacity ``ws_capacity_for(n)``, made on first use (never
        while a graph is captured: ``_capture`` asks first), empty keys (build -1) at first."""
        if not (self._ws_cache_allowed and 0 < n <= WS_CACHE_MAX):
            if "off" not in self._ws_cache:
                self._ws_cache["off"] = (0, wp.zeros(1, dtype=wp.vec4, device=self.dev),
                                         wp.zeros(1, dtype=wp.vec4, device=self.dev),
                                         wp.zeros(1, dtype=wp.vec4i, device=self.dev))
            return self._ws_cache["off"]
        cap = ws_capacity_for(n)
        c = self._ws_cache.get(cap)
        if c is None:
            keys = wp.array(np.full((self._cap, 4), -1, np.int32), dtype=wp.vec4i, device=self.dev)
            c = self._ws_cache[cap] = (1, wp.zeros(self._cap * cap, dtype=wp.vec4, device=self.dev),
                                       wp.zeros(self._cap, dtype=wp.vec4, device=self.dev), keys)
        return c

    def _upload_positions(self):
        # the tick's view of the HIP buffer for this batch size, and whether it ticks resident
        # (RESIDENT_MAX is read here, when the size is set)
        self._hips_n = self._hips_np[: self.n]
        self._resident_n = self.cuda and self.resident()
        # a tick number skipped: no resident kernel keeps a proxy's position past a reset
        self._tick_no = _resident_mod.next_tick(self._tick_no)
        if self.cuda:   # the copying path keeps its positions on the device
            wp.copy(self._dev["positions"], self._host["positions"][0], count=self.n)
            if hasattr(self, "args"):   # (not yet during __init__, which prepares them itself)
                self._prepare_resident()

    def _prepare_resident(self):
        """Make both snapshot slots' resident kernels for this batch size now (their buffers and
        streams), so that no tick allocates them; each is launched by its slot's first tick."""
        n = self.n
        if self.resident(n):
            for i in (0, 1):
                r = self._resident[i]
                if r is None or r.n != n:
                    self._new_resident(n, i)

    def block_dim(self, n: int | None = None) -> int:
        """Threads per proxy of a launch for ``n`` proxies (default: the batch's size)."""
        if not self.cuda:
            return 1
        return self._block_dim_request or block_dim_for(self.n if n is None else n)

    def resident(self, n: int | None = None) -> bool:
        """Whether a tick of ``n`` proxies runs on the resident kernel (kernels/warp/resident.py)."""
        return self._resident_allowed and 0 < (self.n if n is None else n) <= resident_max()

    def close(self) -> None:
        """Let this batch's resident kernels go (they free their SMs; the next tick launches
        the one it needs again)."""
        for r in self._resident:
            if r is not None:
                r.stop()

    def zero_copy(self, n: int | None = None) -> bool:
        """Whether a tick of ``n`` proxies reads and writes host memory directly (no copies)."""
        return self.cuda and (self.n if n is None else n) <= ZERO_COPY_MAX

    def _set_tick(self, dt: float, extra: float):
        tk = self._tick_np[0]
        tk["dt"] = dt
        tk["span"] = search_span(self.reach + extra, self._h)
        # + 1 um: the float32 rounding of the box's corners (cell_of) cannot drop a point
        tk["grad"] = self.reach + self.skin + extra + 1.0e-6
        self._tick_vals = (float(tk["dt"]), int(tk["span"]), float(tk["grad"]))   # (for the resident tick)
        self._tick_dt_set = dt

    def _set_build(self, build: int):
        """The snapshot's build number in the tick's arguments (the working-set cache's key),
        written when it changes."""
        if build != self._tick_build:
            self._tick_np[0]["build"] = self._tick_build = build

    # --- the tick --------------------------------------------------------------------------
    def _record(self, slot, n):
        bd = self.block_dim(n)
        kernel = _tick_kernel(ws_capacity_for(n), maxreg_for(bd) if self.cuda else 0, bd)
        if not self.cuda or self.zero_copy(n):
            arr, tick = self._views, self._tick_view
        else:
            arr, tick = self._dev, self._tick
            wp.copy(arr["hips"], self._host["hips"][0], count=n)
            wp.copy(tick, self._tick_host)
        wp.launch_tiled(kernel, dim=[n], inputs=[slot.sorted_pts, slot.order, slot.start, self.pipeline.grid_args,
                        self.args, arr["positions"], arr["hips"], bd, slot.sorted_vel, tick, arr["normals"],
                        arr["nearest"], arr["states"], arr["steps"], arr["converged"], *self._cache_for(n)],
                        block_dim=bd, device=self.dev)
        if self.cuda and not self.zero_copy(n):
            for k in ("positions", "normals", "nearest", "states", "steps", "converged"):
                wp.copy(self._host[k][0], arr[k], count=n)

    def _new_resident(self, n, i):
        """The resident kernel of ``n`` proxies on snapshot slot ``i`` (not launched yet; the
        other slot's is stopped and dropped if its size differs)."""
        for j, r in enumerate(self._resident):
            if r is not None and (j == i or r.n != n):
                r.stop()
                self._resident[j] = None
        bd = self.block_dim(n)
        kernel = _tick_kernel(ws_capacity_for(n), maxreg_for(bd), bd, resident=True)
        self._resident[i] = _resident_mod.ResidentTick(self, n, kernel, bd, self.pipeline.buffers.slots[i])
        return self._resident[i]

    def _capture(self, slot, n):
        """The tick's CUDA graph for snapshot slot ``slot`` and ``n`` proxies (captured once)."""
        self._cache_for(n)   # (made before the capture: no allocation inside it)
        with wp.ScopedStream(self.stream):
            wp.capture_begin(device=self.dev, stream=self.stream)
            try:
                self._record(slot, n)
            finally:
                graph = wp.capture_end(device=self.dev, stream=self.stream)
        self._graphs[(id(slot), n)] = graph
        return graph

    def _step(self, hips):
        n = self.n
        if n == 0:
            return
        buf = self.pipeline.buffers
        i = buf.acquire()   # the front slot: no build overwrites it during the tick
        try:
            slot = buf.slots[i]
            if slot.vmax > 0.0:
                dt = self._tick_dt(min(slot.timestamps) if slot.timestamps else 0.0, slot.vmax)
                self._set_tick(dt, extra_span(slot.vmax, dt))
            else:   # nothing moves: dt = 0 (tick_dt), the plain spans
                self.last_dt = 0.0
                if self._tick_dt_set != 0.0:
                    self._set_tick(0.0, 0.0)
            if self._resident_n:
                r = self._resident[i]
                if r is None or r.n != n:
                    r = self._new_resident(n, i)
                self._tick_no = _resident_mod.next_tick(self._tick_no)
                r.run(slot.seq, self._tick_vals, hips, self._tick_no)
            elif not self.cuda:
                np.copyto(self._hips_n, hips)
                self._set_build(slot.seq)
                self._record(slot, n)
            else:
                np.copyto(self._hips_n, hips)
                self._set_build(slot.seq)
                last_slot, last_n, graph = self._last
                if last_slot is not slot or last_n != n:
                    graph = self._graphs.get((id(slot), n)) or self._capture(slot, n)
                    self._last = (slot, n, graph)
                wp.capture_launch(graph, stream=self.stream)
                wp.synchronize_stream(self.stream)
        except Exception as e:  # Warp reports CUDA failures as RuntimeError
            raise KernelError(f"Warp proxy kernel failed on {self.pipeline.backend.device_name}: {e}") from e
        finally:
            buf.release(i)


from . import resident as _resident_mod  # noqa: E402  (resident.py imports this module)
