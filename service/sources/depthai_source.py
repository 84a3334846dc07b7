"""Luxonis OAK stereo depth cameras through the ``depthai`` library (v3 API).

``depthai:`` opens the first OAK device found; ``depthai:<device id>`` (the id printed by
``list_devices()`` or ``oakctl list``; a device name or IP address works too) opens that one.
Needs ``pip install depthai`` (>= 3.0) and, on Linux, the Luxonis udev rule for USB access.

The device runs a stereo pipeline: two mono cameras (CAM_B left, CAM_C right) into a
``StereoDepth`` node with left-right check and subpixel disparity; its depth output (uint16,
millimetres) comes to the host. ``align`` picks the viewpoint of the depth image:

* ``"right"`` (default) / ``"left"``: the rectified right or left mono camera; the image is
  undistorted by the rectification, so ``dist`` is zero;
* ``"rgb"``: the colour camera (CAM_A); the depth is warped into it and the colour camera's
  distortion coefficients come with it.

Intrinsics come from the device's own factory calibration (EEPROM), scaled to the output size;
timestamps are the device's capture time converted to the host's monotonic clock (seconds).

Options: ``name``, ``align``, ``width``/``height`` (default 640x400), ``fps`` (default 30),
``preset`` (a StereoDepth preset: default, fast_accuracy, fast_density, high_detail, robotics,
density, accuracy, face), ``subpixel`` (True), ``lr_check`` (True), ``extended`` (False: extended
disparity for close range), ``timeout`` (s, default 2), ``rate_hz``, and the camera keys
``noise``, ``z_min``, ``z_max``, ``max_code``.

Everything that does not need a device is plain code that takes the ``dai`` module as an
argument (``build_pipeline``, ``camera_from_calibration``, ``frame_from_message``), so it is
tested without a camera.
"""
from __future__ import annotations

import math
from datetime import timedelta
from typing import Optional

import numpy as np

from pointfence.kernels.camera import Camera, NoiseModel
from pointfence.kernels.errors import InputError, PointfenceError
from pointfence.kernels.frame import DepthFrame

from .base import LiveSource

INSTALL_HINT = ("install the Luxonis depthai library (`pip install 'depthai>=3'`) and, on Linux, the udev rule from "
                "Luxonis' installation guide so the OAK is accessible without root")
#: align option -> the board socket whose viewpoint the depth image takes
ALIGN_SOCKETS = {"right": "CAM_C", "left": "CAM_B", "rgb": "CAM_A"}
PRESETS = ("default", "fast_accuracy", "fast_density", "high_detail", "robotics", "density", "accuracy", "face")
_CAMERA_KEYS = ("noise", "z_min", "z_max", "max_code")
DEPTH_SCALE = 0.001  # depthai depth frames are millimetres


class DepthAIUnavailable(PointfenceError, RuntimeError):
    """The depthai library is not installed (the message says how to install it)."""


def import_depthai():
    """The ``depthai`` module; raises DepthAIUnavailable with install instructions when missing."""
    try:
        import depthai as dai
    except ImportError as e:
        raise DepthAIUnavailable(f"the depthai library is not importable ({e}); {INSTALL_HINT}") from None
    major = str(getattr(dai, "__version__", "0")).split(".")[0]
    if not major.isdigit() or int(major) < 3:
        raise DepthAIUnavailable(f"depthai {getattr(dai, '__version__', '?')} is installed; pointfence uses the depthai v3 API: "
                                 "`pip install -U 'depthai>=3'`")
    return dai


def _device_id(info) -> str:
    for attr in ("getDeviceId", "getMxId"):
        if hasattr(info, attr):
            return str(getattr(info, attr)())
    return str(getattr(info, "deviceId", getattr(info, "name", info)))


def describe_devices(infos) -> list:
    """Readable lines (id, name, state) of depthai DeviceInfo objects."""
    out = []
    for info in infos:
        state = getattr(info, "state", "")
        state = getattr(state, "name", state)
        out.append(f"{_device_id(info)} ({getattr(info, 'name', '')}{', ' + str(state) if state else ''})")
    return out


