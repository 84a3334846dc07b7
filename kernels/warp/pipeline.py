"""Warp frame pipeline: buffers allocated once, double-buffered snapshots, builds on their own
CUDA stream so that a build never stalls a query on the front snapshot.

On CUDA the whole build of a slot (depth and camera uploads from pinned memory, the kernels,
the scan, the point-count downloads) is one CUDA graph, captured on the first build into that
slot and replayed afterwards: an ingest is a host-side copy into pinned memory plus one graph
launch. Per-frame values (depth, poses) live in device arrays, so the graph never goes stale.
A camera that writes its depth image into ``depth_staging(camera)`` (a view of that pinned
memory) spares the ingest its one host copy.
"""
from __future__ import annotations

import threading
from ctypes import c_int64, c_void_p

import numpy as np
import warp as wp

from pointfence.native import fast

from ..backend import FramePipeline
from ..double_buffer import DoubleBuffer
from ..errors import KernelError
from ..motion import CELL_MOTION, N_MOMENTS
from ..neighbors import Neighbors, search_span
from ..snapshot import HostSnapshot
from . import frames as k
from .neighbor_query import neighbor_kernel

SELECT_CODE = {"all": 0, "box": 1, "color": 2, "mask": 3}


class _Slot:
    """Device arrays of one snapshot (layout in frames.py)."""

    def __init__(self, device, npix: int, ncells: int):
        n = max(npix, 1)
        self.pts = wp.zeros(n, dtype=wp.vec4, device=device)
        self.sigma = wp.zeros(n, dtype=float, device=device)
        self.order = wp.zeros(n, dtype=int, device=device)
        self.sorted_pts = wp.zeros(n, dtype=wp.vec4, device=device)
        self.sorted_vel = wp.zeros(n, dtype=wp.vec4, device=device)  # motion: per sorted point
        self.vmax = 0.0
        self.start = wp.zeros(ncells + 1, dtype=int, device=device)
        self.n_points = 0
        self.seq = 0
        self.timestamps = ()
        self.per_camera = ()


