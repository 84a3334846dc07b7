"""Intel RealSense depth cameras and the RealSense SDK's own recordings, through ``pyrealsense2``.

``realsense:`` opens the first camera attached, ``realsense:<serial>`` the camera with that
serial number (``list_devices()`` or ``rs-enumerate-devices`` print them), and
``realsense:<file.bag | file.db3>`` plays a recording written by the SDK (realsense-viewer,
rs-record, ``rs.recorder``) through the SDK's own playback device, so the same library path
runs as with a camera. Needs ``pip install 'pointfence[realsense]'`` (pyrealsense2 >= 2.55).

What the source reports:

* depth: the Z16 depth stream, uint16 in the sensor's depth units, bit for bit as the SDK
  delivers it; ``depth_scale`` (m per unit) is the depth sensor's ``depth_units`` option;
* intrinsics: the stream profile's (fx, fy, ppx -> cx, ppy -> cy, in pixels, the SDK's float32
  values exactly, pixel centres at integer coordinates as OpenCV's) and its distortion: the
  ``brown_conrady`` model is OpenCV's k1 k2 p1 p2 k3 and becomes ``dist``; other models with
  non-zero coefficients are refused with a hint (``realsense_device.dist_of``);
* timestamps, seconds. A camera is asked for global time (``global_time_enabled``: the SDK
  maps the device's hardware clock onto the host's system clock); frames in the global or
  system time domain are mapped onto the host's ``time.monotonic`` (the time base of the other
  live sources), the system clock's offset from it sampled at each frame, so a step of the
  system clock moves the frames no further than it moves the SDK's own mapping. A camera that
  cannot give global time stamps frames with its hardware clock (``clock == "device"``),
  passed on in seconds. A recording's timestamps are the recorded ones in seconds (ms / 1000,
  in the recorded domain: ``clock == "recorded"``); with ``loop`` each pass continues from the
  last one's time, one frame period later, so timestamps keep increasing.

A recording plays as fast as it is read (``realtime=false``, the default: every recorded frame
is delivered, none dropped; the SDK waits for the reader) or at its recorded pace
(``realtime=true``: the SDK's ``set_real_time``, which drops frames a slow reader misses, as a
camera does). At its end the source ends (``read`` returns None, ``ended`` is True) unless
``loop=true``, which plays it again from its start. A camera delivers its newest frame: one
not read before the next arrives is dropped (``dropped`` counts them).

Options (also as ``realsense:123456?preset=high_accuracy&width=848&height=480&fps=30``): ``name``,
``width``/``height``/``fps`` (the depth mode; a recording offers what it recorded), ``preset`` (a
visual preset of the camera by name: default, hand, high_accuracy, high_density, medium_density,
... as the device names them), ``realtime`` and ``loop`` (recordings), ``timeout`` (s a read waits
for a frame, default 2), ``rate_hz`` (default: the stream's fps), the camera keys ``noise``,
``z_min``, ``z_max``, ``max_code``, ``dist``, and, from Python only, ``device`` (a
``pyrealsense2`` device already open: a ``software_device`` or one of the caller's context).
"""
from __future__ import annotations

import math
import threading
import time
from collections import deque
from typing import Optional

import numpy as np

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError, PointfenceError
from pointfence.kernels.frame import DepthFrame

from . import realsense_device as rsd
from .base import LiveSource

_CAMERA_KEYS = ("noise", "z_min", "z_max", "max_code", "dist")
_OPTIONS = ("name", "width", "height", "fps", "preset", "realtime", "loop", "timeout", "rate_hz", "device")


