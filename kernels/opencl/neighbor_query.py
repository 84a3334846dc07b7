"""The OpenCL neighbour query's host side: buffers kept from call to call, one kernel launch and
one read a call.

Two kernels give the same results bit for bit (kernels/reference/neighbors.py's): ``neighbors``
(neighbors.cl), one work-item a query, for CPUs, and ``neighbors_wg`` (neighbors_gpu.cl), one
work-group a query, for GPUs. The shape is the proxy kernel's setting (``kernel_shape``,
kernels/opencl/kernel_shape.py): "auto" runs the GPU shape on GPU devices.

Both kernels write one packed int32 result (counts, nearest, distance bits, then the index rows),
so a call is: the queries written into a device buffer, the launch, and one blocking read of the
result, on the pipeline's query queue. Queries (and on GPUs the result) are staged in host
memory the runtime allocates (``ALLOC_HOST_PTR``, mapped once: pinned on GPUs, so the copies are
DMA without a bounce buffer), grown (doubling) when a call needs more and never shrunk. Each
snapshot slot has its own kernel instance whose arguments are set once; a call sets only the
scalars that changed.
"""
from __future__ import annotations

import threading

import numpy as np

from ..errors import InputError, KernelError
from ..neighbors import Neighbors, search_span
from .context import build
from .kernel_shape import check_shape, neighbor_group_size, resolve_shape

#: most work-items a query of the GPU-shaped kernel (the device's limit for it may be lower)
MAX_GROUP = 1024
#: work-items a CPU-shaped work-group (queries a work-group)
CPU_LOCAL = 64
# kernel argument positions (both kernels)
A_QUERIES, A_NQ, A_RADIUS, A_SPAN, A_K, A_PROT, A_RES = 5, 6, 7, 8, 9, 10, 11
A_LOCAL = 12   # the GPU shape's local arrays: rowa[W], rowp[W + 1], scan[2 W] (int32)


class _Staging:
    """A device buffer of ``n`` elements of ``dtype`` and, if ``mapped``, a mapped host array
    beside it (``host``, else None)."""

    def __init__(self, cl, ctx, queue, n: int, dtype, flags, mapped: bool = True):
        mf = cl.mem_flags
        nbytes = n * np.dtype(dtype).itemsize
        self.dev = cl.Buffer(ctx, flags, nbytes)
        self.host = self._host_buf = None
        if mapped:
            self._host_buf = cl.Buffer(ctx, mf.READ_WRITE | mf.ALLOC_HOST_PTR, nbytes)
            self.host, _ = cl.enqueue_map_buffer(queue, self._host_buf, cl.map_flags.READ | cl.map_flags.WRITE, 0,
                                                 (n,), dtype, is_blocking=True)
        self.n = n

    def release(self, queue):
        if self.host is not None:
            self.host.base.release(queue)
            self.host = None


