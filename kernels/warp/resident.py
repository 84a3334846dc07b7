"""The resident tick: for small batches on CUDA, the proxy kernel stays on the GPU between ticks.

A CUDA graph launch and the wait for it cost about 10 us on an H100 (``bench floor``), and a
launched kernel starts with empty shared memory, so every tick also gathers each proxy's working
set again. For a batch of up to ``RESIDENT_MAX`` proxies the tick kernel can instead be launched
once and stay: one block a proxy sits on its SM and waits for ticks.

The host and the kernel talk through pinned host memory: an inbox of 16-byte chunks that the
host writes and the kernel reads, and a mailbox of a few words (``proxy.MB_*``) for the rest.
There is one resident kernel per snapshot slot, with the slot's arrays as kernel parameters (in
the constant bank, as the launched kernel has them), rather than one kernel picking the slot's
arrays per tick from device memory and holding their pointers in registers through the step
loop. The two kernels of a batch of up to ``RESIDENT_MAX`` proxies take at most 64 of the GPU's
SMs.

A tick: the host writes the tick's arguments (the slot's build number, dt, search span, gather
radius: only when they change) and every proxy's HIP into the front slot's inbox, then the
tick's number into every chunk's tag (``proxy.IN_HEAD``). Warp 0 of block 0 polls all chunks at
once, one 16-byte load each (about a microsecond a round trip), until every tag carries the
same new number: a chunk is read whole and x86 makes its tag visible only after the words
written before it, so the tick arrives in one round trip over the bus, without a fence. Block 0
passes the tick to the other blocks through device memory. A proxy's position stays in a
register while its kernel ran the batch's previous tick (the batch numbers its ticks one after
another and skips a number at a reset); otherwise block 0 stages every position from the batch's
host array. Every block runs its proxy's tick as ``proxy_tick`` does, writes its results into
the batch's host arrays and counts itself done; the last writes the tick's number into
``MB_DONE``, which the host spins on. Only block 0 reads host memory: reads by many blocks queue
on the bus (a first version, each block reading its own inputs, took 5.5 us more a proxy: 351 us
a tick for 64 proxies on an H100). A proxy keeps its working set in shared memory from tick to
tick while the snapshot (the slot's build), dt and the search span are unchanged and it stays
within its skin of where the set was gathered; results do not depend on the working set
(kernels/warp/proxy.py), so a resident tick moves a proxy as a launched one does, up to the
order of float sums.

Safety and lifetime:
* the host waits at most ``TIMEOUT_S`` for a tick (``KernelError`` then: the service holds the
  robot), spinning for ``SPIN_S`` and then yielding the interpreter lock while it waits; a GPU
  fault ends the kernel and the host's wait times out the same way;
* the kernel leaves by itself after ``IDLE_S`` without a tick (a stalled or stopped loop does not
  keep SMs spinning, and a host call that waits for the whole device is held up at most that
  long), and when the host sets ``MB_STOP`` (``stop``: batch closed, resized or collected); the
  next tick launches it again;
* a process that ends takes its kernels with it (the driver tears the context down).

The blocks must all be on the GPU at once (they wait for block 0's commands), so only batches of
at most ``RESIDENT_MAX`` proxies run this way (two kernels, one block a proxy and an SM a block),
which leaves the other SMs to the frame builds; larger batches use the launched graph.
"""
from __future__ import annotations

import os
import platform
import time
import weakref

import numpy as np
import warp as wp

from ..errors import KernelError
from . import proxy as wproxy
from .proxy import MB_ALIVE, MB_DONE, MB_STOP

#: largest batch that runs resident (POINTFENCE_WARP_RESIDENT_MAX; 0: never)
RESIDENT_MAX = int(os.environ.get("POINTFENCE_WARP_RESIDENT_MAX", "32"))
if not 0 <= RESIDENT_MAX <= wproxy.RESIDENT_CAP:
    raise ValueError(f"POINTFENCE_WARP_RESIDENT_MAX = {RESIDENT_MAX}; expected 0 (never resident) to "
                     f"{wproxy.RESIDENT_CAP}")
#: whether the host's stores become visible in program order (x86-64: total store order), which
#: the inbox's tags rely on; elsewhere (an Arm host, such as Grace) every tick is launched
HOST_STORE_ORDER = platform.machine().lower() in ("x86_64", "amd64")
#: the kernel leaves after this long without a tick (s)
IDLE_S = 0.1
#: a tick not done after this long is a failure (s)
TIMEOUT_S = 0.25
#: the host spins this long on a tick, then yields the interpreter lock while it waits (s)
SPIN_S = 0.002
#: tick numbers run 1 .. TICK_WRAP and start again (int32 words, never 0: a fresh inbox's tags)
TICK_WRAP = 0x7FFFFFF0


def next_tick(no: int) -> int:
    """The tick number after ``no``."""
    return no % TICK_WRAP + 1


def pinned_words(words: int, dev):
    """An int32 array of ``words`` in pinned host memory: (the array, its NumPy view, its view
    as an array of the CUDA device ``dev``, which kernels read and write over the bus)."""
    host = wp.zeros(words, dtype=wp.int32, device="cpu", pinned=True)
    return host, host.numpy(), wp.array(ptr=host.ptr, dtype=wp.int32, shape=words, device=dev)


