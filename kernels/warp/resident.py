"""The resident tick: for small batches on CUDA, the proxy kernel stays on the GPU between ticks.

A CUDA graph launch and the wait for it cost about 10 us on an H100 (``bench floor``), and a
launched kernel starts with empty shared memory, so every tick also gathers each proxy's working
set again. For a batch of up to ``RESIDENT_MAX`` proxies the tick kernel can instead be launched
once and stay: one block a proxy sits on its SM and waits for ticks.

The host and the kernel talk through a mailbox, a few int32 words in pinned host memory
(``proxy.MB_*``). There is one resident kernel per snapshot slot, with the slot's arrays as
kernel parameters (in the constant bank, as the launched kernel has them), rather than one
kernel picking the slot's arrays per tick from device memory and holding their pointers in
registers through the step loop. The two kernels of a batch of up to ``RESIDENT_MAX`` proxies
take at most 64 of the GPU's SMs.

A tick: the host writes the HIPs and positions into the batch's pinned arrays and the tick's
arguments (the slot's build number, dt, search span, gather radius) into the mailbox of the
front slot's kernel, then the tick's sequence number (x86 keeps the order of these stores).
Block 0 of the kernel polls the sequence number (a read over the bus about every microsecond),
copies the header and every proxy's position and HIP into device memory with all its threads at
once and passes the command to the other blocks through device memory; every block runs its
proxy's tick as ``proxy_tick`` does and counts itself done; the last block copies every result
into the pinned arrays and writes the sequence number into ``MB_DONE``, which the host spins on.
Only one block a tick touches host memory: reads of host memory by many blocks queue on the bus
(a first version, each block reading its own inputs, took 5.5 us more a proxy: 351 us a tick
for 64 proxies on an H100). A proxy keeps its working set in shared memory from tick to tick
while the snapshot (the slot's build), dt and the search span are unchanged and it stays within
its skin of where the set was gathered; results do not depend on the working set
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
import time
import weakref

import numpy as np
import warp as wp

from ..errors import KernelError
from . import proxy as wproxy
from .proxy import MB_ALIVE, MB_BUILD, MB_DONE, MB_DT, MB_GRAD, MB_SEQ, MB_SPAN, MB_STOP

#: largest batch that runs resident (POINTFENCE_WARP_RESIDENT_MAX; 0: never)
RESIDENT_MAX = int(os.environ.get("POINTFENCE_WARP_RESIDENT_MAX", "32"))
#: the kernel leaves after this long without a tick (s)
IDLE_S = 0.1
#: a tick not done after this long is a failure (s)
TIMEOUT_S = 0.25
#: the host spins this long on a tick, then yields the interpreter lock while it waits (s)
SPIN_S = 0.002


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
        dev = batch.dev
        self.slot = slot
        self.n, self.kernel, self.bd, self.dev = n, kernel, bd, dev
        # what a launch needs of the batch (not the batch itself: no reference cycle)
        self.views, self.grid_args, self.args = batch._views, batch.pipeline.grid_args, batch.args
        self.device_name = batch.pipeline.backend.device_name
        self.stream = wp.Stream(dev)
        self.mb = wp.zeros(wproxy.MB_WORDS, dtype=wp.int32, device="cpu", pinned=True)
        self.mb_np = self.mb.numpy()
        self.mb_f = self.mb_np.view(np.float32)
        self.mb_dev = wp.array(ptr=self.mb.ptr, dtype=wp.int32, shape=wproxy.MB_WORDS, device=dev)
        self.cmd = wp.zeros(1, dtype=wp.int32, device=dev)
        self.count = wp.zeros(1, dtype=wp.int32, device=dev)
        # the tick's inputs staged in device memory by block 0, the results before they go out
        self.stage = wp.zeros(wproxy.STAGE_HEAD + 6 * n, dtype=float, device=dev)
        self.out = [wp.zeros(n, dtype=dt, device=dev) for dt in (wp.vec3, wp.vec3, float, wp.vec3i)]
        self.seq = 0
        self._posted, self._posted_tick = None, None   # the arguments in the mailbox now
        self.launches = 0
        self.running = False
        self.hung = False
        self._fin = weakref.finalize(self, _stop, self.mb_np, self.mb)

    def _launch(self):
        v = self.views
        self.mb_np[MB_STOP] = 0
        self.mb_np[MB_ALIVE] = 1
        with wp.ScopedStream(self.stream):
            self.cmd.fill_(self.seq)
            self.count.zero_()
        sl = self.slot
        wp.launch_tiled(self.kernel, dim=[self.n], block_dim=self.bd, device=self.dev, stream=self.stream,
                        inputs=[sl.sorted_pts, sl.order, sl.start, sl.sorted_vel, self.grid_args, self.args,
                                self.mb_dev, self.cmd, self.count, self.n,
                                self.seq, int(IDLE_S * 1e9), v["positions"], v["hips"], v["normals"], v["nearest"],
                                v["states"], v["steps"], v["converged"], self.stage, *self.out])
        self.launches += 1
        self.running = True

    def run(self, build: int, tick) -> None:
        """One tick on this kernel's snapshot slot (its build number ``build``) with the tick's
        arguments ``tick`` (dt s, span cells, gather radius m); the HIPs and positions are in the
        batch's pinned arrays. Returns when every proxy's results are there."""
        mb, mf = self.mb_np, self.mb_f
        if self.hung:
            if mb[MB_ALIVE] != 0:
                raise KernelError("the resident Warp proxy kernel is still busy with a tick that timed out; close the batch")
            self.hung = self.running = False
        if not self.running or mb[MB_ALIVE] == 0:
            self._relaunch()
        if build != self._posted or tick is not self._posted_tick:   # (the same as last tick: as they are)
            mb[MB_BUILD] = build
            mf[MB_DT] = tick[0]
            mb[MB_SPAN] = tick[1]
            mf[MB_GRAD] = tick[2]
            self._posted, self._posted_tick = build, tick
        seq = self.seq = self.seq % 0x7FFFFFF0 + 1
        mb[MB_SEQ] = seq   # last: the kernel reads the words above once it sees it
        t0 = None
        while mb[MB_DONE] != seq:
            if mb[MB_ALIVE] == 0:
                # it left (idle) as this tick was posted, before taking it: again, from seq - 1
                self.seq = seq - 1
                self._relaunch()
                self.seq = seq
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

    def _relaunch(self):
        if self.running:
            _stop(self.mb_np)
        self._launch()

    def stop(self) -> None:
        """Let the kernel go (it is launched again by the next ``run``)."""
        if self.running:
            _stop(self.mb_np)
            self.running = False