class NeighborQuery:
    """Fixed-radius queries on an ``OpenCLPipeline``'s snapshots (``pipeline.neighbors``).

    ``shape``: "cpu" or "gpu", the kernel that runs (resolved from ``kernel_shape``: "auto",
    "cpu" or "gpu"; None: the backend's). ``group_size``: work-items a query of the GPU-shaped
    kernel (1 to 1,024 or the device's limit; None: by batch size, ``kernel_shape.neighbor_group_size``); results do not
    depend on it. ``staged`` (fixed at construction): the result is read into a pinned staging
    array and copied from there into the arrays returned (None: on the GPU shape), else read
    straight into them (one copy fewer; on a GPU the driver then stages it in pinned memory of
    its own). The arrays returned are views of one array of the caller's, never of the staging.
    Calls from several threads take turns (one set of buffers)."""

    def __init__(self, pipeline, kernel_shape=None, group_size: int | None = None, staged: bool | None = None):
        self.pipeline = pipeline
        self.cl = cl = pipeline.cl
        backend = pipeline.backend
        if kernel_shape is None:
            kernel_shape = getattr(backend, "kernel_shape", "auto")
        self.shape = resolve_shape(check_shape(kernel_shape), backend.device, cl)
        self.group_size = group_size
        self.staged = self.shape == "gpu" if staged is None else bool(staged)
        self.queue = pipeline.query_queue
        if self.shape == "gpu":
            self._program, self._name = build(pipeline.ctx, "neighbors_gpu.cl"), "neighbors_wg"
        else:
            self._program, self._name = pipeline.prg, "neighbors"
        self._lock = threading.Lock()
        self._kernels = {}   # id(slot) -> [slot, kernel, (queries, res) bound, scalars set, group size set]
        self._q = self._res = None
        self._max_group = None

    def _ensure(self, B: int, n_res: int):
        cl, ctx, q = self.cl, self.pipeline.ctx, self.queue
        mf = cl.mem_flags
        if self._q is None or 4 * B > self._q.n:         # (4 floats a query)
            cap = max(B, 2 * (self._q.n // 4 if self._q else 0), 16)
            if self._q is not None:
                self._q.release(q)
            self._q = _Staging(cl, ctx, q, 4 * cap, np.float32, mf.READ_ONLY)
            self._q.host[:] = 0.0
        if self._res is None or n_res > self._res.n:
            cap = max(n_res, 2 * (self._res.n if self._res else 0), 1024)
            if self._res is not None:
                self._res.release(q)
            self._res = _Staging(cl, ctx, q, cap, np.int32, mf.WRITE_ONLY, mapped=self.staged)

    def _kernel(self, slot, values: tuple):
        """This slot's record (see ``_kernels``), its kernel instance with the current buffers and ``values`` (nq, radius, span,
        K, protected_only) as its arguments, setting only what changed since its last call."""
        cl, p = self.cl, self.pipeline
        rec = self._kernels.get(id(slot))
        if rec is None:
            k = cl.Kernel(self._program, self._name)   # own instance: per-slot arguments
            for i, a in enumerate((slot.pts, slot.order, slot.start, p.gridf, p.dims)):
                k.set_arg(i, a)
            rec = self._kernels[id(slot)] = [slot, k, None, None, None]
        k = rec[1]
        if rec[2] is None or rec[2][0] is not self._q:
            k.set_arg(A_QUERIES, self._q.dev)
        if rec[2] is None or rec[2][1] is not self._res:
            k.set_arg(A_RES, self._res.dev)
        rec[2] = (self._q, self._res)
        old = rec[3]
        types = (np.int32, np.float32, np.int32, np.int32, np.int32)
        for j, (v, t) in enumerate(zip(values, types)):
            if old is None or old[j] != v:
                k.set_arg(A_NQ + j, t(v))
        rec[3] = values
        return rec

    def _set_group(self, rec, w: int):
        """The GPU shape's local arrays for work-groups of ``w`` (when ``w`` changed)."""
        if rec[4] != w:
            k, LocalMemory = rec[1], self.cl.LocalMemory
            for j, n in enumerate((w, w + 1, 2 * w)):
                k.set_arg(A_LOCAL + j, LocalMemory(4 * n))
            rec[4] = w

    def _group(self, kernel, B: int) -> int:
        """Work-items a query of the GPU shape for a batch of ``B``."""
        if self._max_group is None:
            info = self.cl.kernel_work_group_info.WORK_GROUP_SIZE
            self._max_group = min(MAX_GROUP, kernel.get_work_group_info(info, self.pipeline.backend.device))
        if self.group_size is not None:
            w = int(self.group_size)
            if not 1 <= w <= self._max_group:
                raise InputError(f"neighbour query group_size = {w}; the GPU-shaped kernel runs work-groups of 1 to "
                                 f"{self._max_group} work-items on {self.pipeline.backend.device_name}: choose one in "
                                 "that range (None: by batch size)")
            return w
        return neighbor_group_size(B, self._max_group)

    def __call__(self, q: np.ndarray, radius: float, K: int, protected_only: bool) -> Neighbors:
        """Neighbours of the (B, 3) float32 queries ``q`` in the front snapshot; the arrays
        returned are the caller's own."""
        B = q.shape[0]
        if B == 0:
            return Neighbors(np.zeros(0, np.int32), np.zeros((0, K), np.int32), np.zeros(0, np.int32),
                             np.zeros(0, np.float32))
        cl, qq = self.cl, self.queue
        n = 3 * B + B * K
        values = (B, float(radius), search_span(radius, self.pipeline.grid.h), K, int(bool(protected_only)))
        try:
            with self._lock, self.pipeline.buffers.read() as slot:
                self._ensure(B, n)
                qh = self._q.host.reshape(-1, 4)
                qh[:B, :3] = q
                rec = self._kernel(slot, values)
                k = rec[1]
                if self.shape == "gpu":
                    w = self._group(k, B)
                    self._set_group(rec, w)
                    gsize, lsize = (B * w,), (w,)
                else:
                    gsize, lsize = (-(-B // CPU_LOCAL) * CPU_LOCAL,), None
                ev = cl.enqueue_copy(qq, self._q.dev, self._q.host[:4 * B], is_blocking=False)
                cl.enqueue_nd_range_kernel(qq, k, gsize, lsize)
                if self.staged:
                    cl.enqueue_copy(qq, self._res.host[:n], self._res.dev, is_blocking=True)
                    r = self._res.host[:n].copy()
                else:
                    r = np.empty(n, np.int32)
                    cl.enqueue_copy(qq, r, self._res.dev, is_blocking=True)
                del ev   # (waited for by the blocking read: see kernels/opencl/pipeline.py)
                return Neighbors(r[:B], r[3 * B: n].reshape(B, K), r[B: 2 * B], r[2 * B: 3 * B].view(np.float32))
        except cl.Error as e:
            raise KernelError(f"OpenCL neighbour query failed on {self.pipeline.backend.device_name}: {e}") from e
