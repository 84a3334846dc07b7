"""The Warp proxy batch's host side: one tick for all proxies of a batch, nothing allocated per tick.

The kernels (one thread block a proxy) are in kernels/warp/tick_kernels.py; this class owns the
batch's buffers, allocated once per size, and launches them with explicit dimensions. On CUDA
the tick is captured once per snapshot slot into a CUDA graph and replayed each tick. For
batches up to ``WarpTuning.zero_copy_max`` the graph is the kernel alone: its first blocks copy
the HIPs, the positions and the tick's arguments from pinned host memory into device memory for
every block (kernels/warp/tick_inputs.py), and each block writes its results straight into the
batch's (pinned) host arrays, so a tick has no copy nodes and nothing to unpack. Larger
batches upload the HIPs and download the results with copies inside the graph. A launched tick
of up to ``WarpTuning.ws_cache_max`` proxies keeps each working set in device memory for the
next tick, keyed by the snapshot's build, dt, the search span and where it was gathered, and
copies a set that still holds instead of gathering it. A batch of up to
``WarpTuning.resident_max`` proxies on CUDA ticks on resident kernels instead
(kernels/warp/resident.py), which keep their sets in shared memory themselves.

The block size is a constant of each kernel's code (``WarpTuning.block_dim_for``); Warp's CPU
device runs one thread a block, and every tick is a plain launch there.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from ..errors import InputError, KernelError
from ..motion import extra_span
from ..neighbors import search_span
from ..proxy import ProxyBatch
from .args import TickArgs, proxy_args
from .resident import ResidentTick, resident_max
from .resident_protocol import next_tick
from .tick_inputs import SYNC_WORDS
from .tick_kernels import tick_kernel
from .tuning import WarpTuning


class WarpProxies(ProxyBatch):
    """Proxies on a ``WarpPipeline``; create with ``pipeline.proxies(positions, params)``.

    The batch's host arrays (``positions``, ``normals``, ...) are pinned memory on CUDA that the
    tick's kernel writes into (directly, or by copies for batches over
    ``WarpTuning.zero_copy_max``). On CUDA a batch of up to ``WarpTuning.resident_max`` proxies
    runs its ticks on resident kernels (kernels/warp/resident.py); ``close()`` lets them go (the
    next tick brings one back)."""

    def __init__(self, pipeline, positions, params=None, block_dim: int | None = None, resident: bool = True,
                 ws_cache: bool = True, tuning: WarpTuning | None = None):
        """``block_dim``: threads per proxy on CUDA (None: by batch size,
        ``WarpTuning.block_dim_for``); ``resident``: whether small batches may run on a resident
        kernel (CUDA); ``ws_cache``: whether launched ticks of up to ``WarpTuning.ws_cache_max``
        proxies keep the working sets in device memory between ticks (else they gather every
        proxy's set every tick); ``tuning``: the kernels' tuning (default: the backend's)."""
        tuning = pipeline.backend.tuning if tuning is None else tuning
        if not isinstance(tuning, WarpTuning):
            raise InputError(f"tuning = {tuning!r}; expected a WarpTuning (pointfence.kernels.warp.tuning)")
        self.tuning = tuning
        self.dev = pipeline.device
        self._ws_cache_allowed = bool(ws_cache)
        self._resident_allowed = bool(resident) and self.dev.is_cuda
        self._resident = [None, None]   # one resident kernel per snapshot slot
        self.cuda = self.dev.is_cuda
        if self.cuda and block_dim is not None and (block_dim % 32 or not 32 <= block_dim <= 1024):
            raise ValueError(f"block_dim = {block_dim}; expected a multiple of 32 from 32 to 1024")
        self._block_dim_request = block_dim
        self._tick_no = 0   # the resident ticks' number (kernels/warp/resident.py)
        self.stream = pipeline.query_stream
        self._graphs = {}
        self._last = (None, 0, None)   # (slot, n, graph) of the last tick
        self._gather_skin = None   # the skin of the batch's constants (``_set_args``)
        self._tick_dt_set = None   # the tick's arguments: none yet (``_set_tick``)
        self._tick_extra = 0.0
        super().__init__(pipeline, positions, params)
        self._h = pipeline.grid.h
        self._set_args(self.n)
        self._tick = wp.zeros(1, dtype=TickArgs, device=self.dev)
        self._tick_host = wp.zeros(1, dtype=TickArgs, device="cpu", pinned=self.cuda)
        self._tick_view = self._device_view(self._tick_host, TickArgs, 1)
        # the zero-copy tick's inputs, staged in device memory by its first blocks
        # (kernels/warp/tick_inputs.py): the tick's arguments as four words, their copy, and the
        # protocol's words (unused on the CPU device)
        self._tick4 = (wp.array(ptr=self._tick_host.ptr, dtype=wp.vec4i, shape=1, device=self.dev) if self.cuda
                       else wp.zeros(1, dtype=wp.vec4i, device=self.dev))
        self._dtick = wp.zeros(1, dtype=wp.vec4i, device=self.dev)
        self._sync = wp.zeros(SYNC_WORDS, dtype=wp.int32, device=self.dev)
        self._kmax = max(1, self.dev.sm_count)   # the most bodies that copy (tick_inputs.py)
        self._tick_np = self._tick_host.numpy()
        self._tick_build = None   # the build number in the tick's arguments
        self._set_tick(0.0, 0.0)
        self._prepare_resident()

    # --- storage ---------------------------------------------------------------------------
    def _device_view(self, host, dtype, length):
        """The pinned host array ``host`` as an array of the CUDA device (the same memory, read
        and written by kernels over the bus); the array itself on the CPU device."""
        if not self.cuda:
            return host
        return wp.array(ptr=host.ptr, dtype=dtype, shape=length, device=self.dev)

    def _result_arrays(self, cap: int) -> tuple:
        """The result arrays (and the HIPs') in host memory the CUDA kernels read and write
        directly (pinned), kept with their Warp arrays in ``_host``."""
        pinned = self.cuda
        host = {}
        for name, dtype in (("positions", wp.vec3), ("normals", wp.vec3), ("nearest", wp.float32),
                            ("states", wp.int32), ("steps", wp.int32), ("converged", wp.bool), ("hips", wp.vec3)):
            host[name] = (wp.zeros(cap, dtype=dtype, device="cpu", pinned=pinned), dtype)
        self._host = host
        self._hips_np = host["hips"][0].numpy()
        return tuple(host[k][0].numpy() for k in ("positions", "normals", "nearest", "states", "steps", "converged"))

    def _grow(self, cap: int):
        self.close()   # a resident kernel holds the old arrays
        self._resident = [None, None]
        # zero-copy views of the host arrays, and device arrays for batches that copy
        self._views = {k: self._device_view(a, dt, cap) for k, (a, dt) in self._host.items()}
        if self.cuda:
            self._dev = {k: wp.zeros(cap, dtype=dt, device=self.dev) for k, (a, dt) in self._host.items()}
        self._graphs.clear()
        self._last = (None, 0, None)
        self._ws_cache = {}

    def _cache_for(self, n: int):
        """(caching, points, proxy states, proxy keys) for a launched tick of ``n`` proxies: the
        working-set cache of ``WarpTuning.ws_capacity_for(n)`` points a proxy, made on first use (never
        while a graph is captured: ``_capture`` asks first), empty keys (build -1) at first."""
        if not (self._ws_cache_allowed and 0 < n <= self.tuning.ws_cache_max):
            if "off" not in self._ws_cache:
                self._ws_cache["off"] = (0, wp.zeros(1, dtype=wp.vec4, device=self.dev),
                                         wp.zeros(1, dtype=wp.vec4, device=self.dev),
                                         wp.zeros(1, dtype=wp.vec4i, device=self.dev))
            return self._ws_cache["off"]
        cap = self.tuning.ws_capacity_for(n)
        c = self._ws_cache.get(cap)
        if c is None:
            keys = wp.array(np.full((self._cap, 4), -1, np.int32), dtype=wp.vec4i, device=self.dev)
            c = self._ws_cache[cap] = (1, wp.zeros(self._cap * cap, dtype=wp.vec4, device=self.dev),
                                       wp.zeros(self._cap, dtype=wp.vec4, device=self.dev), keys)
        return c

    def _upload_positions(self):
        # the tick's view of the HIP buffer for this batch size, and whether it ticks resident
        # (decided here, when the size is set)
        self._hips_n = self._hips_np[: self.n]
        self._resident_n = self.cuda and self.resident()
        # a tick number skipped: no resident kernel keeps a proxy's position past a reset
        self._tick_no = next_tick(self._tick_no)
        if self.cuda:   # the copying path keeps its positions on the device
            wp.copy(self._dev["positions"], self._host["positions"][0], count=self.n)
        if hasattr(self, "args"):   # (not yet during __init__, which makes them itself)
            self._set_args(self.n)
            self._prepare_resident()

    def _prepare_resident(self):
        """Make both snapshot slots' resident kernels for this batch size now (their buffers and
        streams), so that no tick allocates them; each is launched by its slot's first tick."""
        n = self.n
        if self.resident(n):
            for i in (0, 1):
                r = self._resident[i]
                if r is None or r.n != n:
                    self._new_resident(n, i)

    def block_dim(self, n: int | None = None) -> int:
        """Threads per proxy of a launch for ``n`` proxies (default: the batch's size)."""
        if not self.cuda:
            return 1
        return self._block_dim_request or self.tuning.block_dim_for(self.n if n is None else n)

    def resident(self, n: int | None = None) -> bool:
        """Whether a tick of ``n`` proxies runs on the resident kernel (kernels/warp/resident.py)."""
        return self._resident_allowed and 0 < (self.n if n is None else n) <= resident_max(self.tuning)

    def close(self) -> None:
        """Let this batch's resident kernels go (they free their SMs; the next tick launches
        the one it needs again)."""
        for r in self._resident:
            if r is not None:
                r.stop()

    def zero_copy(self, n: int | None = None) -> bool:
        """Whether a tick of ``n`` proxies reads and writes host memory directly (no copies)."""
        return self.cuda and (self.n if n is None else n) <= self.tuning.zero_copy_max

    def staged(self, n: int | None = None) -> bool:
        """Whether a launched zero-copy tick of ``n`` proxies has its first blocks copy every
        block's inputs into device memory (kernels/warp/tick_inputs.py)."""
        n = self.n if n is None else n
        return self.zero_copy(n) and n >= self.tuning.stage_min

    def _set_args(self, n: int):
        """The batch's kernel constants for ``n`` proxies (``ProxyArgs``: the working-set skin
        depends on the batch size, ``WarpTuning.gather_skin_for``), and the gather radius of the
        tick's arguments with them. A graph or resident kernel holds the constants of its own
        batch size."""
        skin = self.tuning.gather_skin_for(n)
        if self._gather_skin == skin:
            return
        self._gather_skin = skin
        self.args = proxy_args(self.params, self.reach, skin, self._h)
        self.skin = self.args.skin
        if self._tick_dt_set is not None:   # (none yet while __init__ runs)
            self._set_tick(self._tick_dt_set, self._tick_extra)

    def _set_tick(self, dt: float, extra: float):
        tk = self._tick_np[0]
        tk["dt"] = dt
        tk["span"] = search_span(self.reach + extra, self._h)
        # + 1 um: the float32 rounding of the box's corners (cell_of) cannot drop a point
        tk["grad"] = self.reach + self.skin + extra + 1.0e-6
        self._tick_vals = (float(tk["dt"]), int(tk["span"]), float(tk["grad"]))   # (for the resident tick)
        self._tick_dt_set, self._tick_extra = dt, extra

    def _set_build(self, build: int):
        """The snapshot's build number in the tick's arguments (the working-set cache's key),
        written when it changes."""
        if build != self._tick_build:
            self._tick_np[0]["build"] = self._tick_build = build

    # --- the tick --------------------------------------------------------------------------
    def _record(self, slot, n):
        bd = self.block_dim(n)
        t = self.tuning
        kernel = tick_kernel(t.ws_capacity_for(n), t.maxreg_for(bd) if self.cuda else 0, bd)
        if not self.cuda or self.zero_copy(n):
            arr, tick = self._views, self._tick_view
        else:
            arr, tick = self._dev, self._tick
            wp.copy(arr["hips"], self._host["hips"][0], count=n)
            wp.copy(tick, self._tick_host)
        # on CUDA's zero-copy path the first blocks stage the inputs in device memory for all
        staged = int(self.staged(n))
        stage = self._dev if self.cuda else arr
        wp.launch_tiled(kernel, dim=[n], inputs=[slot.sorted_pts, slot.order, slot.start, self.pipeline.grid_args,
                        self.args, arr["positions"], arr["hips"], bd, slot.sorted_vel, tick, arr["normals"],
                        arr["nearest"], arr["states"], arr["steps"], arr["converged"], *self._cache_for(n),
                        staged, n, self._kmax, self._tick4, stage["positions"], stage["hips"], self._dtick,
                        self._sync],
                        block_dim=bd, device=self.dev)
        if self.cuda and not self.zero_copy(n):
            for k in ("positions", "normals", "nearest", "states", "steps", "converged"):
                wp.copy(self._host[k][0], arr[k], count=n)

    def _new_resident(self, n, i):
        """The resident kernel of ``n`` proxies on snapshot slot ``i`` (not launched yet; the
        other slot's is stopped and dropped if its size differs)."""
        for j, r in enumerate(self._resident):
            if r is not None and (j == i or r.n != n):
                r.stop()
                self._resident[j] = None
        bd = self.block_dim(n)
        kernel = tick_kernel(self.tuning.ws_capacity_for(n), self.tuning.maxreg_for(bd), bd, resident=True)
        self._resident[i] = ResidentTick(n, kernel, bd, self.pipeline.buffers.slots[i], dev=self.dev, views=self._views,
                                         grid_args=self.pipeline.grid_args, args=self.args,
                                         device_name=self.pipeline.backend.device_name)
        return self._resident[i]

    def _capture(self, slot, n):
        """The tick's CUDA graph for snapshot slot ``slot`` and ``n`` proxies (captured once)."""
        self._cache_for(n)   # (made before the capture: no allocation inside it)
        with wp.ScopedStream(self.stream):
            wp.capture_begin(device=self.dev, stream=self.stream)
            try:
                self._record(slot, n)
            finally:
                graph = wp.capture_end(device=self.dev, stream=self.stream)
        self._graphs[(id(slot), n)] = graph
        return graph

    def _step(self, hips):
        n = self.n
        if n == 0:
            return
        buf = self.pipeline.buffers
        i = buf.acquire()   # the front slot: no build overwrites it during the tick
        try:
            slot = buf.slots[i]
            if slot.vmax > 0.0:
                dt = self._tick_dt(min(slot.timestamps) if slot.timestamps else 0.0, slot.vmax)
                self._set_tick(dt, extra_span(slot.vmax, dt))
            else:   # nothing moves: dt = 0 (tick_dt), the plain spans
                self.last_dt = 0.0
                if self._tick_dt_set != 0.0:
                    self._set_tick(0.0, 0.0)
            if self._resident_n:
                r = self._resident[i]
                if r is None or r.n != n:
                    r = self._new_resident(n, i)
                self._tick_no = next_tick(self._tick_no)
                r.run(slot.seq, self._tick_vals, hips, self._tick_no)
            elif not self.cuda:
                np.copyto(self._hips_n, hips)
                self._set_build(slot.seq)
                self._record(slot, n)
            else:
                np.copyto(self._hips_n, hips)
                self._set_build(slot.seq)
                last_slot, last_n, graph = self._last
                if last_slot is not slot or last_n != n:
                    graph = self._graphs.get((id(slot), n)) or self._capture(slot, n)
                    self._last = (slot, n, graph)
                wp.capture_launch(graph, stream=self.stream)
                wp.synchronize_stream(self.stream)
        except Exception as e:  # Warp reports CUDA failures as RuntimeError
            raise KernelError(f"Warp proxy kernel failed on {self.pipeline.backend.device_name}: {e}") from e
        finally:
            buf.release(i)
