"""The resident tick's protocol, both sides: the layout of the mailbox and the inbox in pinned
host memory, the host's writes and reads of them, and the kernel's (native CUDA code).

For a batch of up to ``WarpTuning.resident_max`` proxies on CUDA the tick kernel is launched once
and stays on the GPU, one block a proxy, waiting for ticks (kernels/warp/resident.py runs it,
kernels/warp/tick_kernels.py holds its kernel). The host and the kernel talk through pinned host
memory: an inbox of 16-byte chunks that the host writes and the kernel reads, and a mailbox of a
few words for the rest.

A tick: the host writes the tick's arguments (the slot's build number, dt, search span, gather
radius: only when they change) and every proxy's HIP into the inbox (``Inbox``), then the tick's
number into every chunk's tag. Warp 0 of block 0 polls all chunks at once, one 16-byte load
each (about a microsecond a round trip), until every tag carries the same new number
(``tick_in``): a chunk is read whole and x86 makes its tag visible only after the words written
before it, so the tick arrives in one round trip over the bus, without a fence. Block 0 passes
the tick to the other blocks through device memory (``command_put``, ``command_wait``,
``staged4``); after a reset it stages every position from the batch's host array too
(``positions_in``). Every block writes its results into the batch's host arrays and counts
itself done; the last writes the tick's number into ``MB_DONE`` (``tick_done``), which the host
spins on. Only block 0 reads host memory: reads by many blocks queue on the bus (a first
version, each block reading its own inputs, took 5.5 us more a proxy: 351 us a tick for 64
proxies on an H100). The host sets ``MB_STOP`` to make the kernel leave (``request_stop``); the
kernel clears ``MB_ALIVE`` when it has left (``mailbox_set``).
"""
from __future__ import annotations

import time

import numpy as np
import warp as wp

from .primitives import bits_float

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
#: tick numbers run 1 .. TICK_WRAP and start again (int32 words, never 0: a fresh inbox's tags)
TICK_WRAP = 0x7FFFFFF0


# --- the host's side ------------------------------------------------------------------------

def next_tick(no: int) -> int:
    """The tick number after ``no``."""
    return no % TICK_WRAP + 1


def pinned_words(words: int, dev):
    """An int32 array of ``words`` in pinned host memory: (the array, its NumPy view, its view
    as an array of the CUDA device ``dev``, which kernels read and write over the bus)."""
    host = wp.zeros(words, dtype=wp.int32, device="cpu", pinned=True)
    return host, host.numpy(), wp.array(ptr=host.ptr, dtype=wp.int32, shape=words, device=dev)


class Inbox:
    """The host's side of a resident kernel's inbox for ``n`` proxies (``IN_HEAD``): 16-byte
    chunks of (tag, three words) in pinned memory, the header's two, then a HIP's a proxy."""

    def __init__(self, n: int, dev):
        self.host, words, self.dev = pinned_words(4 * (IN_HEAD + n), dev)
        chunks = words.reshape(-1, 4)
        self._i, self._f = chunks, chunks.view(np.float32)
        self._tags = chunks[:, 0]
        self._hips = self._f[IN_HEAD:, 1:4]

    def header(self, build: int, dt: float, span: int, grad: float) -> None:
        """The tick's arguments: the snapshot's build number, dt (s), span (cells), gather radius
        (m); they hold for the ticks posted after this."""
        self._i[0, 1] = build
        self._f[0, 2] = dt
        self._i[0, 3] = span
        self._f[1, 1] = grad

    def post(self, hips, seq: int) -> None:
        """Tick ``seq`` with the HIPs ``hips`` (n, 3) m; the kernel takes it once every tag is
        ``seq``, so the tags are written last."""
        np.copyto(self._hips, hips)
        self._tags.fill(seq)


def request_stop(mb_np, mb=None, timeout_s=1.0) -> bool:
    """Ask a resident kernel to leave and wait (bounded) until it has; whether it has. Only the
    mailbox is read: no CUDA call, so this may run at any time (a finalizer during another
    thread's graph capture, where a stream query would break the capture). ``mb``: the
    mailbox's pinned array, kept alive until then."""
    mb_np[MB_STOP] = 1
    t_end = time.perf_counter() + timeout_s
    while mb_np[MB_ALIVE] != 0:
        if time.perf_counter() > t_end:
            return False
        time.sleep(2e-5)
    return True


# --- the kernel's side (native; block 0 reads the host's memory) -----------------------------

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



@wp.func
def bits_vec3(c: wp.vec4i) -> wp.vec3:
    """Words 1 to 3 of an inbox chunk as a vector."""
    return wp.vec3(bits_float(c[1]), bits_float(c[2]), bits_float(c[3]))
