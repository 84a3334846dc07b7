"""The OpenCL backend object: one context on the chosen device."""
from __future__ import annotations

from ..backend import Backend
from .context import _cl, select_device


class OpenCLBackend(Backend):
    """pyopencl on PoCL's CPU device by default, or any OpenCL device named by ``device``."""

    name = "opencl"

    def __init__(self, device: str | None = None):
        cl = _cl()
        self.device = select_device(device)
        self.context = cl.Context([self.device])

    @property
    def device_name(self) -> str:
        d = self.device
        return f"{d.platform.name.strip()}: {d.name.strip()}"

    def pipeline(self, cameras, params):
        from .pipeline import OpenCLPipeline

        return OpenCLPipeline(self, cameras, params)