class FrameHandoff:
    """Frames from the SDK's callback thread to ``read``.

    ``keep_all=True`` (a recording played as fast as read): ``push`` waits for room, so the SDK's
    playback waits for the reader and no frame is lost. ``keep_all=False`` (cameras, real-time
    playback): only the newest frame is kept; an unread older one is dropped and counted. ``close``
    releases a waiting ``push`` (its frame is dropped) so the SDK's stop never waits on the reader.
    """

    def __init__(self, keep_all: bool, capacity: int = 4):
        self.keep_all = bool(keep_all)
        self.capacity = int(capacity) if keep_all else 1
        self.dropped = 0
        self._items: deque = deque()
        self._cond = threading.Condition()
        self._closed = False

    def push(self, item) -> None:
        with self._cond:
            if self.keep_all:
                while len(self._items) >= self.capacity and not self._closed:
                    self._cond.wait(0.1)
            if self._closed:
                self.dropped += 1
                return
            if len(self._items) >= self.capacity:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cond.notify_all()

    def pop(self, timeout: float):
        """The oldest frame kept, waiting up to ``timeout`` s; None when none came."""
        with self._cond:
            if not self._items and timeout > 0:
                self._cond.wait_for(lambda: bool(self._items) or self._closed, timeout)
            if not self._items:
                return None
            item = self._items.popleft()
            self._cond.notify_all()
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def reopen(self) -> None:
        with self._cond:
            self._closed = False


