"""The OpenCL backend object: a context on the chosen device, and on PoCL a second one on its
in-thread device for the haptic tick (``inline``)."""
from __future__ import annotations

import os

from ..backend import Backend
from .context import _cl, inline_device, select_device
from .kernel_shape import check_shape, shape_from_environment


class OpenCLBackend(Backend):
    """pyopencl on PoCL's CPU device by default, or any OpenCL device named by ``device``."""

    name = "opencl"

    def __init__(self, device: str | None = None, inline: bool | None = None, kernel_shape: str | None = None):
        """``inline``: run small proxy batches on PoCL's in-thread device (``context.inline_device``);
        None reads ``POINTFENCE_OPENCL_INLINE`` (default on; "0" turns it off). ``kernel_shape``:
        the proxy, neighbour-query and cell-sort kernels, "auto" (GPU-shaped on GPU devices), "gpu" or "cpu"
        (``kernels/opencl/kernel_shape.py``); None reads ``POINTFENCE_OPENCL_KERNEL_SHAPE``
        (default "auto")."""
        self.kernel_shape = shape_from_environment() if kernel_shape is None else check_shape(kernel_shape)
        cl = self.cl = _cl()
        self.device = select_device(device)
        self.context = cl.Context([self.device])
        if inline is None:
            inline = os.environ.get("POINTFENCE_OPENCL_INLINE", "1").strip() not in ("0", "off", "false", "no")
        self._inline_wanted = bool(inline)
        self._inline = None

    @property
    def inline_context(self):
        """Context on PoCL's in-thread device sharing host memory with ``context``, or None where
        there is none (not PoCL, turned off, or the zero-copy check failed)."""
        if self._inline is None:
            self._inline = False
            dev = inline_device(self.device) if self._inline_wanted else None
            if dev is not None:
                from .shared_host import zero_copy_ok

                ctx = self.cl.Context([dev])
                if zero_copy_ok(self.cl, self.context, ctx):
                    self._inline = ctx
        return self._inline or None

    @property
    def device_name(self) -> str:
        d = self.device
        return f"{d.platform.name.strip()}: {d.name.strip()}"

    def pipeline(self, cameras, params):
        from .pipeline import OpenCLPipeline

        return OpenCLPipeline(self, cameras, params)