class Inbox:
    """The host's side of a resident kernel's inbox for ``n`` proxies (``proxy.IN_HEAD``): 16-byte
    chunks of (tag, three words) in pinned memory, the header's two, then a HIP's a proxy."""

    def __init__(self, n: int, dev):
        self.host, words, self.dev = pinned_words(4 * (wproxy.IN_HEAD + n), dev)
        chunks = words.reshape(-1, 4)
        self._i, self._f = chunks, chunks.view(np.float32)
        self._tags = chunks[:, 0]
        self._hips = self._f[wproxy.IN_HEAD:, 1:4]

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


def _stop(mb_np, mb=None, timeout_s=1.0) -> bool:
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


class ResidentTick:
    """One resident tick kernel for ``n`` proxies of a ``WarpProxies`` batch (see the module
    docstring): ``run`` does one tick, ``stop`` lets the kernel go."""

    def __init__(self, batch, n: int, kernel, bd: int, slot):
        if n > wproxy.RESIDENT_CAP:
            raise ValueError(f"a resident tick of {n} proxies; at most {wproxy.RESIDENT_CAP} "
                             "(POINTFENCE_WARP_RESIDENT_MAX)")
        dev = batch.dev
        self.slot = slot
        self.n, self.kernel, self.bd, self.dev = n, kernel, bd, dev
        # what a launch needs of the batch (not the batch itself: no reference cycle)
        self.views, self.grid_args, self.args = batch._views, batch.pipeline.grid_args, batch.args
        self.device_name = batch.pipeline.backend.device_name
        self.stream = wp.Stream(dev)
        self.mb, self.mb_np, self.mb_dev = pinned_words(wproxy.MB_WORDS, dev)
        self.inbox = Inbox(n, dev)
        self.cmd = wp.zeros(1, dtype=wp.int32, device=dev)
        self.count = wp.zeros(1, dtype=wp.int32, device=dev)
        # the tick's chunks staged in device memory by block 0 for the others, then the positions
        self.stage = wp.zeros(wproxy.IN_HEAD + 2 * n, dtype=wp.vec4i, device=dev)
        self.seq = 0   # the tick number last posted in the inbox
        self._posted, self._posted_tick = None, None   # the header in the inbox now
        self.launches = 0
        self.running = False
        self.hung = False
        self._fin = weakref.finalize(self, _stop, self.mb_np, self.mb)

    def _launch(self, last: int):
        """Launch the kernel, waiting for a tick other than ``last`` (the tags in the inbox)."""
        v = self.views
        self.mb_np[MB_STOP] = 0
        self.mb_np[MB_ALIVE] = 1
        with wp.ScopedStream(self.stream):
            self.cmd.fill_(last)
            self.count.zero_()
        sl = self.slot
        wp.launch_tiled(self.kernel, dim=[self.n], block_dim=self.bd, device=self.dev, stream=self.stream,
                        inputs=[sl.sorted_pts, sl.order, sl.start, sl.sorted_vel, self.grid_args, self.args,
                                self.inbox.dev, self.mb_dev, self.cmd, self.count, self.n, last,
                                int(IDLE_S * 1e9), v["positions"], v["normals"], v["nearest"], v["states"],
                                v["steps"], v["converged"], self.stage])
        self.launches += 1
        self.running = True

    def run(self, build: int, tick, hips, seq: int) -> None:
        """Tick number ``seq`` (the batch's, one more than its last tick's unless the positions
        were reset since) on this kernel's snapshot slot (its build number ``build``), with the
        tick's arguments ``tick`` (dt s, span cells, gather radius m) and the HIPs ``hips`` (n, 3)
        m. Returns when every proxy's results are in the batch's host arrays."""
        mb = self.mb_np
        if self.hung:
            if mb[MB_ALIVE] != 0:
                raise KernelError("the resident Warp proxy kernel is still busy with a tick that timed out; close the batch")
            self.hung = self.running = False
        if not self.running or mb[MB_ALIVE] == 0:
            self._relaunch(self.seq)
        if build != self._posted or tick is not self._posted_tick:   # (the same as last tick: as they are)
            self.inbox.header(build, *tick)
            self._posted, self._posted_tick = build, tick
        last, self.seq = self.seq, seq
        self.inbox.post(hips, seq)
        t0 = None
        while mb[MB_DONE] != seq:
            if mb[MB_ALIVE] == 0:
                # it left (idle) as this tick was posted, before taking it: again, from the last one
                self._relaunch(last)
            if t0 is None:
                t0 = time.perf_counter()
                continue
            waited = time.perf_counter() - t0
            if waited > TIMEOUT_S:
                self._give_up(seq)
            elif waited > SPIN_S:
                time.sleep(0)   # a slow tick: the other threads may run meanwhile

    def _give_up(self, seq):
        """A tick that did not finish in time: stop the kernel (it leaves after the tick it is in)
        and report it; the next tick launches it again, or fails at once while it has not left."""
        self.hung = not _stop(self.mb_np)
        self.running = self.hung
        raise KernelError(f"the resident Warp proxy kernel did not finish tick {seq} within {TIMEOUT_S * 1e3:.1f} ms "
                          f"on {self.device_name}"
                          + ("; it has not left either (GPU hung?): close the batch" if self.hung else ""))

    def _relaunch(self, last: int):
        if self.running:
            _stop(self.mb_np)
        self._launch(last)

    def stop(self) -> None:
        """Let the kernel go (it is launched again by the next ``run``)."""
        if self.running:
            _stop(self.mb_np)
            self.running = False
