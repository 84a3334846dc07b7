"""The Warp backend object: one Warp device (CUDA GPU by default when present, else CPU)."""
from __future__ import annotations

import warp as wp

from ..backend import Backend
from ..errors import BackendUnavailable, InputError
from .tuning import WarpTuning


class WarpBackend(Backend):
    """NVIDIA Warp on ``device`` ("cuda", "cuda:1", "cpu"; default: the first CUDA GPU, else the CPU).

    ``tuning``: how its kernels use the device (``WarpTuning``), passed on to every pipeline and
    proxy batch it makes; default: ``WarpTuning.from_environment()``, the defaults with the
    overrides that README.md documents (``POINTFENCE_WARP_RESIDENT_MAX``,
    ``POINTFENCE_WARP_WS_CACHE_MAX``), read here and nowhere else."""

    name = "warp"

    def __init__(self, device: str | None = None, tuning: WarpTuning | None = None):
        if tuning is None:
            tuning = WarpTuning.from_environment()
        elif not isinstance(tuning, WarpTuning):
            raise InputError(f"tuning = {tuning!r}; expected a WarpTuning (pointfence.kernels.warp.tuning)")
        self.tuning = tuning
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
