"""The interface every depth source implements.

A source owns one ``Camera`` and yields ``DepthFrame`` objects with a frame counter ``seq``
(0, 1, 2, ...) and a timestamp in seconds on the source's own clock. With ``realtime=False``
(the default for synthetic and recorded sources) ``read`` returns the next frame at once, so
tests and benchmarks run as fast as the machine allows. With ``realtime=True`` frame ``seq``
is due ``seq / rate_hz`` seconds after the first read (wall clock, ``time.monotonic``) and
``read`` sleeps until then; a reader that falls more than one period behind gets the latest
due frame, and the frames in between are dropped, as with a live camera.
"""
from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from typing import Iterator, Optional

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError, PointfenceError
from pointfence.kernels.frame import DepthFrame
from pointfence.kernels.yielding import checkpoint


class DepthSource(ABC):
    """A stream of depth frames from one camera.

    Subclasses implement ``_frame(seq)`` (the frame with counter ``seq``, or None at the end of
    a finite stream) and optionally ``_close()``.

    ``clock_domain``: sources whose timestamps come from one shared clock (a synthetic scene's
    cameras, a hardware-synchronised rig) name it alike; None (the default) is a clock of the
    camera's own, whose offset and drift to the service clock the live service estimates
    (service/camera_clock.py).
    """

    clock_domain: Optional[str] = None

    def __init__(self, camera: Camera, rate_hz: float = 30.0, realtime: bool = False):
        if not isinstance(camera, Camera):
            raise InputError(f"camera = {camera!r}; expected a pointfence.kernels.camera.Camera")
        try:
            rate = float(rate_hz)
        except (TypeError, ValueError):
            rate = float("nan")
        if not (math.isfinite(rate) and rate > 0):
            raise InputError(f"rate_hz = {rate_hz!r}; expected a positive frame rate in Hz (e.g. 30)")
        self._camera = camera
        self._rate = rate
        self._realtime = bool(realtime)
        self._seq = 0
        self._t0_wall: Optional[float] = None
        self._closed = False
        self._ended = False

    # -- properties ----------------------------------------------------------------------
    @property
    def camera(self) -> Camera:
        """The camera (intrinsics, pose, noise model) of this source."""
        return self._camera

    @property
    def rate_hz(self) -> float:
        """Nominal frame rate, Hz."""
        return self._rate

    @property
    def realtime(self) -> bool:
        """True when ``read`` paces frames at ``rate_hz`` on the wall clock."""
        return self._realtime

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def ended(self) -> bool:
        """True once a finite stream has delivered its last frame."""
        return self._ended

    # -- reading -------------------------------------------------------------------------
    @abstractmethod
    def _frame(self, seq: int) -> Optional[DepthFrame]:
        """The frame with counter ``seq``, or None when the stream has ended."""

    def _close(self) -> None:
        """Release resources (files, devices). Called once by ``close``."""

    def read(self, timeout: Optional[float] = None) -> Optional[DepthFrame]:
        """The next frame, or None when the stream has ended or ``timeout`` (s) ran out first.

        With ``realtime=True`` this blocks until the next frame is due; otherwise it returns
        immediately and ``timeout`` is ignored.
        """
        if self._closed:
            raise InputError(f"{type(self).__name__} for camera {self._camera.name!r} is closed; open a new source to read again")
        if self._ended:
            return None
        if self._realtime:
            now = time.monotonic()
            if self._t0_wall is None:
                self._t0_wall = now
            due = self._t0_wall + self._seq / self._rate
            if now - due >= 1.0 / self._rate:  # fell behind: skip to the latest due frame
                self._seq = int((now - self._t0_wall) * self._rate)
                due = self._t0_wall + self._seq / self._rate
            wait = due - now
            if wait > 0:
                if timeout is not None and wait > timeout:
                    time.sleep(max(0.0, timeout))
                    return None
                time.sleep(wait)
        checkpoint()     # making the frame is the source's Python: not while a haptic tick is due
        frame = self._frame(self._seq)
        if frame is None:
            self._ended = True
            return None
        self._seq += 1
        return frame

    def threads(self) -> list:
        """The source's own threads that run Python: they take the interpreter lock the haptic
        loop needs, so the live feed raises them with its readers
        (``frames.LiveFrames.set_rt_priority``). None here, nor in the sources pointfence ships
        (a ROS camera's node runs in its bridge process: ros2/camera_bridge.py)."""
        return []

    def __iter__(self) -> Iterator[DepthFrame]:
        return self

    def __next__(self) -> DepthFrame:
        frame = self.read()
        if frame is None:
            raise StopIteration
        return frame

    def close(self) -> None:
        """Stop the source; further reads raise InputError. Safe to call twice."""
        if not self._closed:
            self._closed = True
            self._close()

    def __enter__(self) -> "DepthSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(camera={self._camera.name!r}, rate_hz={self._rate:g}, realtime={self._realtime})"


class LiveSource(DepthSource):
    """A live camera that delivers frames on its own clock (OpenNI2, depthai): ``read()``
    returns the next frame or None when none arrived within its timeout; iterating waits up
    to ``max(5 s, timeout)`` for a frame, then raises an error naming the camera."""

    timeout: float = 1.0

    def _frame(self, seq: int) -> Optional[DepthFrame]:  # not used: read() is overridden
        return self.read()

    def describe(self) -> str:
        """How errors name this camera, e.g. "openni2 camera 'cam0' (test.oni)"."""
        return f"camera {self.camera.name!r}"

    def __next__(self) -> DepthFrame:
        wait = max(5.0, self.timeout)
        deadline = time.monotonic() + wait
        while True:
            frame = self.read()
            if frame is not None:
                return frame
            if self._ended:
                raise StopIteration
            if time.monotonic() > deadline:
                raise PointfenceError(f"{self.describe()} delivered no frame for {wait:.0f} s; check the cable and power")
