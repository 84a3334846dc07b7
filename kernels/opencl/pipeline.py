"""OpenCL frame pipeline: device buffers allocated once, double-buffered snapshots.

Host class in the style of Warp's examples: it owns every buffer, allocates them at
construction and launches kernels with explicit global sizes. Building runs on its own
command queue so queries on the front snapshot (another queue) never wait for a build.

Every non-blocking copy's event is kept until a later blocking call has waited for it:
pyopencl's event for a copy from or to a host array waits for the copy when it is destroyed,
*holding the interpreter lock*, so a dropped event would stall every Python thread (the
haptic loop's included) until the build queue reaches that copy.
"""
from __future__ import annotations

import numpy as np

from ..backend import FramePipeline
from ..double_buffer import DoubleBuffer
from ..errors import InputError, KernelError
from ..motion import CELL_MOTION, N_MOMENTS
from ..snapshot import HostSnapshot
from ..yielding import checkpoint
from .cell_sort import CellSort
from .context import _cl, build
from .neighbor_query import NeighborQuery

LOCAL = 64
SELECT_CODE = {"all": 0, "box": 1, "color": 2, "mask": 3}


def pinned_upload(device, cl) -> bool:
    """Whether frames go to ``device`` through a pinned upload array (``depth_staging``): on
    devices other than CPUs (a discrete GPU's copies from pageable memory take a staging copy in
    the driver, one a camera); on CPU devices a buffer is host memory already."""
    return not device.type & cl.device_type.CPU


