"""Pre-rendered camera frames played in a loop, in real time.

Rendering a 640x480 synthetic frame takes tens of milliseconds of NumPy that mostly holds the
GIL, which a live haptic loop in the same process feels as milliseconds of lateness; a real
camera's driver (OpenNI2, depthai) delivers frames from C without that cost. ``CannedSource``
renders ``n_frames`` frames of a source once, up front, and then serves frame ``seq`` as the
source's frame ``seq % n_frames`` (keeping that frame's own ``seq``, so a recording names frames
the original source can render again), paced at the source's rate like a live camera. For a
static scene 30 frames give a second of independent noise; for a periodic scene use one period.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Optional

from pointfence.kernels.errors import InputError
from pointfence.kernels.frame import DepthFrame

from .sources.base import DepthSource


class CannedSource(DepthSource):
    """``n_frames`` frames of ``source`` read once, then served at its rate (frame ``seq`` has
    timestamp ``seq / rate_hz``: every canned camera stamps on one clock)."""

    clock_domain = "canned"

    def __init__(self, source: DepthSource, n_frames: int = 30, realtime: bool = True):
        if n_frames < 1:
            raise InputError(f"n_frames = {n_frames!r}; expected >= 1")
        super().__init__(source.camera, source.rate_hz, realtime)
        self.source = source
        self.frames = []
        for _ in range(int(n_frames)):
            f = source.read()
            if f is None:
                break
            self.frames.append(f)
        if not self.frames:
            raise InputError(f"{source!r} delivered no frame to pre-render")
        self.scene = getattr(source, "scene", None)   # ground truth for the measures, if synthetic

    def _frame(self, seq: int) -> Optional[DepthFrame]:
        f = self.frames[seq % len(self.frames)]
        return replace(f, timestamp=seq / self.rate_hz)

    def _close(self) -> None:
        self.source.close()


def canned_sources(cfg, n_frames: int = 30, cache: Optional[dict] = None) -> list:
    """``cfg``'s cameras as ``CannedSource`` objects (pre-rendered, served in real time).
    ``cache`` (a dict) reuses frames rendered for the same camera and source spec."""
    return [_canned(cfg, c, n_frames, cache) for c in cfg.cameras]


def live_sources(cfg, prerender: int = 0) -> list:
    """``cfg``'s cameras opened for a live run; with ``prerender`` > 0 the synthetic ones are
    ``CannedSource`` objects of that many frames (their rendering would otherwise hold the
    interpreter lock of the haptic loop's process), every other source as it is."""
    return [_canned(cfg, c, prerender) if prerender > 0 and str(c.source).startswith("synthetic:")
            else cfg.open_source(c, realtime=True) for c in cfg.cameras]


def _canned(cfg, c, n_frames: int, cache: Optional[dict] = None) -> CannedSource:
    """Camera entry ``c`` of ``cfg`` pre-rendered (see ``canned_sources`` for ``cache``)."""
    key = (c.camera.name, c.source, repr(sorted(c.options.items())), n_frames)
    if cache is not None and key in cache:
        src = CannedSource.__new__(CannedSource)
        DepthSource.__init__(src, c.camera, c.rate_hz, True)
        proto = cache[key]
        src.source, src.frames, src.scene = proto.source, proto.frames, proto.scene
        return src
    src = CannedSource(cfg.open_source(c), n_frames)
    if cache is not None:
        cache[key] = src
    return src