def find_device(dai, target: str = ""):
    """The DeviceInfo of the device ``target`` (id, name or IP; empty = the first found).

    Raises InputError listing what was found when nothing matches.
    """
    infos = list(dai.Device.getAllAvailableDevices())
    target = (target or "").strip()
    if not infos:
        raise InputError(f"depthai source: no OAK device found{' for ' + repr(target) if target else ''} "
                         "(devices found: none). Plug the camera in (USB3 cable), check the udev rule, or for a PoE "
                         "model its network; then `depthai:` opens the first device")
    if not target:
        return infos[0]
    for info in infos:
        if target in (_device_id(info), str(getattr(info, "name", ""))):
            return info
    raise InputError(f"depthai source: no device {target!r}; devices found: {', '.join(describe_devices(infos))}")


def build_pipeline(dai, pipeline, *, align: str = "right", width: int = 640, height: int = 400, fps: float = 30.0,
                   preset: str = "default", subpixel: bool = True, lr_check: bool = True, extended: bool = False):
    """Add the stereo depth nodes to ``pipeline`` (a ``dai.Pipeline`` bound to a device) and
    return the depth output queue (host side, newest frames only)."""
    align = check_align(align)
    preset_mode = getattr(dai.node.StereoDepth.PresetMode, check_preset(preset).upper())
    left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
    right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
    stereo = pipeline.create(dai.node.StereoDepth)
    stereo.setDefaultProfilePreset(preset_mode)
    size = (int(width), int(height))
    left.requestOutput(size, fps=float(fps)).link(stereo.left)
    right.requestOutput(size, fps=float(fps)).link(stereo.right)
    stereo.setLeftRightCheck(bool(lr_check))
    stereo.setSubpixel(bool(subpixel))
    stereo.setExtendedDisparity(bool(extended))
    stereo.setDepthAlign(getattr(dai.CameraBoardSocket, ALIGN_SOCKETS[align]))
    if align == "rgb":
        stereo.setOutputSize(*size)
    return stereo.depth.createOutputQueue(maxSize=4, blocking=False)


def check_align(align) -> str:
    a = str(align).lower()
    if a not in ALIGN_SOCKETS:
        raise InputError(f"depthai source: align = {align!r}; expected one of {', '.join(ALIGN_SOCKETS)}")
    return a


def check_preset(preset) -> str:
    p = str(preset).lower()
    if p not in PRESETS:
        raise InputError(f"depthai source: preset = {preset!r}; expected one of {', '.join(PRESETS)}")
    return p


def camera_from_calibration(dai, calib, align: str, width: int, height: int, name: str = "cam0", **camera_options) -> Camera:
    """The ``Camera`` of depth frames aligned to ``align`` at ``width`` x ``height``, from a
    ``dai.CalibrationHandler`` (the device's EEPROM calibration)."""
    align = check_align(align)
    socket = getattr(dai.CameraBoardSocket, ALIGN_SOCKETS[align])
    try:
        K = np.asarray(calib.getCameraIntrinsics(socket, int(width), int(height)), dtype=np.float64)
    except RuntimeError as e:
        raise InputError(f"depthai source: the device has no calibration for {ALIGN_SOCKETS[align]} ({e}); "
                         f"use another align than {align!r} or calibrate with `pointfence calib intrinsics`") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"depthai source: the device calibration of {ALIGN_SOCKETS[align]} gives intrinsics {K.tolist()}; "
                         "expected a 3x3 camera matrix with positive focal lengths")
    dist = (0.0,) * 5
    if align == "rgb":  # the colour image keeps its lens distortion; rectified mono images do not
        coeffs = list(calib.getDistortionCoefficients(socket))[:5]
        dist = tuple(float(c) for c in coeffs) + (0.0,) * (5 - len(coeffs))
    kw = dict(camera_options)
    if "noise" in kw and not isinstance(kw["noise"], NoiseModel):
        kw["noise"] = NoiseModel(**kw["noise"]) if isinstance(kw["noise"], dict) else NoiseModel(*kw["noise"])
    return Camera(name, int(width), int(height), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                  depth_scale=DEPTH_SCALE, dist=dist, **kw)


def _seconds(t) -> float:
    return t.total_seconds() if isinstance(t, timedelta) else float(t)