def _round_up(n: int, m: int = LOCAL) -> int:
    return max(m, (n + m - 1) // m * m)


class _Views:
    """One context's buffers of a snapshot slot (see ``_Slot``)."""

    def __init__(self, pts, sigma, order, start, vel):
        self.pts, self.sigma, self.order, self.start, self.vel = pts, sigma, order, start, vel


class _Slot(_Views):
    """Device arrays of one snapshot (see frames.cl for the layout).

    pts: float4 per rig pixel, (x, y, z, r_f) in pixel order; only pixels listed in ``order``
    are meaningful. sigma: float per rig pixel. order: int32 per point, sorted by cell,
    entry = pixel | protected << 31. start: int32 (n_cells + 1), cell c's entries are
    order[start[c]:start[c+1]]. vel: float4 per point in ``order``'s order, the estimated
    velocity (kernels/motion.py; meaningful only while ``vmax`` > 0).

    With ``inline_ctx`` the arrays live in page-aligned host memory (``host``, which also keeps
    that memory alive: the ``USE_HOST_PTR`` buffers of both contexts point into it) that both the
    build context and the in-thread context address (``inline``: that context's buffers).
    """

    def __init__(self, cl, ctx, npix: int, ncells: int, inline_ctx=None):
        mf = cl.mem_flags
        n = max(npix, 1)
        sizes = {"pts": 16 * n, "sigma": 4 * n, "order": 4 * n, "start": 4 * (ncells + 1), "vel": 16 * n}
        if inline_ctx is None:
            super().__init__(**{k: cl.Buffer(ctx, mf.READ_WRITE, b) for k, b in sizes.items()})
            self.host = self.inline = None
        else:
            from .shared_host import aligned_zeros, host_buffer

            dt = {"pts": np.float32, "sigma": np.float32, "order": np.int32, "start": np.int32, "vel": np.float32}
            self.host = {k: aligned_zeros(b, dt[k]) for k, b in sizes.items()}
            super().__init__(**{k: host_buffer(cl, ctx, a) for k, a in self.host.items()})
            self.inline = _Views(**{k: host_buffer(cl, inline_ctx, a, read_only=True) for k, a in self.host.items()})
        self.vmax = 0.0
        self.n_points = 0
        self.seq = 0
        self.timestamps = ()
        self.per_camera = ()


class OpenCLPipeline(FramePipeline):
    def __init__(self, backend, cameras, params):
        super().__init__(cameras, params)
        cl = _cl()
        self.backend = backend
        self.cl = cl
        ctx = self.ctx = backend.context
        #: PoCL's in-thread device context (None: queries run on ``ctx`` like the builds)
        self.inline_ctx = getattr(backend, "inline_context", None)
        self.build_queue = cl.CommandQueue(ctx)
        self.query_queue = cl.CommandQueue(ctx)
        self.inline_queue = None if self.inline_ctx is None else cl.CommandQueue(self.inline_ctx)
        self.prg = build(ctx, "frames.cl", "neighbors.cl")
        self.k_zero = self.prg.zero_ints
        self.k_moments = self.prg.cell_moments
        self.k_expand = self.prg.expand_velocity

        mf = cl.mem_flags
        rig = self.rig
        npix, C = rig.n_pixels, self.grid.n_cells
        self.npix, self.ncells = npix, C
        self.rays = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=rig.rays)
        self.depth = cl.Buffer(ctx, mf.READ_ONLY, 2 * npix)
        self._staging, self._staging_views = self._pinned_depth(cl, ctx, backend.device)
        sel = params.selection.kind
        self.color = cl.Buffer(ctx, mf.READ_ONLY, 3 * npix if sel == "color" else 1)
        self.mask = cl.Buffer(ctx, mf.READ_ONLY, npix if sel == "mask" else 1)
        self.pix_cell = cl.Buffer(ctx, mf.READ_WRITE, 4 * npix)
        self.pix_prot = cl.Buffer(ctx, mf.READ_WRITE, npix)
        self.cam_counts = cl.Buffer(ctx, mf.READ_WRITE, 4 * len(rig))
        self._cam_counts_host = np.zeros(len(rig), np.int32)
        # Pixels a count_camera work-item walks: long stretches on CPUs (few atomics); on GPUs short
        # ones, so that thousands of work-items share a camera (at 4,096 a 640x480 camera has 75
        # work-items, each a long serial walk).
        self.cam_chunk = 4096 if backend.device.type & cl.device_type.CPU else 64
        if params.motion.enabled:
            self.moments = cl.Buffer(ctx, mf.READ_WRITE, 4 * N_MOMENTS * C)
            self.cell_motion = cl.Buffer(ctx, mf.READ_ONLY, 4 * CELL_MOTION * C)
            self._moments_host = np.zeros((C, N_MOMENTS), np.float32)
            self._cell_motion_host = np.zeros((C, CELL_MOTION), np.float32)
        self.buffers = DoubleBuffer([_Slot(cl, ctx, npix, C, self.inline_ctx) for _ in range(2)])
        #: the cell sort (kernels/opencl/cell_sort.py): its ``shape`` is the backend's ``kernel_shape``
        #: resolved for the device ("gpu": runs ordered by their heads, no per-cell sort)
        self.cell_sort = CellSort(self)
        self._n_host = np.zeros(1, np.int32)
        self._zero_cell_starts()

        ws, g = params.workspace, self.grid
        self.wmin = np.array([*ws.min, 0], np.float32)
        self.wmax = np.array([*ws.max, 0], np.float32)
        self.gridf = g.as_float4()
        self.dims = g.as_int4()
        s, r = params.selection, params.radius
        self.sel_args = (
            np.int32(SELECT_CODE[s.kind]), np.array([*s.box_min, 0], np.float32), np.array([*s.box_max, 0], np.float32),
            np.array([*s.color_lo, 0], np.int32), np.array([*s.color_hi, 0], np.int32),
        )
        self.radius_arg = np.array([r.r_base, r.k_sigma, r.r_max, 1.0 if r.adaptive else 0.0], np.float32)
        #: the neighbour query (kernels/opencl/neighbor_query.py): its ``shape`` is the backend's
        #: ``kernel_shape`` resolved for the device, ``group_size`` the GPU shape's work-group
        self.neighbor_query = NeighborQuery(self)
        self._bind_build_kernels()

    def _pinned_depth(self, cl, ctx, device):
        """Where ``pinned_upload``: the rig's depth images in one pinned host array (uint16, a
        pixel each, rig order; memory the runtime allocates, mapped once), uploaded by one DMA
        copy a build, and a (H, W) view of it a camera (``depth_staging``); else (None, ())."""
        if not pinned_upload(device, cl):
            return None, ()
        self._staging_buf = cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.ALLOC_HOST_PTR, 2 * max(self.npix, 1))
        arr, _ = cl.enqueue_map_buffer(self.build_queue, self._staging_buf, cl.map_flags.READ | cl.map_flags.WRITE, 0,
                                       (max(self.npix, 1),), np.uint16, is_blocking=True)
        arr[:] = 0
        offs = self.rig.offsets
        views = tuple(arr[int(offs[i]):int(offs[i + 1])].reshape(c.height, c.width)
                      for i, c in enumerate(self.rig.cameras))
        return arr, views

    def depth_staging(self, camera):
        """Camera ``camera``'s view of the pinned upload array (see ``_pinned_depth``), or None
        where there is none (CPU devices)."""
        i = camera if isinstance(camera, (int, np.integer)) else self.rig.index.get(camera)
        if i is None or not 0 <= int(i) < len(self.rig):
            raise InputError(f"depth_staging: no camera {camera!r} in the rig ({', '.join(self.rig.index)})")
        return self._staging_views[int(i)] if self._staging is not None else None

    def _bind_build_kernels(self):
        """Kernel instances of the build with their arguments set once (pyopencl's ``kernel(...)``
        sets every argument again on every launch): classify a camera a slot (a build sets only
        the camera's pose and parameters), count_camera a camera, and the zeroing of the counts."""
        cl, rig, prg = self.cl, self.rig, self.prg

        def bound(name, *args):
            k = cl.Kernel(prg, name)
            k.set_args(*args)
            return k

        pose0, cam0 = np.zeros(16, np.float32), np.zeros(8, np.float32)
        # a camera taking its readings at the near end of their steps has a kernel of its own
        name = ["classify_near" if cam.near_reading else "classify" for cam in rig.cameras]
        self._classify = [[bound(name[i], self.depth, self.rays, pose0, cam0, rig.ints[i].copy(), self.wmin, self.wmax,
                                 self.gridf, self.dims, *self.sel_args, self.color, self.mask, self.radius_arg,
                                 self.pix_cell, self.pix_prot, slot.pts, slot.sigma) for i in range(len(rig))]
                          for slot in self.buffers.slots]
        per = self.cam_chunk
        self._count_camera = [(bound("count_camera", self.pix_cell, rig.ints[i].copy(), np.int32(per), self.cam_counts),
                               (_round_up((int(rig.ints[i][1]) + per - 1) // per),)) for i in range(len(rig))]
        self._zero_cam_counts = bound("zero_ints", self.cam_counts, np.int32(len(rig)))

    def _zero_cell_starts(self):
        for slot in self.buffers.slots:
            self.k_zero(self.build_queue, (_round_up(self.ncells + 1),), None, slot.start, np.int32(self.ncells + 1))
        self.build_queue.finish()

    # --- build -----------------------------------------------------------------------------
    def _build_steps(self, frames, packed):
        """The build (see ``FramePipeline.ingest_steps``): enqueued and flushed to the device
        before the yield; the read of its point count waited for, motion estimated and the slot
        published after it."""
        cl, q, rig = self.cl, self.build_queue, self.rig
        b = self.buffers.back()
        slot = self.buffers.slots[b]
        events = []   # see the module docstring: dropped only after the wait for the read of n below
        try:
            for i, f in enumerate(frames):
                checkpoint()
                off = int(rig.offsets[i])
                if self._staging is None:
                    events.append(cl.enqueue_copy(q, self.depth, np.ascontiguousarray(f.depth), dst_offset=2 * off,
                                                  is_blocking=False))
                elif f.depth.ctypes.data != self._staging_views[i].ctypes.data:   # not written in place
                    np.copyto(self._staging_views[i], f.depth)
                if self.params.selection.kind == "color" and f.color is not None:
                    events.append(cl.enqueue_copy(q, self.color, np.ascontiguousarray(f.color), dst_offset=3 * off,
                                                  is_blocking=False))
                if self.params.selection.kind == "mask" and f.mask is not None:
                    m = (np.asarray(f.mask) != 0).astype(np.uint8)
                    events.append(cl.enqueue_copy(q, self.mask, m, dst_offset=off, is_blocking=False))
            if self._staging is not None:
                events.append(cl.enqueue_copy(q, self.depth, self._staging, is_blocking=False))
            for i, k in enumerate(self._classify[b]):
                checkpoint()
                k.set_arg(2, packed[i, :16].copy())   # pose
                k.set_arg(3, packed[i, 16:24].copy())   # camera parameters
                cl.enqueue_nd_range_kernel(q, k, (_round_up(int(rig.ints[i][1])),), None)
            checkpoint()
            self.cell_sort.enqueue(q, b)
            checkpoint()
            cl.enqueue_nd_range_kernel(q, self._zero_cam_counts, (LOCAL,), None)
            for k, gsize in self._count_camera:
                cl.enqueue_nd_range_kernel(q, k, gsize, None)
            events.append(cl.enqueue_copy(q, self._cam_counts_host, self.cam_counts, is_blocking=False))
            n_read = cl.enqueue_copy(q, self._n_host, slot.start, src_offset=4 * self.ncells, is_blocking=False)
            q.flush()
            try:
                yield                   # the device builds; the caller's other work runs meanwhile
            finally:
                n_read.wait()           # (also where the caller closes the generator here)
            events.clear()
            slot.vmax = self._motion(slot, frames)
        except cl.Error as e:
            raise KernelError(f"OpenCL frame pipeline failed on {self.backend.device_name}: {e}") from e
        slot.n_points = int(self._n_host[0])
        slot.seq = self.seq + 1
        slot.timestamps = tuple(float(f.timestamp) for f in frames)
        slot.per_camera = tuple(int(n) for n in self._cam_counts_host)
        self.buffers.publish(b)
        return slot.n_points, slot.per_camera

    def _motion(self, slot, frames) -> float:
        """Estimate the slot's velocities (kernels/motion.py) before it is published; return vmax."""
        if not self.params.motion.enabled:
            return 0.0
        cl, q = self.cl, self.build_queue

        def moments():
            self.k_moments(q, (_round_up(self.ncells),), None, slot.pts, slot.order, slot.start, self.gridf, self.dims,
                           self.moments)
            cl.enqueue_copy(q, self._moments_host, self.moments, is_blocking=True)
            return self._moments_host.astype(np.float64)

        cell_motion, vmax = self._estimate_motion(moments, tuple(float(f.timestamp) for f in frames))
        if cell_motion is not None and vmax > 0:
            self._cell_motion_host[:] = cell_motion
            cl.enqueue_copy(q, self.cell_motion, self._cell_motion_host, is_blocking=False)   # (host array kept: an attribute)
            self.k_expand(q, (_round_up(self.ncells),), None, self.cell_motion, slot.pts, slot.order, slot.start,
                          self.gridf, self.dims, slot.vel)
            q.finish()
            return vmax
        return 0.0

    # --- queries -------------------------------------------------------------------------
    def _neighbors(self, q, radius, max_neighbors, protected_only):
        """One write of the queries, one launch and one read (``NeighborQuery``)."""
        return self.neighbor_query(q, radius, max_neighbors, protected_only)

    def proxies(self, positions, params=None, **options):
        """A batch of proxies on this pipeline, one kernel launch per tick (``kernels/opencl/proxy.py``)."""
        from .proxy import OpenCLProxies

        return OpenCLProxies(self, positions, params, **options)

    def host_snapshot(self) -> HostSnapshot:
        cl, q = self.cl, self.query_queue
        with self.buffers.read() as slot:
            n = slot.n_points
            order = np.empty(n, np.int32)
            start = np.empty(self.ncells + 1, np.int32)
            pts = np.empty((max(self.npix, 1), 4), np.float32)
            sigma = np.empty(max(self.npix, 1), np.float32)
            events = []
            if n:
                events += [cl.enqueue_copy(q, order, slot.order, is_blocking=False),
                           cl.enqueue_copy(q, pts, slot.pts, is_blocking=False),
                           cl.enqueue_copy(q, sigma, slot.sigma, is_blocking=False)]
            vel = None
            if n and slot.vmax > 0:
                vel4 = np.empty((n, 4), np.float32)
                events.append(cl.enqueue_copy(q, vel4, slot.vel, is_blocking=False))
                vel = vel4[:, :3]
            cl.enqueue_copy(q, start, slot.start, is_blocking=True)
            events.clear()
            pix = order & 0x7FFFFFFF
            cam = (np.searchsorted(self.rig.offsets, pix, side="right") - 1).astype(np.uint8)
            return HostSnapshot(pts[pix], sigma[pix], cam, (order < 0).astype(np.uint8), pix.astype(np.int32), start,
                                self.grid, slot.timestamps, slot.seq, slot.per_camera,
                                None if vel is None else np.ascontiguousarray(vel), slot.vmax if vel is not None else 0.0)
