"""OpenCL proxy batch: one kernel launch per haptic tick for all proxies (kernels/opencl/proxy.cl).

Device buffers (proxy positions, HIPs, packed outputs, per-proxy working sets) are allocated
when the batch is created and grow only when the number of proxies grows. The proxies'
positions stay on the device between ticks. A tick is: one non-blocking HIP upload, the kernel
(every step inside it) against the front snapshot, and one blocking read of the results, which
the kernel writes in the layout of the batch's host arrays (``out_block``), straight into them.

On PoCL a batch of up to ``INLINE_MAX`` proxies runs on the in-thread device (the kernel
executes in the thread that calls ``step``, reading the snapshot's shared host memory: no
worker hand-off, no wait behind a frame build); larger batches run on the worker pool. In-thread,
the HIPs and the outputs are host arrays the kernel addresses directly, and a tick makes no
blocking call: the calling thread keeps Python's interpreter lock from the HIP write to the
results (the haptic loop relies on this, ``service/loop.py``).

Two kernels give the same results bit for bit (``kernels/opencl/kernel_shape.py``): the
CPU-shaped ``proxy_tick`` (a work-item a proxy, working sets in global memory) and, on GPUs, the
GPU-shaped ``proxy_tick_wg`` (a work-group a proxy, its working set in local memory).
"""
from __future__ import annotations

import numpy as np

from ..errors import KernelError
from ..motion import extra_span
from ..neighbors import search_span
from ..proxy import LANES, WS_CAPACITY, ProxyBatch
from .context import build
from .kernel_shape import GroupSizing, check_shape, resolve_shape
from .shared_host import aligned_zeros, host_buffer

#: device memory the working sets of a batch may take together (bytes)
WS_BUDGET = 512 << 20
VW = LANES
#: largest batch run on PoCL's in-thread device (one core); larger ones use the worker pool
INLINE_MAX = 16
_COMPLETE = 0   # CL_COMPLETE


def _program(pipeline, inline: bool, shape: str):
    progs = pipeline.__dict__.setdefault("_proxy_programs", {})
    key = (inline, shape)
    if key not in progs:
        files = ("proxy.cl", "proxy_gpu.cl") if shape == "gpu" else ("proxy.cl",)
        progs[key] = build(pipeline.inline_ctx if inline else pipeline.ctx, *files)
    return progs[key]


def out_block(cap: int):
    """(block, views) for a batch of ``cap`` proxies: one page-aligned byte block (PoCL's
    in-thread kernel writes into it in place) in the layout of the kernels' ``write_out``
    (proxy.cl), and the batch's arrays as views of it: positions (cap, 3) float32 (world m),
    nearest clearances (cap,) float32 (m), normals (cap, 3) float32, states and
    steps (cap,) int32, converged flags (cap,) bool."""
    block = aligned_zeros(37 * cap, np.uint8)
    f = block[:36 * cap].view(np.float32)
    i = block[:36 * cap].view(np.int32)
    return block, (f[:3 * cap].reshape(cap, 3), f[3 * cap:4 * cap], f[4 * cap:7 * cap].reshape(cap, 3),
                   i[7 * cap:8 * cap], i[8 * cap:9 * cap], block[36 * cap:].view(np.bool_))