def frame_from_message(msg, camera: Camera, seq: int) -> DepthFrame:
    """A ``DepthFrame`` from a depthai ``ImgFrame`` of depth (RAW16, millimetres).

    The timestamp is ``msg.getTimestamp()``: device capture time on the host's monotonic clock, s.
    """
    depth = np.asarray(msg.getFrame())
    if depth.dtype != np.uint16:
        raise InputError(f"depthai frame of {camera.name!r}: dtype {depth.dtype}; expected uint16 depth in millimetres "
                         "(is the queue the StereoDepth 'depth' output, not 'disparity'?)")
    if depth.shape != (camera.height, camera.width):
        raise InputError(f"depthai frame of {camera.name!r}: {depth.shape[1]}x{depth.shape[0]}; expected "
                         f"{camera.width}x{camera.height} (set the width/height options to match the [[camera]] entry)")
    return DepthFrame(camera.name, np.ascontiguousarray(depth), _seconds(msg.getTimestamp()), seq)


def list_devices() -> list:
    """Readable descriptions of the OAK devices attached now."""
    dai = import_depthai()
    return describe_devices(dai.Device.getAllAvailableDevices())


class DepthAISource(LiveSource):
    """Depth frames from an OAK camera (see the module docstring)."""

    def __init__(self, target: str = "", camera: Optional[Camera] = None, *, name: Optional[str] = None,
                 align: str = "right", width: int = 640, height: int = 400, fps: float = 30.0, preset: str = "default",
                 subpixel: bool = True, lr_check: bool = True, extended: bool = False, timeout: float = 2.0,
                 rate_hz: Optional[float] = None, realtime: bool = True, **camera_options):
        unknown = sorted(set(camera_options) - set(_CAMERA_KEYS))
        if unknown:
            raise InputError(f"depthai source {target!r}: unknown option(s) {', '.join(unknown)}; it accepts: name, align, width, "
                             "height, fps, preset, subpixel, lr_check, extended, timeout, rate_hz, " + ", ".join(_CAMERA_KEYS))
        align, preset = check_align(align), check_preset(preset)
        if camera is not None:
            width, height = camera.width, camera.height
        for key, v in (("width", width), ("height", height), ("fps", fps), ("timeout", timeout)):
            try:
                ok = float(v) > 0 and math.isfinite(float(v))
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise InputError(f"depthai source {target!r}: {key} = {v!r}; expected a positive number")
        self.timeout = float(timeout)
        dai = import_depthai()
        self._dai = dai
        info = find_device(dai, target)
        self.device_id = _device_id(info)
        self._device = self._pipeline = None
        try:
            self._device = dai.Device(info)
            self._pipeline = dai.Pipeline(self._device)
            self._queue = build_pipeline(dai, self._pipeline, align=align, width=width, height=height, fps=fps,
                                         preset=preset, subpixel=subpixel, lr_check=lr_check, extended=extended)
            if camera is None:
                camera = camera_from_calibration(dai, self._device.readCalibration(), align, width, height,
                                                 name or "cam0", **camera_options)
            super().__init__(camera, rate_hz if rate_hz is not None else fps, realtime=False)
            self._pipeline.start()
        except BaseException:
            self._release()
            raise
        self.align = align

    @property
    def realtime(self) -> bool:
        return True  # the device paces the frames

    def read(self, timeout: Optional[float] = None) -> Optional[DepthFrame]:
        """The newest depth frame, or None when none came within ``timeout`` s (default: the
        ``timeout`` option)."""
        if self._closed:
            raise InputError(f"DepthAISource for camera {self._camera.name!r} is closed; open a new source to read again")
        wait = self.timeout if timeout is None else max(0.0, float(timeout))
        msg = self._queue.get(timedelta(seconds=wait))
        if msg is None:
            if not self._pipeline.isRunning():
                self._ended = True
            return None
        frame = frame_from_message(msg, self._camera, self._seq)
        self._seq += 1
        return frame

    def describe(self) -> str:
        return f"depthai camera {self._camera.name!r} ({self.device_id})"

    def _release(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except Exception:
                pass
        if self._device is not None:
            try:
                self._device.close()
            except Exception:
                pass
        self._pipeline = self._device = None

    def _close(self) -> None:
        self._release()

    def __repr__(self) -> str:
        return f"DepthAISource({self.device_id!r}, align={self.align!r}, camera={self._camera.name!r})"
