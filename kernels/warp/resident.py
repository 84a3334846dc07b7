"""The resident tick's host side: for small batches on CUDA, the proxy kernel stays on the GPU
between ticks.

A CUDA graph launch and the wait for it cost about 10 us on an H100 (``bench floor``), and a
launched kernel starts with empty shared memory, so every tick also gathers each proxy's working
set again. For a batch of up to ``WarpTuning.resident_max`` proxies the tick kernel can instead
be launched once and stay: one block a proxy sits on its SM and waits for ticks. The host and
the kernel talk through pinned host memory (the protocol, both sides:
kernels/warp/resident_protocol.py). There is one resident kernel per snapshot slot, with the
slot's arrays as kernel parameters (in the constant bank, as the launched kernel has them),
rather than one kernel picking the slot's arrays per tick from device memory and holding their
pointers in registers through the step loop. The two kernels of a batch take an SM a proxy
each: at most 64 of the GPU's SMs with the default ``resident_max`` of 32.

A proxy's position stays in a register while its kernel ran the batch's previous tick (the
batch numbers its ticks one after another and skips a number at a reset); otherwise block 0
stages every position from the batch's host array. A proxy keeps its working set in shared
memory from tick to tick while the snapshot (the slot's build), dt and the search span are
unchanged and it stays within its skin of where the set was gathered; results do not depend on
the working set, so a resident tick moves a proxy as a launched one does, up to the order of
float sums.

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
at most ``WarpTuning.resident_max`` proxies run this way (two kernels, one block a proxy and an
SM a block), which leaves the other SMs to the frame builds; larger batches use the launched
graph.
"""
from __future__ import annotations

import platform
import time
import weakref

import warp as wp

from ..errors import KernelError
from .resident_protocol import (IN_HEAD, MB_ALIVE, MB_DONE, MB_STOP, MB_WORDS, RESIDENT_CAP, Inbox,
                                pinned_words, request_stop)

#: whether the host's stores become visible in program order (x86-64: total store order), which
#: the inbox's tags rely on; elsewhere (an Arm host, such as Grace) every tick is launched
HOST_STORE_ORDER = platform.machine().lower() in ("x86_64", "amd64")
#: the kernel leaves after this long without a tick (s)
IDLE_S = 0.1
#: a tick not done after this long is a failure (s)
TIMEOUT_S = 0.25
#: the host spins this long on a tick, then yields the interpreter lock while it waits (s)
SPIN_S = 0.002


def resident_max(tuning) -> int:
    """Largest batch that runs on the resident kernel with ``tuning`` (a ``WarpTuning``): its
    ``resident_max``, or 0 on a host without x86's store order (``HOST_STORE_ORDER``)."""
    return tuning.resident_max if HOST_STORE_ORDER else 0


class ResidentTick:
    """One resident tick kernel for ``n`` proxies of a ``WarpProxies`` batch (see the module
    docstring): ``run`` does one tick, ``stop`` lets the kernel go.

    ``kernel``: the resident kernel (``tick_kernel(..., resident=True)``) for blocks of ``bd``
    threads; ``slot``: the snapshot slot it runs on; ``views``: the batch's result arrays as the
    CUDA device ``dev`` sees them (its pinned host arrays: positions, normals, nearest, states,
    steps, converged); ``grid_args``, ``args``: the pipeline's grid and the batch's
    ``ProxyArgs``; ``device_name`` for errors. What a launch needs of the batch, not the batch
    itself: no reference cycle."""

    def __init__(self, n: int, kernel, bd: int, slot, *, dev, views, grid_args, args, device_name: str):
        if n > RESIDENT_CAP:
            raise ValueError(f"a resident tick of {n} proxies; at most {RESIDENT_CAP} "
                             "(WarpTuning.resident_max)")
        self.slot = slot
        self.n, self.kernel, self.bd, self.dev = n, kernel, bd, dev
        self.views, self.grid_args, self.args = views, grid_args, args
        self.device_name = device_name
        self.stream = wp.Stream(dev)
        self.mb, self.mb_np, self.mb_dev = pinned_words(MB_WORDS, dev)
        self.inbox = Inbox(n, dev)
        self.cmd = wp.zeros(1, dtype=wp.int32, device=dev)
        self.count = wp.zeros(1, dtype=wp.int32, device=dev)
        # the tick's chunks staged in device memory by block 0 for the others, then the positions
        self.stage = wp.zeros(IN_HEAD + 2 * n, dtype=wp.vec4i, device=dev)
        self.seq = 0   # the tick number last posted in the inbox
        self._posted, self._posted_tick = None, None   # the header in the inbox now
        self.launches = 0
        self.running = False
        self.hung = False
        self._fin = weakref.finalize(self, request_stop, self.mb_np, self.mb)

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
        self.hung = not request_stop(self.mb_np)
        self.running = self.hung
        raise KernelError(f"the resident Warp proxy kernel did not finish tick {seq} within {TIMEOUT_S * 1e3:.1f} ms "
                          f"on {self.device_name}"
                          + ("; it has not left either (GPU hung?): close the batch" if self.hung else ""))

    def _relaunch(self, last: int):
        if self.running:
            request_stop(self.mb_np)
        self._launch(last)

    def stop(self) -> None:
        """Let the kernel go (it is launched again by the next ``run``)."""
        if self.running:
            request_stop(self.mb_np)
            self.running = False
