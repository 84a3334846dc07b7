"""OpenNI2 depth cameras (Kinect v1, PrimeSense Carmine, Asus Xtion, ...) and ``.oni`` recordings.

``openni2:<uri>`` opens a live device (``openni2:any`` or ``openni2:`` + a device URI from
``list_devices()``); ``openni2:<file.oni>`` plays a recording through OpenNI2's own file driver,
so the same library code path runs as with a camera. Needs the OpenNI2 runtime
(Debian/Ubuntu: ``apt-get install libopenni2-0``) and its Python bindings (``pip install openni``).

What the source reports:

* depth: uint16 in the stream's units (``PIXEL_FORMAT_DEPTH_1_MM`` -> ``depth_scale`` 0.001,
  ``DEPTH_100_UM`` -> 0.0001);
* timestamps: the device's frame timestamp (microseconds) in seconds; a looping recording keeps
  its timestamps increasing across loops;
* intrinsics: PrimeSense devices report the zero-plane distance and pixel size of their depth
  sensor, which give the focal length (fx = fy = ZPD / (2 ZPPS) at 640 px width); otherwise the
  stream's field of view gives it (fx = W / (2 tan(hfov / 2))). The principal point is the image
  centre (W / 2, H / 2), as OpenNI2's CoordinateConverter assumes. With
  ``registration="depth_to_color"`` the depth image is warped into the colour camera, whose field
  of view then sets the intrinsics;
* mirroring: off. A recording made with mirroring on (it says so in its stream properties) is
  flipped back in software, so the geometry is right (``unmirror=false`` keeps it as recorded).

Options (also as ``openni2:file.oni?loop=false&color=true``): ``name``, ``rate_hz``, ``realtime``
(recordings: play at recorded speed; default False = each read returns the next recorded frame
at once), ``loop`` (recordings; default True), ``registration`` ("off", "depth_to_color" or None
= leave the device's setting), ``color`` (also read the RGB stream when it matches the depth
size), ``width``/``height``/``fps`` (live: pick that depth video mode), ``timeout`` (s a read
waits for a frame, default 2), ``redist`` (folder holding libOpenNI2.so), ``unmirror``, and the camera keys
``noise``, ``z_min``, ``z_max``, ``dist``, ``max_code``.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import math
import os
import threading
from pathlib import Path
from typing import Optional

import numpy as np

from pointfence.kernels.camera import Camera, NoiseModel
from pointfence.kernels.errors import InputError, PointfenceError
from pointfence.kernels.frame import DepthFrame

from .base import LiveSource

INSTALL_HINT = (
    "install the OpenNI2 runtime (Debian/Ubuntu: `sudo apt-get install libopenni2-0`; elsewhere the "
    "OpenNI 2.2 SDK, then set OPENNI2_REDIST to the folder that holds libOpenNI2.so) and its Python "
    "bindings (`pip install openni`)"
)
#: PS1080 driver stream properties (PS1080.h): zero-plane distance (mm) and pixel size (mm, at 1280 px).
PS1080_ZERO_PLANE_DISTANCE = 0x1080100C
PS1080_ZERO_PLANE_PIXEL_SIZE = 0x1080100D
#: OpenNI2 playback speed that makes each readFrame deliver the next recorded frame.
PLAYBACK_MANUAL = -1.0
_CAMERA_KEYS = ("noise", "z_min", "z_max", "dist", "max_code")
_SYSTEM_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib/arm-linux-gnueabihf",
                "/usr/lib", "/usr/local/lib", "/lib", "/lib64", "/usr/lib/OpenNI2", "/opt/OpenNI2/Redist")
_LIB_NAMES = ("libOpenNI2.so", "libOpenNI2.so.0", "libOpenNI2.dylib", "OpenNI2.dll")

_lock = threading.Lock()
_loaded_from: Optional[str] = None


class OpenNI2Unavailable(PointfenceError, RuntimeError):
    """The OpenNI2 runtime or its Python bindings are not installed (the message says how to install them)."""


def _bindings():
    try:
        from openni import _openni2 as c_api
        from openni import openni2
    except ImportError as e:
        raise OpenNI2Unavailable(f"the OpenNI2 Python bindings are not importable ({e}); {INSTALL_HINT}") from None
    return openni2, c_api


def library_candidates(redist: Optional[str] = None) -> list:
    """Paths (or sonames) tried, in order, to load the OpenNI2 runtime."""
    dirs = []
    if redist:
        dirs.append(str(redist))
    else:
        for var in ("OPENNI2_REDIST64", "OPENNI2_REDIST"):
            if os.environ.get(var):
                dirs.append(os.environ[var])
        dirs.extend(_SYSTEM_DIRS)
    out = [str(Path(d) / n) for d in dirs for n in _LIB_NAMES if (Path(d) / n).is_file()]
    if not redist:
        found = ctypes.util.find_library("OpenNI2")
        if found:
            out.append(found)
    return out


def load_openni2(redist: Optional[str] = None):
    """Load and initialise the OpenNI2 runtime once per process; returns the ``openni2`` module.

    ``redist``: a folder holding libOpenNI2.so (default: $OPENNI2_REDIST64, $OPENNI2_REDIST, the
    system library folders). Raises OpenNI2Unavailable, saying how to install, when it is missing.
    """
    global _loaded_from
    openni2, c_api = _bindings()
    with _lock:
        if _loaded_from is None and getattr(openni2, "loaded_dll_directory", None):
            _loaded_from = str(openni2.loaded_dll_directory)  # someone else initialised it
        if _loaded_from is None:
            tried = []
            for cand in library_candidates(redist):
                try:
                    c_api.load_dll(cand)
                except OSError as e:
                    tried.append(f"{cand}: {e}")
                    continue
                _loaded_from = cand
                openni2.loaded_dll_directory = os.path.dirname(cand) or "."
                break
            if _loaded_from is None:
                where = f"in {redist!r}" if redist else "in $OPENNI2_REDIST or the system library folders"
                detail = ("; tried " + "; ".join(tried)) if tried else ""
                raise OpenNI2Unavailable(f"the OpenNI2 runtime (libOpenNI2.so) was not found {where}{detail}; {INSTALL_HINT}")
        if not openni2.is_initialized():
            openni2.initialize()
    return openni2


def list_devices(redist: Optional[str] = None) -> list:
    """URIs (str) of the OpenNI2 devices attached now."""
    load_openni2(redist)  # initialises the library
    c_api = _bindings()[1]
    pdevs = ctypes.POINTER(c_api.OniDeviceInfo)()
    count = ctypes.c_int()
    c_api.oniGetDeviceList(ctypes.byref(pdevs), ctypes.byref(count))
    try:
        return [pdevs[i].uri.decode(errors="replace") for i in range(count.value)]
    finally:
        c_api.oniReleaseDeviceList(pdevs)


def _is_file_target(target: str) -> bool:
    return target.lower().endswith(".oni") or Path(target).is_file()


def focal_from_fov(size_px: int, fov_rad: float) -> float:
    """Pinhole focal length (px) of an image ``size_px`` wide spanning ``fov_rad``."""
    return size_px / (2.0 * math.tan(fov_rad / 2.0))


def focal_from_zero_plane(zpd_mm: float, zpps_mm: float, width: int) -> float:
    """PrimeSense depth focal length (px) at image ``width`` from the zero-plane distance and the
    zero-plane pixel size (given at 1280 px, so doubled at 640 px)."""
    return zpd_mm / (zpps_mm * 1280.0 / width)


def depth_scale_of(pixel_format) -> float:
    """Metres per depth unit of an OpenNI2 depth pixel format."""
    name = str(getattr(pixel_format, "name", pixel_format)).upper()
    if name.endswith("DEPTH_1_MM"):
        return 0.001
    if name.endswith("DEPTH_100_UM"):
        return 0.0001
    raise InputError(f"OpenNI2 depth pixel format {name}; expected DEPTH_1_MM or DEPTH_100_UM "
                     "(shift formats are raw disparity: pick a depth video mode with width/height/fps)")


class OpenNI2Source(LiveSource):
    """Depth frames from an OpenNI2 device or ``.oni`` recording (see the module docstring)."""

    def __init__(self, target: str = "any", camera: Optional[Camera] = None, *, name: Optional[str] = None,
                 rate_hz: Optional[float] = None, realtime: bool = False, loop: bool = True,
                 registration: Optional[str] = None, color: bool = False, width: Optional[int] = None,
                 height: Optional[int] = None, fps: Optional[int] = None, timeout: float = 2.0,
                 redist: Optional[str] = None, unmirror: bool = True, **camera_options):
        unknown = sorted(set(camera_options) - set(_CAMERA_KEYS))
        if unknown:
            raise InputError(f"openni2 source {target!r}: unknown option(s) {', '.join(unknown)}; it accepts: name, rate_hz, "
                             "realtime, loop, registration, color, width, height, fps, timeout, redist, unmirror, " + ", ".join(_CAMERA_KEYS))
        if registration not in (None, "off", "depth_to_color"):
            raise InputError(f"openni2 source {target!r}: registration = {registration!r}; expected 'off', 'depth_to_color' "
                             "or none (leave the device's setting)")
        try:
            self.timeout = float(timeout)
        except (TypeError, ValueError):
            self.timeout = float("nan")
        if not (self.timeout > 0 and math.isfinite(self.timeout)):
            raise InputError(f"openni2 source {target!r}: timeout = {timeout!r}; expected seconds > 0")
        target = str(target or "any")
        self.target = target
        self.is_file = _is_file_target(target)
        if self.is_file and not Path(target).is_file():
            raise InputError(f"openni2 source: recording {target!r} not found; pass an existing .oni file or a device URI "
                             "(openni2:any for the first attached camera)")
        self._openni2 = load_openni2(redist)
        self._device = self._depth = self._color = None
        try:
            self._open(target, registration, color, width, height, fps, realtime, loop)
            self.software_unmirror = self.software_unmirror and bool(unmirror)
            mode = self._depth.get_video_mode()
            w, h = int(mode.resolutionX), int(mode.resolutionY)
            self.depth_scale = depth_scale_of(mode.pixelFormat)
            self.fps = float(mode.fps) if mode.fps else 30.0
            self.intrinsics_source, (fx, fy, cx, cy) = self._intrinsics(w, h)
            if camera is None:
                cam_kw = dict(camera_options)
                if "noise" in cam_kw and not isinstance(cam_kw["noise"], NoiseModel):
                    cam_kw["noise"] = NoiseModel(**cam_kw["noise"]) if isinstance(cam_kw["noise"], dict) else NoiseModel(*cam_kw["noise"])
                camera = Camera(name or "cam0", w, h, fx, fy, cx, cy, depth_scale=self.depth_scale, **cam_kw)
            elif (camera.width, camera.height) != (w, h):
                raise InputError(f"openni2 source {target!r}: the device streams {w}x{h} depth but camera {camera.name!r} is "
                                 f"{camera.width}x{camera.height}; set width/height options or fix the camera entry")
            elif abs(camera.depth_scale - self.depth_scale) > 1e-12:
                raise InputError(f"openni2 source {target!r}: the stream's units are {self.depth_scale} m but camera "
                                 f"{camera.name!r} has depth_scale = {camera.depth_scale}; use {self.depth_scale}")
            super().__init__(camera, rate_hz if rate_hz is not None else self.fps, realtime=False)
        except BaseException:
            self._release()
            raise
        self.device_realtime = bool(realtime) or not self.is_file
        self.loop = bool(loop)
        self._t_offset = 0.0
        self._last_ts = -math.inf
        self._count = 0

    # -- opening -------------------------------------------------------------------------
    def _open(self, target, registration, color, width, height, fps, realtime, loop):
        o = self._openni2
        try:
            if self.is_file:
                self._device = o.Device.open_file(os.fsencode(target))
            elif target in ("any", "*", ""):
                # OpenNI2 lists recordings opened earlier in this process as devices: skip them.
                live = [u for u in list_devices() if not _is_file_target(u)]
                if not live:
                    raise InputError("openni2 source: no OpenNI2 camera attached (devices attached: none). Plug the camera in, "
                                     "check USB permissions (udev rules of libopenni2-0), or pass a .oni recording")
                self.target = target = live[0]
                self._device = o.Device.open_file(target.encode())
            else:
                self._device = o.Device.open_file(target.encode())  # a device URI opens like a file name
        except InputError:
            raise
        except Exception as e:  # OpenNIError: no such device
            if self.is_file:
                raise InputError(f"openni2 source: OpenNI2 cannot play {target!r} ({e}); expected an OpenNI .oni recording") from None
            try:
                found = list_devices()
            except Exception:
                found = []
            listing = ", ".join(found) if found else "none"
            raise InputError(f"openni2 source: cannot open device {target!r} ({e}); devices attached: {listing}. "
                             "Plug the camera in, check USB permissions (udev rules of libopenni2-0), or pass a .oni file") from None
        dev = self._device
        if not dev.has_sensor(o.SENSOR_DEPTH):
            raise InputError(f"openni2 source {target!r}: the device has no depth sensor")
        if self.is_file:
            pb = dev.playback
            pb.set_speed(1.0 if realtime else PLAYBACK_MANUAL)
            pb.set_repeat_enabled(bool(loop))
            self.frames_in_file = None
        self._depth = dev.create_depth_stream()
        if self.is_file:
            self.frames_in_file = int(dev.playback.get_number_of_frames(self._depth))
        if not self.is_file and (width or height or fps):
            self._set_mode(width, height, fps)
        self.registration = "off"
        if registration is not None:
            mode = o.IMAGE_REGISTRATION_DEPTH_TO_COLOR if registration == "depth_to_color" else o.IMAGE_REGISTRATION_OFF
            if registration == "depth_to_color" and not dev.is_image_registration_mode_supported(mode):
                raise InputError(f"openni2 source {target!r}: the device does not support registration = 'depth_to_color' "
                                 "(recordings keep the registration they were made with); use registration = 'off'")
            try:
                dev.set_image_registration_mode(mode)
            except Exception as e:
                if registration == "depth_to_color":
                    raise InputError(f"openni2 source {target!r}: setting registration failed ({e}); use registration = 'off'") from None
            self.registration = registration
        else:
            try:
                reg = dev.get_image_registration_mode()
                self.registration = "depth_to_color" if reg == o.IMAGE_REGISTRATION_DEPTH_TO_COLOR else "off"
            except Exception:
                self.registration = "off"
        self.software_unmirror = False
        try:
            self._depth.set_mirroring_enabled(False)
        except Exception:
            pass
        try:
            self.software_unmirror = bool(self._depth.get_mirroring_enabled())
        except Exception:
            self.software_unmirror = False
        self._want_color = bool(color) and dev.has_sensor(o.SENSOR_COLOR)
        if self._want_color:
            self._color = dev.create_color_stream()
            try:
                self._color.set_mirroring_enabled(False)
            except Exception:
                pass
            self._color.start()
        self._depth.start()

    def _set_mode(self, width, height, fps):
        modes = self._depth.get_sensor_info().videoModes
        fmt_ok = [m for m in modes if str(m.pixelFormat).upper().endswith(("DEPTH_1_MM", "DEPTH_100_UM"))]
        pick = [m for m in fmt_ok if (width is None or m.resolutionX == int(width)) and (height is None or m.resolutionY == int(height))
                and (fps is None or m.fps == int(fps))]
        if not pick:
            have = ", ".join(sorted({f"{m.resolutionX}x{m.resolutionY}@{m.fps}" for m in fmt_ok}))
            raise InputError(f"openni2 source {self.target!r}: no depth mode {width}x{height}@{fps}; the device offers {have}")
        self._depth.set_video_mode(pick[0])

    def _stream_prop(self, pid, ctype):
        try:
            return self._depth.get_property(pid, ctype).value
        except Exception:
            return None

    def _intrinsics(self, w: int, h: int):
        """(how, (fx, fy, cx, cy)) of the depth image as streamed."""
        cx, cy = w / 2.0, h / 2.0
        if self.registration != "depth_to_color":
            zpd = self._stream_prop(PS1080_ZERO_PLANE_DISTANCE, ctypes.c_uint64)
            zpps = self._stream_prop(PS1080_ZERO_PLANE_PIXEL_SIZE, ctypes.c_double)
            if zpd and zpps and zpd > 0 and zpps > 0:
                f = focal_from_zero_plane(float(zpd), float(zpps), w)
                return "zero-plane", (f, f, cx, cy)
        stream = self._depth
        if self.registration == "depth_to_color":
            stream = self._color or self._device.create_color_stream()
        try:
            hfov, vfov = float(stream.get_horizontal_fov()), float(stream.get_vertical_fov())
        except Exception:
            hfov = vfov = float("nan")
        if not (0 < hfov < math.pi and 0 < vfov < math.pi):
            raise InputError(f"openni2 source {self.target!r}: the device reports neither its focal length nor its field of view; "
                             "give fx, fy, cx, cy in the [[camera]] entry (see `pointfence calib intrinsics`)")
        return "field-of-view", (focal_from_fov(w, hfov), focal_from_fov(h, vfov), cx, cy)

    # -- reading -------------------------------------------------------------------------
    @property
    def realtime(self) -> bool:
        """True when reads wait for the device (live cameras, recordings at recorded speed)."""
        return self.device_realtime

    def read(self, timeout: Optional[float] = None) -> Optional[DepthFrame]:
        """The next frame; None when a recording without ``loop`` has ended, or when no frame
        came within ``timeout`` seconds (default: the source's ``timeout`` option)."""
        if self._closed:
            raise InputError(f"OpenNI2Source for camera {self._camera.name!r} is closed; open a new source to read again")
        if self._ended:
            return None
        if self.is_file and not self.loop and self.frames_in_file is not None and self._count >= self.frames_in_file:
            self._ended = True
            return None
        wait = self.timeout if timeout is None else max(0.0, float(timeout))
        o = self._openni2
        if o.wait_for_any_stream([self._depth], timeout=wait) is None:
            if self.is_file and not self.loop:
                self._ended = True
            return None
        f = self._depth.read_frame()
        row = int(f.stride) // 2 if getattr(f, "stride", 0) else int(f.width)
        depth = np.frombuffer(f.get_buffer_as_uint16(), dtype=np.uint16).reshape(f.height, row)[:, :f.width].copy()
        ts = f.timestamp * 1e-6
        frame_index = int(f.frameIndex)
        f.close()
        color = None
        if self._color is not None and o.wait_for_any_stream([self._color], timeout=min(wait, 0.1)) is not None:
            color = self._color_image(self._color.read_frame(), depth.shape)
        if self.software_unmirror:
            depth = depth[:, ::-1].copy()
            color = None if color is None else color[:, ::-1].copy()
        if ts + self._t_offset <= self._last_ts:  # a looping recording started again
            self._t_offset = self._last_ts - ts + 1.0 / self.fps
        t = ts + self._t_offset
        self._last_ts = t
        seq = self._seq
        self._seq += 1
        self._count += 1
        self.last_frame_index = frame_index
        return DepthFrame(self._camera.name, depth, t, seq, color=color)

    @staticmethod
    def _color_image(cf, shape) -> Optional[np.ndarray]:
        """The RGB888 colour frame as (H, W, 3) uint8 when it matches the depth size, else None."""
        try:
            if (cf.height, cf.width) != shape or not str(cf.videoMode.pixelFormat).upper().endswith("RGB888"):
                return None
            row = int(cf.stride) if getattr(cf, "stride", 0) else 3 * int(cf.width)
            img = np.frombuffer(cf.get_buffer_as_uint8(), dtype=np.uint8).reshape(cf.height, row)[:, :3 * cf.width]
            return img.reshape(cf.height, cf.width, 3).copy()
        finally:
            cf.close()

    def describe(self) -> str:
        return f"openni2 camera {self._camera.name!r} ({self.target})"

    # -- closing -------------------------------------------------------------------------
    def _release(self) -> None:
        for s in (self._color, self._depth):
            if s is not None:
                try:
                    s.stop()
                    s.close()
                except Exception:
                    pass
        if self._device is not None:
            try:
                self._device.close()
            except Exception:
                pass
        self._device = self._depth = self._color = None

    def _close(self) -> None:
        self._release()

    def __repr__(self) -> str:
        kind = "recording" if self.is_file else "device"
        return (f"OpenNI2Source({self.target!r}, {kind}, camera={self._camera.name!r}, "
                f"{self._camera.width}x{self._camera.height}, intrinsics from {self.intrinsics_source})")
