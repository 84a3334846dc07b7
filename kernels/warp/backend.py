"""The Warp backend object: one Warp device (CUDA GPU by default when present, else CPU)."""
from __future__ import annotations

import warp as wp

from ..backend import Backend
from ..errors import BackendUnavailable


class WarpBackend(Backend):
    """NVIDIA Warp on ``device`` ("cuda", "cuda:1", "cpu"; default: the first CUDA GPU, else the CPU)."""

    name = "warp"

    def __init__(self, device: str | None = None):
        wp.config.quiet = True
        wp.init()
        names = [d.alias for d in wp.get_devices()]
        if device in (None, ""):
            device = "cuda:0" if wp.is_cuda_available() else "cpu"
        if device == "cuda":
            device = "cuda:0"
        if device not in names:
            raise BackendUnavailable(f"no Warp device {device!r}; Warp sees {', '.join(names)}")
        self.device = wp.get_device(device)

    @property
    def device_name(self) -> str:
        d = self.device
        return f"Warp {wp.__version__}: {d.alias} ({d.name})"

    def pipeline(self, cameras, params):
        from .pipeline import WarpPipeline

        return WarpPipeline(self, cameras, params)
