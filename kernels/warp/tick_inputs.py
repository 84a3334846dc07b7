"""A launched tick's inputs, staged in device memory by the first blocks (CUDA, the zero-copy path).

On the zero-copy path (batches of up to ``WarpTuning.zero_copy_max`` proxies) the tick's inputs
are in pinned host memory: every proxy's position (m, world frame) and HIP, and the tick's
arguments (``TickArgs``). A block that reads its own inputs over the bus queues behind every
other block's small reads: with three blocks an SM, a 1,024-proxy tick's blocks took 7.6 us to
reach their step loop, most of it these reads (bench/HISTORY.md, stop 43). So the first blocks
to start copy them all into device memory, 16 bytes a thread a round, every load of a round in
flight at once (one round, one trip over the bus, for every default zero-copy batch: 4,096
proxies take 48 bodies of 128 threads), and the others wait for them, then read theirs from device memory (the resident kernel's block 0 does the same for its ticks:
kernels/warp/resident_protocol.py). One 16-byte load a thread keeps the kernel's registers as
they were: each load kept in flight holds four registers in the code around the step loop too.

"First to start" are the bodies that take tickets 0 to k - 1 (k: the copy's 16-byte chunks
over the block size, at least 1 and at most ``kmax``, the device's SM count: a larger copy takes
more chunks a thread), not blocks 0 to k - 1. No body finishes before the copy is in, so the
bodies on the GPU until then are the first to start, and they hold the first tickets; every SM
holds at least one block of the kernel, so all k copying bodies are among them, whatever order
the hardware starts blocks in and however few blocks fit at once. (Without the bound, a batch
whose copy needs more bodies than fit at once would have every resident body waiting for a
copier that cannot start; tests/test_warp_gpu_paths.py has such a batch. Another kernel holding
SMs, a frame build or another batch's resident kernel, can delay the copy until it leaves them,
not stop it.) Three words of device memory (``sync``, zero when allocated) hold the
protocol:

* ``[0]`` the tickets: every body takes one (``atomicInc`` wraps to 0 after the n-th);
* ``[1]`` the slices copied: each copying body adds one when its slice is in device memory, and
  every body waits until all k have;
* ``[2]`` the bodies done (wrapping like the tickets): the last body to finish a tick sets
  ``[1]`` back to 0, when every body has passed its wait.

So every word is back at 0 after each tick, and nothing is reset between ticks. A tick that stops
halfway is a CUDA fault, which loses the context, and these words with it. Warp's CPU device
runs the kernel with ``staged`` 0 and never calls these functions.
"""
from __future__ import annotations

import warp as wp

#: words of the staging protocol's device array (``sync``; the fourth is padding)
SYNC_WORDS = 4


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    __shared__ unsigned ticket;
    unsigned* sy = (unsigned*)sync.data;
    if (lane == 0) ticket = atomicInc(sy, (unsigned)(n - 1));
    __syncthreads();
    // the positions and the HIPs (3 n floats each, 16-byte aligned) as 16-byte chunks, bd a body
    // and round (k >= 1: body 0 also copies the tails and the tick's arguments, even where n = 1
    // has no chunk; k <= kmax: every copying body is on the GPU before any body can finish)
    const int nf = 3 * n, n4 = nf >> 2, jobs = 2 * n4;
    const int k = max(1, min((jobs + bd - 1) / bd, kmax));
    const int t = (int)ticket;
    if (t < k) {
        for (int j = t * bd + lane; j < jobs; j += k * bd) {
            const float4 v = j < n4 ? ((const float4*)pos.data)[j] : ((const float4*)hips.data)[j - n4];
            if (j < n4) ((float4*)dpos.data)[j] = v; else ((float4*)dhips.data)[j - n4] = v;
        }
        if (t == 0) {   // the tails (fewer than four floats each) and the tick's arguments
            const int i = 4 * n4 + lane;
            if (i < nf) {
                ((float*)dpos.data)[i] = ((const float*)pos.data)[i];
                ((float*)dhips.data)[i] = ((const float*)hips.data)[i];
            }
            if (lane == 0) dtick.data[0] = tick.data[0];
        }
        __threadfence();
        __syncthreads();
        if (lane == 0) atomicAdd(sy + 1, 1u);
    }
    if (lane == 0) {
        while (((volatile unsigned*)sy)[1] != (unsigned)k) __nanosleep(64);
        __threadfence();
    }
    __syncthreads();
#endif
""")
def stage_inputs(pos: wp.array(dtype=wp.vec3), hips: wp.array(dtype=wp.vec3), tick: wp.array(dtype=wp.vec4i),
                 dpos: wp.array(dtype=wp.vec3), dhips: wp.array(dtype=wp.vec3), dtick: wp.array(dtype=wp.vec4i),
                 sync: wp.array(dtype=wp.int32), n: int, kmax: int, lane: int, bd: int):
    """Every thread of a body of a tick of ``n`` proxies (``bd`` threads a body): the bodies with
    the first tickets (at most ``kmax``: the device's SM count) copy the positions, the HIPs and
    the tick's arguments (``tick``: ``TickArgs`` as four words) from host memory into ``dpos``,
    ``dhips`` and ``dtick``, a slice each; every body waits until all slices are in."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    const float* f = (const float*)(a.data + i);
    return wp::vec3(__ldcg(f), __ldcg(f + 1), __ldcg(f + 2));
#else
    return a.data[i];
#endif
""")
def staged3(a: wp.array(dtype=wp.vec3), i: int) -> wp.vec3:
    """Element i of a staged array (read from L2: another SM wrote it in this kernel)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    const int4 v = __ldcg((const int4*)a.data);
    return wp::vec4i(v.x, v.y, v.z, v.w);
#else
    return a.data[0];
#endif
""")
def staged_tick(a: wp.array(dtype=wp.vec4i)) -> wp.vec4i:
    """The staged tick's arguments as four words (dt bits, span, grad bits, build: ``TickArgs``)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    unsigned* sy = (unsigned*)sync.data;
    if (atomicInc(sy + 2, (unsigned)(n - 1)) == (unsigned)(n - 1)) atomicExch(sy + 1, 0u);
#endif
""")
def tick_end(sync: wp.array(dtype=wp.int32), n: int):
    """One thread of a body that has finished the tick: the last of the ``n`` sets the slices'
    count back to 0 (every body has passed its wait)."""
    ...
