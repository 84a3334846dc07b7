"""One reader thread per camera, each at its own rate, with staleness reporting.

``CameraReader(source)`` reads ``source`` on its own daemon thread and keeps the newest frame;
the consumer (the frame pipeline) takes it with ``latest()`` without ever waiting on a camera.
A camera is *stale* when its newest frame is older than ``stale_after`` seconds (default: 3
frame periods at the source's rate, at least 0.1 s) on the host clock, when its stream ended,
or when its reader stopped on an error; ``status()`` says which and since when.

``CameraRig(sources)`` runs one reader per source and reports them together::

    with CameraRig(config.open_sources()) as rig:
        frames = rig.latest()          # {camera name: newest DepthFrame}
        for name, why in rig.stale().items():
            log.warning("camera %s is stale: %s", name, why)
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterable, Optional

from pointfence.kernels.errors import InputError
from pointfence.kernels.frame import DepthFrame
from pointfence.kernels.yielding import checkpoint

from ..osthread import name_this_thread
from .base import DepthSource


@dataclass(frozen=True)
class ReaderStatus:
    """What a reader knows about its camera at one instant."""

    camera: str
    frames: int  # frames received so far
    age: float  # seconds since the newest frame arrived (inf before the first)
    rate_hz: float  # measured arrival rate over the last frames (0 before two frames)
    stale: bool
    reason: str  # "" when fresh; otherwise why it is stale
    error: Optional[str] = None


class CameraReader:
    """Reads one ``DepthSource`` on its own thread (see the module docstring).

    Args:
        source: the camera.
        stale_after: seconds without a new frame after which the camera is stale.
        on_frame: optional callback ``f(frame)`` run on the reader thread for every frame.
        poll: seconds one ``read`` may block, so ``stop`` is noticed quickly.
        clock: host clock (``time.monotonic``), replaceable in tests.
    """

    def __init__(self, source: DepthSource, stale_after: Optional[float] = None,
                 on_frame: Optional[Callable[[DepthFrame], None]] = None, poll: float = 0.1,
                 clock: Callable[[], float] = time.monotonic):
        if not isinstance(source, DepthSource):
            raise InputError(f"CameraReader: source = {source!r}; expected a DepthSource (see pointfence.service.sources.open_source)")
        if stale_after is None:
            stale_after = max(0.1, 3.0 / source.rate_hz)
        if not (isinstance(stale_after, (int, float)) and math.isfinite(stale_after) and stale_after > 0):
            raise InputError(f"CameraReader {source.camera.name!r}: stale_after = {stale_after!r}; expected seconds > 0")
        self.source = source
        self.name = source.camera.name
        self.stale_after = float(stale_after)
        self.on_frame = on_frame
        self.poll = float(poll)
        self._clock = clock
        self._lock = threading.Lock()
        self._new = threading.Condition(self._lock)
        self._frame: Optional[DepthFrame] = None
        self._arrived = -math.inf
        self._arrivals: list = []
        self._count = 0
        self._error: Optional[str] = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"camera-{self.name}", daemon=True)

    # -- thread --------------------------------------------------------------------------
    def start(self) -> "CameraReader":
        self._thread.start()
        return self

    def _run(self) -> None:
        name_this_thread(f"pf-cam-{self.name}")
        src = self.source
        try:
            while not self._stop.is_set():
                frame = src.read(timeout=self.poll) if src.realtime else src.read()
                if frame is None:
                    if src.ended:
                        break
                    continue
                now = self._clock()
                # the frame's bookkeeping and ``on_frame`` (the camera's clock fit) are Python that
                # holds the interpreter lock: step aside while a tick of the haptic loop runs or
                # is about to (kernels/yielding.py; a no-op without the loop's gate)
                checkpoint()
                with self._new:
                    self._frame = frame
                    self._arrived = now
                    self._count += 1
                    self._arrivals = (self._arrivals + [now])[-16:]
                    self._new.notify_all()
                if self.on_frame is not None:
                    self.on_frame(frame)
                if not src.realtime:  # a file or synthetic source: pace it at its rate here
                    self._stop.wait(1.0 / src.rate_hz)
        except Exception as e:  # reported through status(); the other cameras go on
            with self._new:
                self._error = f"{type(e).__name__}: {e}"
                self._new.notify_all()

    def stop(self, close: bool = True, timeout: float = 2.0) -> None:
        """Stop the thread (and close the source unless ``close=False``)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout)
        if close:
            self.source.close()

    # -- consumer side -------------------------------------------------------------------
    def latest(self) -> Optional[DepthFrame]:
        """The newest frame (None before the first); never blocks on the camera."""
        with self._lock:
            return self._frame

    def wait(self, after: int = 0, timeout: Optional[float] = None) -> Optional[DepthFrame]:
        """Block until more than ``after`` frames have arrived (or ``timeout`` s); the newest frame."""
        with self._new:
            self._new.wait_for(lambda: self._count > after or self._error is not None or not self._thread.is_alive(), timeout)
            return self._frame

    def status(self) -> ReaderStatus:
        now = self._clock()
        with self._lock:
            count, arrived, arrivals, error = self._count, self._arrived, list(self._arrivals), self._error
        age = now - arrived if count else math.inf
        rate = (len(arrivals) - 1) / (arrivals[-1] - arrivals[0]) if len(arrivals) > 1 and arrivals[-1] > arrivals[0] else 0.0
        reason = ""
        if error is not None:
            reason = f"reader stopped: {error}"
        elif self.source.ended:
            reason = "stream ended"
        elif not self._thread.is_alive() and self._stop.is_set():
            reason = "reader stopped"
        elif age > self.stale_after:
            reason = ("no frame yet" if not count else f"no new frame for {age:.2f} s") + f" (stale after {self.stale_after:.2f} s)"
            problem = getattr(self.source, "problem", None)   # a source that rejects bad input says why
            if problem:
                reason += f": {problem}"
        return ReaderStatus(self.name, count, age, rate, bool(reason), reason, error)

    @property
    def stale(self) -> bool:
        return self.status().stale


class CameraRig:
    """One ``CameraReader`` per source; names must be unique."""

    def __init__(self, sources: Iterable[DepthSource], stale_after: Optional[float] = None, **reader_options):
        sources = list(sources)
        names = [s.camera.name for s in sources]
        if len(set(names)) != len(names):
            raise InputError(f"CameraRig: camera names {names}; expected unique names")
        self.readers = {s.camera.name: CameraReader(s, stale_after, **reader_options) for s in sources}

    def start(self) -> "CameraRig":
        for r in self.readers.values():
            r.start()
        return self

    def stop(self, close: bool = True) -> None:
        for r in self.readers.values():
            r.stop(close=close)

    def latest(self) -> dict:
        """{camera name: newest frame} of the cameras that delivered one."""
        out = {}
        for name, r in self.readers.items():
            f = r.latest()
            if f is not None:
                out[name] = f
        return out

    def status(self) -> dict:
        return {name: r.status() for name, r in self.readers.items()}

    def stale(self) -> dict:
        """{camera name: reason} of the stale cameras (empty when all are fresh)."""
        return {name: s.reason for name, s in self.status().items() if s.stale}

    def __enter__(self) -> "CameraRig":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