class RealSenseSource(LiveSource):
    """Depth frames from a RealSense camera or SDK recording (see the module docstring)."""

    def __init__(self, target: str = "", camera: Optional[Camera] = None, *, name: Optional[str] = None,
                 width: Optional[int] = None, height: Optional[int] = None, fps: Optional[int] = None,
                 preset: Optional[str] = None, realtime: bool = False, loop: bool = False, timeout: float = 2.0,
                 rate_hz: Optional[float] = None, device=None, **camera_options):
        target = "" if target is None else str(target)
        unknown = sorted(set(camera_options) - set(_CAMERA_KEYS))
        if unknown:
            raise InputError(f"realsense source {target!r}: unknown option(s) {', '.join(unknown)}; it accepts: "
                             + ", ".join(_OPTIONS + _CAMERA_KEYS))
        try:
            self.timeout = float(timeout)
        except (TypeError, ValueError):
            self.timeout = float("nan")
        if not (self.timeout > 0 and math.isfinite(self.timeout)):
            raise InputError(f"realsense source {target!r}: timeout = {timeout!r}; expected seconds > 0")
        for key, v in (("realtime", realtime), ("loop", loop)):
            if not isinstance(v, bool):
                raise InputError(f"realsense source {target!r}: {key} = {v!r}; expected true or false")
        self._rs = rs = rsd.import_realsense()
        self._context = None
        if device is not None and not hasattr(device, "query_sensors"):
            raise InputError(f"realsense source {target!r}: device = {device!r}; expected a pyrealsense2 device "
                             "(a software_device, or one from the caller's rs.context()), or leave it out")
        if device is not None:
            self.is_file = bool(device.is_playback())
            self.target = target or rsd.describe_device(rs, device)
        else:
            self.is_file = rsd.is_recording_target(target)
            self._context = rs.context()
            device = (rsd.load_recording(rs, self._context, target) if self.is_file
                      else rsd.find_device(rs, self._context, target))
            self.target = target if self.is_file else rsd.describe_device(rs, device).split(" ", 1)[0]
        self._device = device
        self._playback = device.as_playback() if self.is_file else None
        where = f"{self.target!r}"
        if self.is_file and preset is not None:
            raise InputError(f"realsense source {where}: preset = {preset!r} applies to a camera; a recording plays "
                             "with the preset it was recorded with. Leave out the preset option")
        if not self.is_file and loop:
            raise InputError(f"realsense source {where}: loop applies to recordings; a camera streams until closed")
        self._sensor, self._profile = rsd.pick_depth_profile(rs, device, where, _int(width, "width", where),
                                                            _int(height, "height", where), _int(fps, "fps", where))
        self.preset = None
        self.global_time = False
        if not self.is_file:
            if preset is not None:
                rsd.apply_preset(rs, self._sensor, preset, where)
                self.preset = rsd.preset_name(preset)
            self.global_time = rsd.enable_global_time(rs, self._sensor)
        depth = self._sensor.as_depth_sensor() if self._sensor.is_depth_sensor() else None
        self.depth_scale = float(depth.get_depth_scale()) if depth is not None else float("nan")
        self.fps = float(self._profile.fps()) or 30.0
        if camera is None:
            camera = rsd.camera_from_profile(rs, self._profile, self.depth_scale, where, name or "cam0", **camera_options)
        else:
            w, h = self._profile.width(), self._profile.height()
            if (camera.width, camera.height) != (w, h):
                raise InputError(f"realsense source {where}: the depth stream is {w}x{h} but camera {camera.name!r} is "
                                 f"{camera.width}x{camera.height}; set the width/height options or fix the [[camera]] entry")
            if math.isfinite(self.depth_scale) and abs(camera.depth_scale - self.depth_scale) > 1e-12:
                raise InputError(f"realsense source {where}: the depth sensor's units are {self.depth_scale} m but camera "
                                 f"{camera.name!r} has depth_scale = {camera.depth_scale}; use {self.depth_scale}")
        super().__init__(camera, rate_hz if rate_hz is not None else self.fps, realtime=False)
        self.device_realtime = bool(realtime) or not self.is_file
        self.loop = bool(loop)
        self.clock = "recorded" if self.is_file else ("host-monotonic" if self.global_time else "device")
        self.last_frame_number: Optional[int] = None
        self.last_domain: Optional[str] = None
        self.passes = 0  # recordings: plays started
        self._t_offset = 0.0
        self._last_ts = -math.inf
        self._pass_frames = 0
        self._handoff = FrameHandoff(keep_all=self.is_file and not realtime)
        self._streaming = False
        try:
            if self._playback is not None:
                self._playback.set_real_time(bool(realtime))
            self._start()
        except BaseException:
            self._release()
            raise

    # -- streaming -----------------------------------------------------------------------
    def _on_frame(self, f) -> None:
        """The SDK's frame callback (its own thread): copy the frame out and hand it over."""
        try:
            depth = np.array(np.asanyarray(f.get_data()), dtype=np.uint16, copy=True)
            item = (depth, float(f.get_timestamp()), rsd.domain_name(f.get_frame_timestamp_domain()),
                    int(f.get_frame_number()))
        except Exception as e:  # noqa: BLE001 - reported by read(), never raised into the SDK's thread
            item = e
        self._handoff.push(item)

    def _start(self) -> None:
        self._handoff.reopen()
        try:
            self._sensor.open(self._profile)
        except RuntimeError as e:
            raise PointfenceError(f"realsense source {self.target!r}: cannot open the depth stream "
                                  f"{rsd.describe_profile(self._profile)} ({e}); is another program using the camera?") from None
        self._sensor.start(self._on_frame)
        if self._playback is not None:
            self._playback.resume()  # a pass after the first: _stop left the playback paused
        self._streaming = True
        self.passes += 1
        self._pass_frames = 0

    def _stop(self) -> None:
        self._handoff.close()  # a callback waiting for room returns, so the SDK's stop cannot wait on us
        if self._streaming:
            self._streaming = False
            if self._playback is not None and self._playback.current_status() == self._rs.playback_status.playing:
                # librealsense (2.59) aborts the process ("pure virtual method called") now and then when
                # a playback stopped mid-play is destroyed; paused first, it is not
                self._playback.pause()
            for step in (self._sensor.stop, self._sensor.close):
                try:
                    step()
                except RuntimeError:
                    pass  # already stopped by the playback's end
            if self._playback is not None:
                # the sensor's stop and close only queue their work on the playback's reading thread;
                # a playback destroyed while that work is pending corrupts the heap now and then
                # (librealsense 2.59: "malloc_consolidate(): unaligned fastbin chunk"). pause() runs
                # on that thread and waits for it, so everything queued before it has run on return
                self._playback.pause()

    @property
    def realtime(self) -> bool:
        """True when reads wait for the device (cameras, recordings played at their recorded pace)."""
        return self.device_realtime

    @property
    def dropped(self) -> int:
        """Frames the SDK delivered that no read took (a newer one replaced them)."""
        return self._handoff.dropped

    def _playback_stopped(self) -> bool:
        return self._playback is not None and self._playback.current_status() == self._rs.playback_status.stopped

    def read(self, timeout: Optional[float] = None) -> Optional[DepthFrame]:
        """The next frame; None when no frame came within ``timeout`` s (default: the ``timeout``
        option) or when a recording without ``loop`` has ended (``ended`` is then True)."""
        if self._closed:
            raise InputError(f"RealSenseSource for camera {self._camera.name!r} is closed; open a new source to read again")
        if self._ended:
            return None
        wait = self.timeout if timeout is None else max(0.0, float(timeout))
        deadline = time.monotonic() + wait
        while True:
            item = self._handoff.pop(max(0.0, min(0.05, deadline - time.monotonic())))
            if item is not None:
                return self._frame_of(item)
            if self._playback_stopped():  # the SDK says stopped only after the last frame's callback returned
                item = self._handoff.pop(0.0)
                if item is not None:
                    return self._frame_of(item)
                if self.loop and self._pass_frames > 0:
                    self._stop()
                    self._start()
                    continue
                self._stop()
                self._ended = True
                return None
            if time.monotonic() >= deadline:
                if not self.is_file and not self._device.is_connected():
                    raise PointfenceError(f"{self.describe()} was disconnected; plug it back in and restart the source")
                return None

    def _frame_of(self, item) -> DepthFrame:
        if isinstance(item, Exception):
            raise PointfenceError(f"{self.describe()}: reading a frame failed ({type(item).__name__}: {item})")
        depth, ts_ms, domain, number = item
        if depth.shape != (self._camera.height, self._camera.width):
            raise PointfenceError(f"{self.describe()}: frame {number} is {depth.shape[1]}x{depth.shape[0]}; expected "
                                  f"{self._camera.width}x{self._camera.height}")
        if self.is_file or domain not in rsd.HOST_DOMAINS:
            t = ts_ms / 1000.0
            if not self.is_file:
                self.clock = "device"
        else:
            t = rsd.host_monotonic(ts_ms)
            self.clock = "host-monotonic"
        if self.is_file and self.loop:
            if t + self._t_offset <= self._last_ts:  # a new pass of a looping recording
                self._t_offset = self._last_ts - t + 1.0 / self.fps
            t += self._t_offset
        self._last_ts = t
        self.last_frame_number, self.last_domain = number, domain
        self._pass_frames += 1
        seq = self._seq
        self._seq += 1
        return DepthFrame(self._camera.name, depth, t, seq)

    def describe(self) -> str:
        kind = "recording" if self.is_file else "camera"
        return f"realsense {kind} {self._camera.name!r} ({self.target})"

    # -- closing -------------------------------------------------------------------------
    def _release(self) -> None:
        handoff = getattr(self, "_handoff", None)
        if handoff is not None and getattr(self, "_streaming", False):
            self._stop()
        self._sensor = self._profile = self._playback = self._device = self._context = None

    def _close(self) -> None:
        self._release()

    def __repr__(self) -> str:
        kind = "recording" if self.is_file else "camera"
        c = self._camera
        return (f"RealSenseSource({self.target!r}, {kind}, camera={c.name!r}, {c.width}x{c.height}@{self.fps:g}, "
                f"depth_scale={self.depth_scale:g}, clock={self.clock})")


def _int(v, key: str, where: str) -> Optional[int]:
    if v is None:
        return None
    if isinstance(v, float) and v.is_integer():
        v = int(v)
    if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
        raise InputError(f"realsense source {where}: {key} = {v!r}; expected a positive integer")
    return v


def list_devices() -> list:
    """Readable descriptions (serial, name, firmware) of the RealSense cameras attached now."""
    return rsd.list_devices()
