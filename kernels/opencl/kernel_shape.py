"""Which OpenCL proxy and neighbour-query kernels run, and how the GPU-shaped ones are sized.

Two proxy kernels give the same results bit for bit (kernels/opencl/proxy_gpu.cl says how):

* ``"cpu"``: ``proxy_tick`` (proxy.cl), one work-item a proxy running every step of the tick
  over its working set in global memory with 8-wide vector loops: PoCL's CPU devices;
* ``"gpu"``: ``proxy_tick_wg`` (proxy_gpu.cl), one work-group a proxy, its working set in
  local memory, every pass over it spread over the work-group: GPUs (the Warp kernel's shape).

``"auto"`` (the default) takes ``"gpu"`` on devices of type ``CL_DEVICE_TYPE_GPU`` and ``"cpu"``
elsewhere. The choice is an option of ``OpenCLBackend`` (``kernel_shape``; unset, the
``POINTFENCE_OPENCL_KERNEL_SHAPE`` environment variable, read when the backend is made) and of
``pipeline.proxies(..., kernel_shape=...)``.

The same setting picks the neighbour-query kernel (kernels/opencl/neighbor_query.py): ``"cpu"``
runs ``neighbors`` (neighbors.cl, one work-item a query), ``"gpu"`` runs ``neighbors_wg``
(neighbors_gpu.cl, one work-group a query), with the same results bit for bit; and the
snapshot's cell sort (kernels/opencl/cell_sort.py): ``"cpu"`` a counting sort and a per-cell sort,
``"gpu"`` runs of one cell ordered by their heads, the same snapshot entry for entry.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

from ..errors import InputError

SHAPES = ("auto", "cpu", "gpu")
ENVIRONMENT = "POINTFENCE_OPENCL_KERNEL_SHAPE"
#: largest batch size any table needs to cover (a table's last row)
ANY = 1 << 62
#: work-group size limits of proxy_tick_wg: 24 work-items add the lane sums; GW_MAXW in proxy_gpu.cl
MIN_GROUP, MAX_GROUP = 32, 256
#: local memory proxy_tick_wg declares itself (row table, scan, reduction slots, lane sums), bytes,
#: with room to spare
STATIC_LOCAL = 4096
#: bytes of local memory a working-set point and a term-buffer point take
WS_POINT, TERM_POINT = 16, 12


def check_shape(shape, what: str = "kernel_shape") -> str:
    """``shape`` if it is one of ``SHAPES`` (None: "auto"), else an ``InputError``."""
    s = "auto" if shape is None else str(shape).strip().lower()
    if s not in SHAPES:
        raise InputError(f"{what} = {shape!r}; expected one of {', '.join(SHAPES)} "
                         "(auto: the GPU-shaped proxy kernel on GPU devices, the CPU-shaped one elsewhere)")
    return s


def shape_from_environment(environ=None) -> str:
    """The shape ``POINTFENCE_OPENCL_KERNEL_SHAPE`` asks for ("auto" when unset)."""
    environ = os.environ if environ is None else environ
    text = environ.get(ENVIRONMENT, "").strip()
    return check_shape(text or None, ENVIRONMENT)


def resolve_shape(shape: str, device, cl) -> str:
    """"cpu" or "gpu" for ``shape`` on ``device`` ("auto": "gpu" on GPU devices that allow
    work-groups of ``MIN_GROUP``)."""
    s = check_shape(shape)
    fits = device.max_work_group_size >= MIN_GROUP
    if s == "auto":
        return "gpu" if device.type & cl.device_type.GPU and fits else "cpu"
    if s == "gpu" and not fits:
        raise InputError(f"kernel_shape = 'gpu' needs work-groups of {MIN_GROUP} work-items; {device.name.strip()} "
                         f"allows {device.max_work_group_size}: use kernel_shape='cpu'")
    return s


#: work-items a query of the GPU-shaped neighbour kernel by batch size ((largest batch, work-items),
#: ...): a batch that leaves multiprocessors idle spreads each query over many work-items
#: (latency), a large one over fewer so that more queries run at once
NEIGHBOR_GROUPS = ((256, 512), (1024, 256), (ANY, 128))


def neighbor_group_size(n: int, max_group: int, table=NEIGHBOR_GROUPS) -> int:
    """Work-items a query for a batch of ``n`` queries on a device that runs work-groups of at
    most ``max_group`` work-items of the neighbour kernel."""
    return max(1, min(_pick(table, n), max_group))


def _pick(table, n: int) -> int:
    return next(v for most, v in table if n <= most)


@dataclass(frozen=True)
class GroupSizing:
    """Sizes of the GPU-shaped kernel by batch size (results do not depend on them). The
    defaults are the fastest of an H200 sweep at 1,024 and 65,536 proxies (a batch of 1,024 runs
    in one wave: 27 KB of local memory a work-group).

    group_sizes: work-items a proxy ((largest batch, work-items), ...): a small batch spreads
        each proxy over many (latency), a large one over few so that more proxies run at once.
    ws_caps: working-set points a proxy in local memory, wanted, by batch size; trimmed to what
        the device's local memory holds beside the term buffer. A proxy with more points within
        reach + skin scans the hash instead (same results, slower).
    term_points: points of the term buffer the normal sums are taken from (12 bytes a point);
        a larger working set is summed in several rounds.
    """

    group_sizes: tuple = ((4096, 128), (ANY, 64))
    ws_caps: tuple = ((64, 4096), (4096, 1280), (ANY, 1536))
    term_points: int = 256

    def plan(self, n: int, ws_request: int, local_bytes: int, max_group: int) -> tuple:
        """(work-group size, working-set points, term-buffer points) for a batch of ``n``
        proxies, at most ``ws_request`` points a set, on a device with ``local_bytes`` of local
        memory and work-groups of at most ``max_group`` work-items for this kernel."""
        w = min(_pick(self.group_sizes, n), MAX_GROUP, max_group) // 8 * 8
        if w < MIN_GROUP:
            raise InputError(f"the GPU-shaped proxy kernel needs work-groups of {MIN_GROUP} work-items; the device "
                             f"allows {max_group} for it: use kernel_shape='cpu'")
        cap = min(_pick(self.ws_caps, n), ws_request, 64 * w)   # (64: the clip's near bits, one ulong)
        tb = -(-min(self.term_points, max(cap, 8)) // w) * w
        room = (local_bytes - STATIC_LOCAL - TERM_POINT * tb) // WS_POINT
        cap = min(cap, room) // 8 * 8
        if cap < 8:
            raise InputError(f"the device's {local_bytes} bytes of local memory hold no working set for the GPU-shaped "
                             "proxy kernel: use kernel_shape='cpu'")
        return w, cap, tb