class WarpPipeline(FramePipeline):
    def __init__(self, backend, cameras, params):
        super().__init__(cameras, params)
        self.backend = backend
        dev = self.device = backend.device
        rig, g = self.rig, self.grid
        npix, C = rig.n_pixels, g.n_cells
        self.npix, self.ncells = npix, C
        self.cuda = dev.is_cuda
        self.build_stream = wp.Stream(dev) if self.cuda else None
        self.query_stream = wp.Stream(dev) if self.cuda else None

        self.rays = wp.array(rig.rays, dtype=wp.vec2, device=dev)
        self.depth = wp.zeros(max(npix, 1), dtype=wp.uint16, device=dev)
        self._depth_host = wp.zeros(max(npix, 1), dtype=wp.uint16, device="cpu", pinned=self.cuda)
        sel = params.selection.kind
        self.color = wp.zeros(3 * npix if sel == "color" else 1, dtype=wp.uint8, device=dev)
        self.mask = wp.zeros(npix if sel == "mask" else 1, dtype=wp.uint8, device=dev)
        self.counts = wp.zeros(C + 1, dtype=int, device=dev)
        self.nchunks = int(min(1024, max(1, C // 64)))
        self.chunk = (C + self.nchunks - 1) // self.nchunks
        self.partial = wp.zeros(self.nchunks, dtype=int, device=dev)
        self._cams_host = wp.zeros(len(rig), dtype=k.CamArgs, device="cpu", pinned=self.cuda)
        self._cams = wp.zeros(len(rig), dtype=k.CamArgs, device=dev)
        self._graphs = {}
        self.pix_cell = wp.zeros(max(npix, 1), dtype=int, device=dev)
        self.pix_prot = wp.zeros(max(npix, 1), dtype=int, device=dev)
        # (cell, entry) pairs of every pixel for the radix sort, with its scratch half
        self.sort_keys = wp.zeros(2 * max(npix, 1), dtype=int, device=dev)
        self.sort_entries = wp.zeros(2 * max(npix, 1), dtype=int, device=dev)
        self.sort_bits = max(1, int(C).bit_length())      # keys are 0 .. C
        self.cam_counts = wp.zeros(len(rig), dtype=int, device=dev)
        cam_of = np.repeat(np.arange(len(rig), dtype=np.int32), np.diff(rig.offsets))
        if params.motion.enabled:
            self.moments = wp.zeros((C, N_MOMENTS), dtype=float, device=dev)
            self.cell_motion = wp.zeros(C * CELL_MOTION // 4, dtype=wp.vec4, device=dev)
        self.cam_of = wp.array(cam_of if npix else np.zeros(1, np.int32), dtype=int, device=dev)
        self.buffers = DoubleBuffer([_Slot(dev, npix, C), _Slot(dev, npix, C)])
        self._n_host = wp.zeros(1, dtype=int, device="cpu", pinned=self.cuda)
        self._cam_host = wp.zeros(len(rig), dtype=int, device="cpu", pinned=self.cuda)
        # NumPy views of the host arrays, made once (a .numpy() call per ingest costs microseconds)
        self._depth_np = self._depth_host.numpy()
        self._cams_np = self._cams_host.numpy()
        self._n_np = self._n_host.numpy()
        self._cam_np = self._cam_host.numpy()
        self._staging = [self._depth_np[rig.offsets[i]:rig.offsets[i + 1]].reshape(c.height, c.width)
                         for i, c in enumerate(rig.cameras)]

        ga = self.grid_args = k.GridArgs()
        ws = params.workspace
        ga.wmin, ga.wmax = wp.vec3(*ws.min), wp.vec3(*ws.max)
        ga.origin = wp.vec3(*g.origin)
        ga.inv_h = float(g.inv_h)
        ga.nx, ga.ny, ga.nz = g.dims
        sa = self.select_args = k.SelectArgs()
        s, r = params.selection, params.radius
        sa.kind = SELECT_CODE[s.kind]
        sa.box_min, sa.box_max = wp.vec3(*s.box_min), wp.vec3(*s.box_max)
        sa.lo, sa.hi = wp.vec3i(*s.color_lo), wp.vec3i(*s.color_hi)
        sa.r_base, sa.k_sigma, sa.r_max, sa.adaptive = r.r_base, r.k_sigma, r.r_max, int(r.adaptive)
        ch = self._cams_host.numpy()
        ch["offset"], ch["n"], ch["max_code"], ch["index"] = (rig.ints[:, j] for j in range(4))
        self._nq_cap = self._nq_res_cap = 0
        self._nq_lock = threading.Lock()
        # recorded query launches: (slot, block size) -> [launch, results, (queries, B), values]
        self._nq_cmds = {}

    def depth_staging(self, camera):
        i = camera if isinstance(camera, (int, np.integer)) else self.rig.index.get(camera)
        if i is None or not 0 <= int(i) < len(self._staging):
            from ..errors import InputError

            raise InputError(f"depth_staging: no camera {camera!r} in the rig ({', '.join(self.rig.index)})")
        return self._staging[int(i)]

    def _stream(self, s):
        return wp.ScopedStream(s) if s is not None else wp.ScopedDevice(self.device)

    # --- build -----------------------------------------------------------------------------
    def _build_steps(self, frames, packed):
        """The build (see ``FramePipeline.ingest_steps``): on CUDA the build's graph is launched
        before the yield and waited for after it; on Warp's CPU device the kernels run before it."""
        b = self.buffers.back()
        slot = self.buffers.slots[b]
        for i, f in enumerate(frames):
            dst = self._staging[i]
            if f.depth.ctypes.data != dst.ctypes.data:   # not written in place by the camera
                np.copyto(dst, f.depth)
        ch = self._cams_np
        ch["R"] = packed[:, 0:9].reshape(-1, 3, 3)
        ch["t"] = packed[:, 9:12]
        ch["bias_a"], ch["bias_b"] = packed[:, 12], packed[:, 13]
        for j, name in enumerate(("depth_scale", "z_min", "z_max", "noise_a", "noise_b", "lateral")):
            ch[name] = packed[:, 16 + j]
        ch["has_color"], ch["has_mask"] = packed[:, 22], packed[:, 23]
        try:
            if self.params.selection.kind in ("color", "mask"):
                self._upload_selection(frames)
            if not self.cuda:
                self._record(slot)
            else:
                graph = self._graphs.get(b)
                if graph is None:
                    with wp.ScopedStream(self.build_stream):
                        wp.capture_begin(device=self.device, stream=self.build_stream)
                        try:
                            self._record(slot)
                        finally:
                            graph = wp.capture_end(device=self.device, stream=self.build_stream)
                    self._graphs[b] = graph
                wp.capture_launch(graph, stream=self.build_stream)
            try:
                yield                   # the device builds; the caller's other work runs meanwhile
            finally:
                if self.cuda:
                    wp.synchronize_stream(self.build_stream)
            slot.vmax = self._motion(slot, frames)
        except Exception as e:  # Warp raises plain RuntimeError on launch failures
            raise KernelError(f"Warp frame pipeline failed on {self.backend.device_name}: {e}") from e
        slot.n_points = int(self._n_np[0])
        slot.seq = self.seq + 1
        slot.timestamps = tuple(float(f.timestamp) for f in frames)
        slot.per_camera = tuple(self._cam_np.tolist())
        self.buffers.publish(b)
        return slot.n_points, slot.per_camera

    def _record(self, slot):
        """Enqueue one whole build into ``slot`` (captured into a graph on CUDA)."""
        dev, C = self.device, self.ncells
        wp.copy(self.depth, self._depth_host)
        wp.copy(self._cams, self._cams_host)
        self.counts.zero_()
        self.cam_counts.zero_()
        for i in range(len(self.rig)):
            wp.launch(k.classify, dim=int(self.rig.ints[i, 1]), device=dev,
                      inputs=[self.depth, self.rays, self._cams, i, self.grid_args, self.select_args,
                              self.color, self.mask, self.pix_cell, self.pix_prot, slot.pts, slot.sigma])
        if self.npix:
            # one atomic per run of same-cell pixels instead of one per pixel (32 adjacent pixels
            # of a warp hitting one counter serialise on the GPU)
            per = self.backend.tuning.run_pixels
            wp.launch(k.count_runs, dim=(self.npix + per - 1) // per, device=dev,
                      inputs=[self.pix_cell, self.cam_of, self.npix, per, self.counts, self.cam_counts])
        wp.launch(k.scan_chunks, dim=self.nchunks, device=dev, inputs=[self.counts, C, self.chunk, slot.start, self.partial])
        wp.launch(k.scan_partials, dim=1, device=dev, inputs=[self.partial, self.nchunks, slot.start, C])
        wp.launch(k.scan_add, dim=self.nchunks, device=dev, inputs=[slot.start, C, self.chunk, self.partial])
        if self.npix:
            # order: the pixels sorted by cell with a stable radix sort of pixel-ordered pairs, so
            # each cell's entries are in pixel order whatever order the GPU ran in (deterministic,
            # the reference's order); the counting atomics above give only the cells' starts
            wp.launch(k.sort_input, dim=self.npix, device=dev,
                      inputs=[self.pix_cell, self.pix_prot, C, self.sort_keys, self.sort_entries])
            wp.utils.radix_sort_pairs(self.sort_keys, self.sort_entries, self.npix, 0, self.sort_bits)
            wp.launch(k.take_sorted, dim=self.npix, device=dev, inputs=[self.sort_entries, slot.start, C, slot.order])
            wp.launch(k.gather_sorted, dim=self.npix, device=dev,
                      inputs=[slot.order, slot.start, C, slot.pts, slot.sorted_pts])
        wp.copy(self._n_host, slot.start, src_offset=C, count=1)
        wp.copy(self._cam_host, self.cam_counts)

    def _motion(self, slot, frames) -> float:
        """Estimate the slot's velocities (kernels/motion.py) before it is published; return vmax."""
        if not self.params.motion.enabled:
            return 0.0
        dev, C = self.device, self.ncells

        def moments():
            with self._stream(self.build_stream):
                wp.launch(k.cell_moments, dim=C, device=dev, inputs=[slot.sorted_pts, slot.start, self.grid_args, self.moments])
                return self.moments.numpy().astype(np.float64)

        cell_motion, vmax = self._estimate_motion(moments, tuple(float(f.timestamp) for f in frames))
        if cell_motion is None or vmax <= 0:
            return 0.0
        with self._stream(self.build_stream):
            self.cell_motion.assign(cell_motion.reshape(-1, 4))
            wp.launch(k.expand_velocity, dim=C, device=dev,
                      inputs=[self.cell_motion, slot.sorted_pts, slot.start, self.grid_args, slot.sorted_vel])
        if self.cuda:
            wp.synchronize_stream(self.build_stream)
        return vmax

    def _upload_selection(self, frames):
        rig = self.rig
        if self.params.selection.kind == "color":
            c = np.zeros((self.npix, 3), np.uint8)
            for i, f in enumerate(frames):
                if f.color is not None:
                    c[rig.offsets[i]:rig.offsets[i + 1]] = f.color.reshape(-1, 3)
            self.color.assign(c.reshape(-1))
        else:
            m = np.zeros(self.npix, np.uint8)
            for i, f in enumerate(frames):
                if f.mask is not None:
                    m[rig.offsets[i]:rig.offsets[i + 1]] = np.asarray(f.mask).reshape(-1) != 0
            self.mask.assign(m)

    # --- queries -------------------------------------------------------------------------
    def _ensure_query_capacity(self, B, K):
        """The query buffers for ``B`` queries of ``K`` neighbours, grown (doubling) when a call
        needs more and reused by every call that fits, both in pinned host memory that the
        kernel reads and writes over the bus on CUDA: the queries, and the packed results
        (counts, nearest, distance bits, then the index rows: kernels/warp/neighbor_query.py)."""
        dev, pinned = self.device, self.cuda
        if B > self._nq_cap:
            cap = max(B, 2 * self._nq_cap, 16)
            self._q_host = wp.zeros(cap, dtype=wp.vec3, device="cpu", pinned=pinned)
            self._q_np = self._q_host.numpy()
            self._nq_cap = cap
        need = 3 * B + B * K
        if need > self._nq_res_cap:
            cap = max(need, 2 * self._nq_res_cap, 1024)
            host = wp.zeros(cap, dtype=int, device="cpu", pinned=pinned)
            # the kernel writes the host memory itself (CUDA: over the bus, while other blocks
            # still run), so a call has no copy to wait for
            self._nq_res = wp.array(ptr=host.ptr, dtype=int, shape=cap, device=dev) if self.cuda else host
            self._nq_res_host, self._nq_res_np = host, host.numpy()
            self._nq_res_cap = cap

    def _query_launch(self, slot, bd: int, B: int, values: tuple):
        """The query kernel's recorded launch on ``slot`` for ``B`` queries, its parameters set to
        ``values`` (radius, span, K, protected_only): recorded once per slot and block size (and
        again when the result buffer grows), then only the changed parameters are set, the
        queries' view whenever B or the query buffer changed (a
        ``wp.launch`` packs every argument again, tens of microseconds of Python)."""
        key = (id(slot), bd)
        rec = self._nq_cmds.get(key)
        if rec is None or rec[1] is not self._nq_res:
            qa = wp.array(ptr=self._q_host.ptr, dtype=wp.vec3, shape=B, device=self.device)
            cmd = wp.launch_tiled(neighbor_kernel(bd), dim=[B], block_dim=bd, device=self.device, record_cmd=True,
                                  inputs=[slot.sorted_pts, slot.order, slot.start, self.grid_args, qa, *values,
                                          self._nq_res])
            rec = self._nq_cmds[key] = [cmd, self._nq_res, (self._q_host, B), values]
        cmd = rec[0]
        if rec[2][0] is not self._q_host or rec[2][1] != B:
            # the queries as the kernel sees them: the pinned host memory itself (grown since
            # this slot's last query, or another B)
            cmd.set_param_at_index(4, wp.array(ptr=self._q_host.ptr, dtype=wp.vec3, shape=B, device=self.device))
            cmd.set_dim([B, bd])
            rec[2] = (self._q_host, B)
        if rec[3] != values:
            for j, (v, old) in enumerate(zip(values, rec[3])):
                if v != old:
                    cmd.set_param_at_index(5 + j, v)
            rec[3] = values
        return cmd

    def _neighbors(self, q, radius, max_neighbors, protected_only):
        """One launch (a thread block a query, kernels/warp/neighbor_query.py) on buffers kept
        from call to call in pinned memory, and one wait for the stream. The returned arrays are
        the caller's own copies."""
        B, K = q.shape[0], max_neighbors
        if B == 0:
            return Neighbors(np.zeros(0, np.int32), np.zeros((0, K), np.int32), np.zeros(0, np.int32),
                             np.zeros(0, np.float32))
        bd = self.backend.tuning.query_block_dim if self.cuda else 1
        values = (float(radius), search_span(radius, self.grid.h), K, int(protected_only))
        try:
            # (the buffers serve one call at a time: callers on other threads wait here)
            with self._nq_lock, self.buffers.read() as slot:
                self._ensure_query_capacity(B, K)
                self._q_np[:B] = q
                self._query_launch(slot, bd, B, values).launch(self.query_stream)
                if self.cuda:
                    wp.synchronize_stream(self.query_stream)
                r = self._nq_res_np
                count = r[:B].copy()
                # each row's hits, -1 after them (the kernel writes no padding, so most of the
                # B x K rows cross the bus neither way): native/neighbor_rows.h
                index = np.empty((B, K), np.int32)
                fast.pf_neighbor_rows(c_void_p(r[3 * B:].ctypes.data), c_void_p(count.ctypes.data), c_int64(B),
                                      c_int64(K), c_void_p(index.ctypes.data))
                return Neighbors(count, index, r[B: 2 * B].copy(), r[2 * B: 3 * B].view(np.float32).copy())
        except Exception as e:  # Warp raises plain RuntimeError on launch failures
            raise KernelError(f"Warp neighbour query failed on {self.backend.device_name}: {e}") from e

    def proxies(self, positions, params=None, **options):
        """A batch of proxies on this pipeline, one launch per tick (``kernels/warp/proxy.py``)."""
        from .proxy import WarpProxies

        return WarpProxies(self, positions, params, **options)

    def host_snapshot(self) -> HostSnapshot:
        with self.buffers.read() as slot:
            n = slot.n_points
            order = slot.order.numpy()[:n].astype(np.int32)
            start = slot.start.numpy().astype(np.int32)
            pix = order & 0x7FFFFFFF
            pts = slot.pts.numpy()[pix].astype(np.float32)
            sigma = slot.sigma.numpy()[pix].astype(np.float32)
            cam = (np.searchsorted(self.rig.offsets, pix, side="right") - 1).astype(np.uint8)
            vel = slot.sorted_vel.numpy()[:n, :3].astype(np.float32).copy() if (n and slot.vmax > 0) else None
            return HostSnapshot(pts.reshape(n, 4), sigma, cam, (order < 0).astype(np.uint8), pix.astype(np.int32),
                                start, self.grid, slot.timestamps, slot.seq, slot.per_camera, vel,
                                slot.vmax if vel is not None else 0.0)