class OpenCLProxies(ProxyBatch):
    """Proxies on an ``OpenCLPipeline``; create with ``pipeline.proxies(positions, params)``.

    ``ws_capacity``: points per proxy working set (a multiple of ``LANES``; shrunk automatically so
    that a large batch's working sets fit ``WS_BUDGET``). Results never depend on it.
    ``local_size``: work-group size of the launch (None lets the OpenCL runtime choose).
    ``inline``: run on PoCL's in-thread device while the batch has at most ``INLINE_MAX``
    proxies (None: whenever the pipeline has one; False: never). ``device_kind`` says where the
    batch runs now ("in-thread" or "pool").
    ``kernel_shape``: "cpu", "gpu" or "auto" (None: the backend's ``kernel_shape``, see
    ``kernels/opencl/kernel_shape.py``); ``shape`` says which kernel runs. ``sizing``: the
    GPU-shaped kernel's ``GroupSizing`` (``local_size`` is the CPU-shaped kernel's alone); for the
    GPU shape ``ws_cap`` is the local working set of the current batch size, ``group_size`` the
    work-items a proxy.
    """

    def __init__(self, pipeline, positions, params=None, ws_capacity: int = WS_CAPACITY, local_size=None,
                 inline=None, kernel_shape=None, sizing: GroupSizing | None = None):
        self.cl = pipeline.cl
        self._ws_request = max(VW, int(ws_capacity) // VW * VW)
        self.local_size = local_size
        if kernel_shape is None:
            kernel_shape = getattr(pipeline.backend, "kernel_shape", "auto")
        self.shape = resolve_shape(check_shape(kernel_shape), pipeline.backend.device, self.cl)
        self.sizing = sizing if sizing is not None else GroupSizing()
        self.group_size = None
        # (the in-thread device is PoCL's: the CPU shape's)
        self._inline_allowed = pipeline.inline_ctx is not None and inline is not False and self.shape == "cpu"
        self._inline = None
        self.kernel = None
        self._spans = None
        super().__init__(pipeline, positions, params)

    @property
    def device_kind(self) -> str:
        return "in-thread" if self._inline else "pool"

    def _bind(self, inline: bool):
        """Kernel instance, queue and parameter buffer on the in-thread or the pool context."""
        pipeline, cl = self.pipeline, self.cl
        self._inline = inline
        self.ctx = pipeline.inline_ctx if inline else pipeline.ctx
        self.queue = pipeline.inline_queue if inline else pipeline.query_queue
        name = "proxy_tick_wg" if self.shape == "gpu" else "proxy_tick"
        self.kernel = k = cl.Kernel(_program(pipeline, inline, self.shape), name)  # own instance: per-batch arguments
        p = self.params
        gather_r = self.reach + p.skin
        self.prm_host = np.array([p.r1, p.band, p.r3 - p.r1, p.step, p.tolerance, p.slack, p.skin, gather_r,
                                  self.reach, p.margin, p.turn_back_cos, 0, 0, 0, 0, 0], np.float32)
        mf = cl.mem_flags
        self.prm = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=self.prm_host)
        k.set_arg(3, pipeline.gridf)
        k.set_arg(4, pipeline.dims)
        k.set_arg(11, self.prm)
        k.set_arg(12, np.int32(p.mode == "fixture"))
        k.set_arg(13, np.int32(p.max_steps))
        self._gather_r = gather_r
        self._spans = None
        self._set_spans(0.0)
        self._dt_arg = 0.0
        k.set_arg(17, np.float32(0.0))
        self._arg_slot = None

    def _set_spans(self, extra: float):
        """Hash spans of the gather and of the direct path, grown by ``extra`` m (motion)."""
        h = self.pipeline.grid.h
        spans = (search_span(self._gather_r + extra, h), search_span(self.reach + extra, h))
        if spans != self._spans:
            self.kernel.set_arg(14, np.int32(spans[0]))
            self.kernel.set_arg(15, np.int32(spans[1]))
            self._spans = spans

    # --- storage -------------------------------------------------------------------------------
    def _result_arrays(self, cap: int) -> tuple:
        """Views of one block in the kernels' output layout (``out_block``): a tick reads its
        results straight into them, and on PoCL's in-thread device the kernel writes them there
        itself."""
        self._out_block, (pos, nearest, normals, states, steps, conv) = out_block(cap)
        return pos, normals, nearest, states, steps, conv

    def _grow(self, cap: int):
        inline = self._inline_allowed and cap <= INLINE_MAX
        if inline != self._inline:
            self._bind(inline)
        cl, ctx, mf = self.cl, self.ctx, self.cl.mem_flags
        self._pos = cl.Buffer(ctx, mf.READ_WRITE, 16 * cap)
        if self.shape == "gpu":   # working sets in local memory: sized per batch size (_size_groups)
            self.ws_cap = 0
            self._ws = cl.Buffer(ctx, mf.READ_WRITE, 16)
            self._near = cl.Buffer(ctx, mf.READ_WRITE, 16)
        else:
            self.ws_cap = int(max(256, min(self._ws_request, WS_BUDGET // (16 * cap) // VW * VW)))
            self._ws = cl.Buffer(ctx, mf.READ_WRITE, 16 * self.ws_cap * cap)
            self._near = cl.Buffer(ctx, mf.READ_WRITE, 4 * (self.ws_cap // VW) * cap)   # clip's chunk lists
        self._pos_host = np.zeros((cap, 4), np.float32)
        if self._inline:   # shared with the in-thread kernel: no copies in a tick
            self._hips_host = aligned_zeros(12 * cap, np.float32, (cap, 3))
            self._hips = host_buffer(cl, ctx, self._hips_host, read_only=True)
            self._out = host_buffer(cl, ctx, self._out_block)
        else:
            self._hips_host = np.zeros((cap, 3), np.float32)
            self._hips = cl.Buffer(ctx, mf.READ_ONLY, 12 * cap)
            self._out = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=self._out_block)
        self._arg_slot = None
        self._set_batch_args()

    def _set_batch_args(self):
        k = self.kernel
        k.set_arg(6, self._pos)
        k.set_arg(7, self._hips)
        k.set_arg(8, self._out)
        k.set_arg(9, self._ws)
        k.set_arg(10, np.int32(self.ws_cap))
        k.set_arg(18, self._near)
        k.set_arg(22 if self.shape == "gpu" else 19, np.int32(self._cap))   # out_block's layout
        self._n_arg = None
        self._sized_for = None

    def _size_groups(self, n: int):
        """The GPU-shaped kernel's work-group size, local working set and term buffer for a
        batch of ``n`` proxies (local memory arguments 19 and 20, ``ws_cap``)."""
        if self.shape != "gpu" or self._sized_for == n:
            return
        cl, dev = self.cl, self.queue.device
        max_group = self.kernel.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, dev)
        w, cap, tb = self.sizing.plan(max(n, 1), self._ws_request, dev.local_mem_size, max_group)
        k = self.kernel
        k.set_arg(10, np.int32(cap))
        k.set_arg(19, cl.LocalMemory(16 * cap))
        k.set_arg(20, cl.LocalMemory(12 * tb))
        k.set_arg(21, np.int32(tb))
        self.group_size, self.ws_cap, self._sized_for = w, cap, n

    def _upload_positions(self):
        n = self.n
        self._size_groups(n)
        self._pos_host[:n, :3] = self._positions[:n]
        self.cl.enqueue_copy(self.queue, self._pos, self._pos_host[:n], is_blocking=True)

    # --- one tick ------------------------------------------------------------------------------
    def _step(self, hips):
        cl, n, k = self.cl, self.n, self.kernel
        if n == 0:
            return
        np.copyto(self._hips_host[:n], hips)
        if self._n_arg != n:
            k.set_arg(5, np.int32(n))
            self._n_arg = n
            if self.shape == "gpu":   # a work-group a proxy
                self._size_groups(n)
                self._gsize, self._lsize = (n * self.group_size,), (self.group_size,)
            else:
                ls = self.local_size
                self._gsize = (n if ls is None else (n + ls - 1) // ls * ls,)
                self._lsize = None if ls is None else (ls,)
        q = self.queue
        buf = self.pipeline.buffers
        i = buf.acquire()   # the front slot: no build overwrites it during the tick
        try:
            slot = buf.slots[i]
            if slot is not self._arg_slot:
                v = slot.inline if self._inline else slot
                k.set_arg(0, v.pts)
                k.set_arg(1, v.order)
                k.set_arg(2, v.start)
                k.set_arg(16, v.vel)
                self._arg_slot = slot
            dt = self._tick_dt(min(slot.timestamps) if slot.timestamps else 0.0, slot.vmax)
            if dt != self._dt_arg:
                k.set_arg(17, np.float32(dt))
                self._dt_arg = dt
            self._set_spans(extra_span(slot.vmax, dt))
            try:
                if self._inline:
                    ev = cl.enqueue_nd_range_kernel(q, k, self._gsize, self._lsize)  # runs here, now
                    if ev.command_execution_status != _COMPLETE:
                        ev.wait()
                else:
                    ev = cl.enqueue_copy(q, self._hips, self._hips_host[:n], is_blocking=False)
                    cl.enqueue_nd_range_kernel(q, k, self._gsize, self._lsize)
                    cl.enqueue_copy(q, self._out_block, self._out, is_blocking=True)   # into the batch's arrays
                    del ev   # complete by now: its destructor does not wait (see opencl/pipeline.py)
            except cl.Error as e:
                raise KernelError(f"OpenCL proxy kernel failed on {self.pipeline.backend.device_name} "
                                  f"({self.device_kind}): {e}") from e
        finally:
            buf.release(i)

