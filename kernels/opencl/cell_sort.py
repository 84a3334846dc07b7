"""The OpenCL snapshot's cell sort: every surviving pixel's entry filed under its hash cell, in
rig pixel order (camera, then pixel) within each cell, the reference's stable sort, so that the
same frames give the same snapshot on every run and every device.

Two shapes give the same ``order`` and ``start``, entry for entry (``kernel_shape``, as for the
proxy and neighbour kernels: kernels/opencl/kernel_shape.py; "auto" runs "gpu" on GPU devices):

* ``"cpu"`` (frames.cl): a counting sort whose work-items each walk ``CPU_RUN`` pixels (1 where
  this shape is forced on a GPU) and take one atomic a run of equal cells, a scatter whose order
  within a cell follows the atomics, then ``sort_cells``, one work-item a cell putting its
  entries into pixel order: the scatter leaves a cell as stretches of consecutive pixels,
  disjoint intervals, which it orders by their first pixel (their starts listed in
  ``pix_rank``, free once the scatter has read it, and the cell copied to a scratch range; a
  cell already in order is left alone, a heapsort where a cell has more than
  ``SORT_STRETCHES`` stretches): right for PoCL's few threads, a long serial chain for one GPU
  thread.
* ``"gpu"`` (cell_sort_gpu.cl): the pixels are cut into runs (stretches of one cell, at most
  ``RUN_MAX`` pixels, never crossing a multiple of it); a run's head counts the whole run into
  its cell with one atomic and takes an index among its cell's runs with another
  (``count_heads``), lists its pixel and length there (``place_heads``: a cell's list lies in the
  cell's own slot range, as it has no more runs than points), and then places its entries from
  that list alone (``order_runs``): runs of one cell are disjoint pixel intervals, so a run's
  offset in pixel order is the length of the cell's runs that start at a smaller pixel, whatever
  order the atomics listed them in. No per-cell sort and no per-pixel atomic; a head reads its
  cell's list, independent loads (a 3 cm cell of a 640x480 camera at 0.6 m: about 30 runs a
  camera).

Both are deterministic by construction: the result is a function of the pixels' cells alone.
"""
from __future__ import annotations

import numpy as np

from .context import build
from .kernel_shape import check_shape, resolve_shape

#: work-items of a work-group (global sizes are rounded up to it)
LOCAL = 64
#: pixels a work-item of the CPU shape's count walks (one atomic a run of equal cells among them)
CPU_RUN = 64
#: longest run of the GPU shape (RUN_MAX in cell_sort_gpu.cl)
RUN_MAX = 64


