"""Host arrays that two OpenCL contexts on the same CPU share without copies.

PoCL's CPU devices compute directly in the host memory of a buffer created with
``CL_MEM_USE_HOST_PTR``. The frame pipeline builds a snapshot on PoCL's worker pool (``pthread``
device) into such arrays, and the haptic tick reads the same arrays through buffers of a second
context on PoCL's in-thread ``basic`` device. OpenCL does not promise this across contexts, so
``zero_copy_ok`` checks it on the devices at hand before the pipeline relies on it.
"""
from __future__ import annotations

import numpy as np

from ..errors import KernelError
from .context import build_source

PAGE = 4096

_CHECK_SRC = """
__kernel void copy_add(__global const int *a, __global int *b, int k) { int i = get_global_id(0); b[i] = a[i] + k; }
"""


def aligned_zeros(nbytes: int, dtype=np.float32, shape=None) -> np.ndarray:
    """Zeroed array of at least ``nbytes`` (>= 1 element) starting on a page boundary."""
    item = np.dtype(dtype).itemsize
    n = max(1, -(-int(nbytes) // item))
    raw = np.zeros(n * item + PAGE, np.uint8)
    off = (-raw.ctypes.data) % PAGE
    a = raw[off:off + n * item].view(dtype)
    return a if shape is None else a.reshape(shape)


def host_buffer(cl, ctx, array: np.ndarray, read_only: bool = False):
    mf = cl.mem_flags
    return cl.Buffer(ctx, (mf.READ_ONLY if read_only else mf.READ_WRITE) | mf.USE_HOST_PTR, hostbuf=array)


def zero_copy_ok(cl, ctx_a, ctx_b) -> bool:
    """Whether a kernel of either context sees what a kernel of the other wrote into a shared
    host array, and the host sees what both wrote, with no transfer enqueued: a then b, and b
    then a (one build of the check kernel per context)."""
    n = 4096
    try:
        ka = cl.Kernel(build_source(ctx_a, _CHECK_SRC, "copy_add"), "copy_add")
        kb = cl.Kernel(build_source(ctx_b, _CHECK_SRC, "copy_add"), "copy_add")
        for (cw, kw), (cr, kr) in (((ctx_a, ka), (ctx_b, kb)), ((ctx_b, kb), (ctx_a, ka))):
            a = aligned_zeros(4 * n, np.int32)
            b = aligned_zeros(4 * n, np.int32)
            c = aligned_zeros(4 * n, np.int32)
            a[:] = np.arange(n, dtype=np.int32)
            qw, qr = cl.CommandQueue(cw), cl.CommandQueue(cr)
            aw, bw = host_buffer(cl, cw, a), host_buffer(cl, cw, b)
            br, cbuf = host_buffer(cl, cr, b), host_buffer(cl, cr, c)
            for k in (1, 7):
                kw(qw, (n,), None, aw, bw, np.int32(k))
                qw.finish()
                kr(qr, (n,), None, br, cbuf, np.int32(k))
                qr.finish()
                if not (np.array_equal(b, a + k) and np.array_equal(c, a + 2 * k)):
                    return False
    except (cl.Error, KernelError):   # the check kernel does not build or run: no sharing
        return False
    return True
