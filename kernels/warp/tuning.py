"""Tuning of the Warp backend's kernels: plain values, passed in (``WarpBackend(tuning=...)``,
``pipeline.proxies(..., tuning=...)``), never read at import.

The defaults are the H100 sweeps' choices (bench/HISTORY.md). Two of them are also user-facing
switches documented in README.md ("Backends") and may be overridden from the environment when
a backend is made (``WarpTuning.from_environment``, the one place that reads them):
``POINTFENCE_WARP_RESIDENT_MAX`` (``resident_max``) and ``POINTFENCE_WARP_WS_CACHE_MAX``
(``ws_cache_max``).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace

from ..errors import InputError
from .resident_protocol import RESIDENT_CAP

#: largest batch size any table needs to cover (a table's last row)
ANY = 1 << 62

#: the environment overrides read by ``WarpTuning.from_environment``: variable -> field
ENVIRONMENT = {"POINTFENCE_WARP_RESIDENT_MAX": "resident_max", "POINTFENCE_WARP_WS_CACHE_MAX": "ws_cache_max"}


def _table(name: str, rows, value=int, ok=lambda v: v >= 1, what: str = "value >= 1") -> tuple:
    """A by-batch-size table ((largest batch, value), ...), checked: ascending sizes, the last
    covering every batch, every value converted by ``value`` and passing ``ok`` (``what`` says
    how, in the error; default: positive integers)."""
    try:
        rows = tuple((int(most), value(v)) for most, v in rows)
    except (TypeError, ValueError):
        raise InputError(f"WarpTuning {name} = {rows!r}; expected ((largest batch, {what}), ...)") from None
    sizes = [most for most, _ in rows]
    if not rows or sizes != sorted(set(sizes)) or sizes[-1] < ANY or not all(ok(v) for _, v in rows):
        raise InputError(f"WarpTuning {name} = {rows!r}; expected rows of (largest batch, {what}) by ascending "
                         f"batch size, the last row's size at least {ANY} (every batch)")
    return rows


@dataclass(frozen=True)
class WarpTuning:
    """How the Warp kernels use the device (results do not depend on any of it).

    block_dims: threads per proxy on CUDA (one block each) by batch size, ((largest batch,
        threads), ...). A small batch spreads each proxy over many threads (latency), a large one
        over fewer, so that more blocks run at once (throughput). Warp's CPU device runs one
        thread a block whatever this says.
    block_dim: one block size for every batch instead (None: ``block_dims``); a multiple of 32
        from 32 to 1024.
    maxreg: register cap of the tick kernel for every block size (0: ``maxregs``).
    maxregs: register caps by block size, ((threads, cap), ...): the cap that fits one more block
        an SM than the compiler's choice (about 200 registers a thread), with no spill in the
        step loop (the cold code around it spills a little): 168 for 128 threads (3 blocks an
        SM, against 2), 152 for 32 (13, against 10; shared memory allows 13). Block sizes not
        listed: none up to 256 threads, else the largest that lets a block run (65,536
        registers an SM).
    ws_caps: points of a proxy's working set held in shared memory (16 bytes a point), by batch
        size ((largest batch, points), ...): a small batch has an SM per proxy and takes what
        static shared memory allows (48 KB a block), a large one leaves room for more blocks an
        SM. A proxy with more points within reach + skin scans the hash in global memory.
    zero_copy_max: largest batch whose tick reads and writes pinned host memory directly (no
        copies in the CUDA graph).
    stage_min: smallest zero-copy batch whose first blocks copy every block's inputs into device
        memory (kernels/warp/tick_inputs.py); smaller batches read their own over the bus, where
        few blocks' reads do not queue and the copy's handshake costs 1-5 us more (neutral at 64
        proxies, 7-10 us faster at 128; bench/HISTORY.md, stop 44).
    gather_skins: working-set skin on the GPU by batch size, ((largest batch, m), ...): a proxy
        gathers the points within reach + this (at least HapticParams.skin) and gathers again when
        it has moved further; a set that does not fit in shared memory is gathered with
        HapticParams.skin instead. 2.5 mm up to 64 proxies: a tick that spends its step budget
        gathers again less often (a gather costs about 15,000 cycles, 7 us, of its block), and
        their sets have room for the 12 % more points; 1.5 mm above, where the smaller sets would
        overflow and be counted twice (bench/HISTORY.md, stops 13 and 44).
    gather_skin: one skin for every batch instead (None: ``gather_skins``), m.
    ws_cache_max: largest batch whose launched tick keeps each proxy's working set in device
        memory from tick to tick (``ws_capacity_for(n)`` points a proxy: 25 MB for 1,024
        proxies); 0: never.
    resident_max: largest batch that ticks on the resident kernel on CUDA
        (kernels/warp/resident.py), 0 (never) to ``RESIDENT_CAP``.
    run_pixels: pixels per counting thread of the frame build (one atomic per run of same-cell
        pixels instead of one a pixel).
    query_block_dim: threads per query of the neighbour query on CUDA (one block each,
        kernels/warp/neighbor_query.py), a multiple of 32 from 32 to 1024.
    """

    block_dims: tuple = ((64, 256), (4096, 128), (ANY, 32))
    block_dim: int | None = None
    maxreg: int = 0
    maxregs: tuple = ((32, 152), (128, 168))
    ws_caps: tuple = ((64, 2496), (4096, 1536), (ANY, 768))
    zero_copy_max: int = 4096
    stage_min: int = 64
    gather_skins: tuple = ((64, 2.5e-3), (ANY, 1.5e-3))
    gather_skin: float | None = None
    ws_cache_max: int = 4096
    resident_max: int = 32
    run_pixels: int = 16
    query_block_dim: int = 512

    def __post_init__(self):
        object.__setattr__(self, "block_dims", _table("block_dims", self.block_dims))
        object.__setattr__(self, "ws_caps", _table("ws_caps", self.ws_caps))
        try:
            caps = tuple((int(bd), int(c)) for bd, c in self.maxregs)
        except (TypeError, ValueError):
            caps = None
        if caps is None or any(bd % 32 or not 32 <= bd <= 1024 or not 32 <= c <= 255 for bd, c in caps):
            raise InputError(f"WarpTuning maxregs = {self.maxregs!r}; expected ((threads, cap), ...) with threads a "
                             "multiple of 32 from 32 to 1024 and caps from 32 to 255")
        object.__setattr__(self, "maxregs", caps)
        for _, bd in self.block_dims:
            if bd % 32 or not 32 <= bd <= 1024:
                raise InputError(f"WarpTuning block_dims = {self.block_dims}: {bd} threads; expected multiples "
                                 "of 32 from 32 to 1024")
        q = self.query_block_dim
        if isinstance(q, bool) or not isinstance(q, int) or q % 32 or not 32 <= q <= 1024:
            raise InputError(f"WarpTuning query_block_dim = {q!r}; expected a multiple of 32 from 32 to 1024")
        bd = self.block_dim
        if bd is not None and (isinstance(bd, bool) or not isinstance(bd, int) or bd % 32 or not 32 <= bd <= 1024):
            raise InputError(f"WarpTuning block_dim = {bd!r}; expected None or a multiple of 32 from 32 to 1024")
        for key, hi in (("maxreg", 255), ("zero_copy_max", None), ("stage_min", None), ("ws_cache_max", None),
                        ("resident_max", RESIDENT_CAP), ("run_pixels", None)):
            v = getattr(self, key)
            lo = 1 if key == "run_pixels" else 0
            if isinstance(v, bool) or not isinstance(v, int) or v < lo or (hi is not None and v > hi):
                raise InputError(f"WarpTuning {key} = {v!r}; expected an integer from {lo}"
                                 + (f" to {hi}" if hi is not None else ""))
        g = self.gather_skin
        if g is not None and (isinstance(g, bool) or not isinstance(g, (int, float)) or not math.isfinite(g) or g < 0):
            raise InputError(f"WarpTuning gather_skin = {g!r}; expected None or a finite length >= 0 m")
        object.__setattr__(self, "gather_skins", _table("gather_skins", self.gather_skins, float,
                                                         lambda v: math.isfinite(v) and v >= 0, "skin >= 0 m"))

    @classmethod
    def from_environment(cls, environ=None, base: "WarpTuning | None" = None) -> "WarpTuning":
        """``base`` (default: the defaults) with the documented environment overrides applied
        (``ENVIRONMENT``; ``environ`` default: ``os.environ``). A value that is not an integer in
        range is an ``InputError`` naming the variable."""
        environ = os.environ if environ is None else environ
        t = base or cls()
        for var, key in ENVIRONMENT.items():
            text = environ.get(var, "").strip()
            if not text:
                continue
            try:
                t = replace(t, **{key: int(text)})
            except (ValueError, InputError) as e:
                raise InputError(f"{var} = {text!r}: {e if isinstance(e, InputError) else 'not an integer'}; "
                                 f"unset it or give an integer (README.md, Backends)") from None
        return t

    def block_dim_for(self, n: int) -> int:
        """Threads per proxy for a batch of ``n`` proxies on CUDA."""
        if self.block_dim:
            return self.block_dim
        return next(bd for most, bd in self.block_dims if n <= most)

    def maxreg_for(self, bd: int) -> int:
        """Register cap for blocks of ``bd`` threads (0: none): ``maxreg``, else ``maxregs``' cap
        for this size, else none up to 256 threads and, for larger blocks, the most a block can
        have (the kernel takes about 200 registers a thread uncapped)."""
        if self.maxreg:
            return self.maxreg
        for threads, cap in self.maxregs:
            if threads == bd:
                return cap
        return 0 if bd <= 256 else (65536 // bd) & ~7

    def gather_skin_for(self, n: int) -> float:
        """Working-set skin on the GPU for a batch of ``n`` proxies, m."""
        if self.gather_skin is not None:
            return float(self.gather_skin)
        return next(v for most, v in self.gather_skins if n <= most)

    def ws_capacity_for(self, n: int) -> int:
        """Working-set points in shared memory per proxy for a batch of ``n`` proxies."""
        return next(c for most, c in self.ws_caps if n <= most)