def _round_up(n: int, m: int = LOCAL) -> int:
    return max(m, (n + m - 1) // m * m)


class CellSort:
    """The cell sort of an ``OpenCLPipeline``: its work buffers, allocated once, and its launches.

    ``pipeline``: the owner (its ``cl``, ``ctx``, ``prg`` (frames.cl), ``backend``, ``npix`` (rig
    pixels), ``ncells``, ``pix_cell`` and ``pix_prot`` (classify's output) and ``buffers`` (the
    snapshot slots, whose ``start`` and ``order`` the sort writes)). ``kernel_shape``: "auto", "cpu" or "gpu" (None: the backend's);
    ``shape`` is the one that runs."""

    def __init__(self, pipeline, kernel_shape=None):
        cl = self.cl = pipeline.cl
        ctx, backend = pipeline.ctx, pipeline.backend
        if kernel_shape is None:
            kernel_shape = getattr(backend, "kernel_shape", "auto")
        self.shape = resolve_shape(check_shape(kernel_shape), backend.device, cl)
        npix, C = pipeline.npix, pipeline.ncells
        self.npix, self.ncells = npix, C
        self.nchunks = int(min(4096, max(1, C // 64)))
        self.chunk = (C + self.nchunks - 1) // self.nchunks
        mf = cl.mem_flags
        n = max(npix, 1)
        # counts[c]: points of cell c; on the GPU shape counts[C + c] too: runs of cell c
        self.n_counts = 2 * C if self.shape == "gpu" else C
        self.counts = cl.Buffer(ctx, mf.READ_WRITE, 4 * self.n_counts)
        self.partial = cl.Buffer(ctx, mf.READ_WRITE, 4 * self.nchunks)
        if self.shape == "gpu":
            self.program = build(ctx, "cell_sort_gpu.cl")
            self.run_slot, self.run_len, self.head_pix, self.head_len = (cl.Buffer(ctx, mf.READ_WRITE, 4 * n)
                                                                         for _ in range(4))
        else:
            self.program = pipeline.prg
            self.pix_rank = cl.Buffer(ctx, mf.READ_WRITE, 4 * n)
            self.scratch = cl.Buffer(ctx, mf.READ_WRITE, 4 * n)      # sort_cells' copy of a cell out of order
            # Pixels per count_runs work-item: long runs on CPUs (fewer atomics), 1 on GPUs.
            self.per = CPU_RUN if backend.device.type & cl.device_type.CPU else 1
            self.n_runs = (npix + self.per - 1) // self.per
        #: per snapshot slot, the launches in order: (kernel instance with its arguments set, global size)
        self._launches = [self._bind(pipeline.prg, pipeline.pix_cell, pipeline.pix_prot, slot.start, slot.order)
                          for slot in pipeline.buffers.slots]

    def _kernel(self, program, name: str, gsize: tuple, *args):
        """(an instance of kernel ``name`` with ``args`` set, ``gsize``)."""
        k = self.cl.Kernel(program, name)
        k.set_args(*args)
        return k, gsize

    def _bind(self, frames_prg, pix_cell, pix_prot, start, order) -> list:
        """The sort's launches into one slot's ``start`` (int32, ncells + 1) and ``order`` (int32,
        a point each), from classify's ``pix_cell`` and ``pix_prot``: their arguments are set once
        here, so that a build only enqueues them."""
        npix, C, chunk, k = np.int32(self.npix), np.int32(self.ncells), np.int32(self.chunk), self._kernel
        gpix, gcells, gchunks = (_round_up(self.npix),), (_round_up(self.ncells),), (self.nchunks,)
        out = [k(frames_prg, "zero_ints", (_round_up(self.n_counts),), self.counts, np.int32(self.n_counts))]
        if self.shape == "gpu":
            out.append(k(self.program, "count_heads", gpix, pix_cell, npix, C, self.counts, self.run_slot, self.run_len))
        else:
            out.append(k(frames_prg, "count_runs", (_round_up(self.n_runs),), pix_cell, npix, np.int32(self.per),
                         self.counts, self.pix_rank))
        out += [k(frames_prg, "scan_chunks", gchunks, self.counts, C, chunk, start, self.partial),
                k(frames_prg, "scan_partials", (1,), self.partial, np.int32(self.nchunks), start, C),
                k(frames_prg, "scan_add", gchunks, start, C, chunk, self.partial)]
        if self.shape == "gpu":
            out += [k(self.program, "place_heads", gpix, pix_cell, npix, start, self.run_slot, self.run_len,
                      self.head_pix, self.head_len),
                    k(self.program, "order_runs", gpix, pix_cell, pix_prot, npix, C, self.counts, start, self.head_pix,
                      self.head_len, self.run_len, order)]
        else:
            out += [k(frames_prg, "scatter", gpix, pix_cell, self.pix_rank, pix_prot, npix, start, order),
                    k(frames_prg, "sort_cells", gcells, start, C, order, self.pix_rank, self.scratch)]
        return out

    def enqueue(self, q, slot: int):
        """Enqueue the sort of snapshot slot ``slot`` (its index in the pipeline's ``buffers``)
        on ``q``, after classify has written ``pix_cell`` and ``pix_prot``."""
        for kernel, gsize in self._launches[slot]:
            self.cl.enqueue_nd_range_kernel(q, kernel, gsize, None)
