"""Conversions between ROS 2 camera messages and pointfence's depth images and ``Camera``.

* ``sensor_msgs/Image``: ``16UC1`` holds millimetres (0 = no reading), ``32FC1`` metres (NaN,
  inf or <= 0 = no reading), as REP 118 and the ROS depth drivers define them. Rows may be
  padded (``step`` >= width x bytes per pixel); big-endian data is swapped.
* ``sensor_msgs/CompressedImage`` in the ``compressedDepth`` form of
  ``compressed_depth_image_transport`` (``depth_png.py``: a 12-byte ConfigHeader then a PNG).
* ``sensor_msgs/CameraInfo``: ``K`` (fx, fy, cx, cy in px), ``D`` with the ``plumb_bob`` model
  (k1, k2, p1, p2, k3: OpenCV's order, as ``Camera.dist``), width and height.

The depth handed to the pipeline is always uint16 codes in the camera's units
(``Camera.depth_scale`` m per code): millimetres become codes by ``round(mm x 0.001 /
depth_scale)``, metres by ``round(m / depth_scale)``; a depth the codes cannot hold (at or above
``max_code``) is dropped (code 0), never clipped to a wrong distance. Every malformed message is
an ``InputError`` that names the topic, the field, the value and what was expected.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from pointfence.kernels.camera import Camera, NoiseModel
from pointfence.kernels.errors import InputError

from .. import depth_png

MM = 0.001   # m per code of a 16UC1 image
#: CameraInfo distortion models whose first five coefficients are Camera.dist's
PLUMB_BOB_MODELS = ("plumb_bob", "rational_polynomial", "")
#: how Camera fields that CameraInfo does not carry may be given (scene [[camera]] keys)
CAMERA_KEYS = ("depth_scale", "noise", "z_min", "z_max", "max_code", "T_world_cam")


def stamp_seconds(stamp) -> float:
    """A ``builtin_interfaces/Time`` as seconds (float)."""
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def set_stamp(header, t: float) -> None:
    """Write ``t`` (s, >= 0) into ``header.stamp``."""
    if not (math.isfinite(t) and t >= 0):
        raise InputError(f"stamp {t!r} s; expected a finite time >= 0 (ROS time counts seconds since 1970)")
    ns = int(round(t * 1e9))
    header.stamp.sec, header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000


# -- CameraInfo <-> Camera ----------------------------------------------------------------
def camera_from_info(info, name: str, where: str, **camera_options) -> Camera:
    """The ``Camera`` described by CameraInfo ``info`` (``camera_options``: CAMERA_KEYS, which
    CameraInfo does not carry; ``depth_scale`` defaults to 0.001 m, the units of 16UC1)."""
    unknown = sorted(set(camera_options) - set(CAMERA_KEYS))
    if unknown:
        raise InputError(f"{where}: unknown camera option(s) {', '.join(unknown)}; expected {', '.join(CAMERA_KEYS)}")
    fx, fy, cx, cy, dist = intrinsics_of(info, where)
    kw = dict(camera_options)
    kw.setdefault("depth_scale", MM)
    if "noise" in kw and not isinstance(kw["noise"], NoiseModel):
        n = kw["noise"]
        kw["noise"] = NoiseModel(**n) if isinstance(n, dict) else NoiseModel(*n)
    return Camera(name, int(info.width), int(info.height), fx, fy, cx, cy, dist=dist, **kw)


def intrinsics_of(info, where: str) -> tuple:
    """(fx, fy, cx, cy, dist) of CameraInfo ``info``, checked (px; dist in OpenCV's order)."""
    w, h = int(info.width), int(info.height)
    if w <= 0 or h <= 0:
        raise InputError(f"{where}: CameraInfo width x height = {w} x {h}; expected the image size in pixels (> 0)")
    k = [float(v) for v in info.k]
    if len(k) != 9 or not all(math.isfinite(v) for v in k) or k[0] <= 0 or k[4] <= 0:
        raise InputError(f"{where}: CameraInfo K = {k}; expected a calibrated 3x3 matrix with fx = K[0] > 0 and fy = K[4] > 0 "
                         "(an uncalibrated camera publishes zeros: calibrate it or give fx, fy, cx, cy in [[camera]])")
    if k[1] != 0 or k[3] != 0 or k[6:] != [0.0, 0.0, 1.0]:
        raise InputError(f"{where}: CameraInfo K = {k}; expected [fx, 0, cx, 0, fy, cy, 0, 0, 1] (no skew)")
    if int(info.binning_x) > 1 or int(info.binning_y) > 1 or int(info.roi.width) or int(info.roi.height):
        raise InputError(f"{where}: CameraInfo binning {info.binning_x}x{info.binning_y}, ROI {info.roi.width}x{info.roi.height}; "
                         "pointfence takes full-resolution images only: turn binning and ROI off in the driver")
    model = str(info.distortion_model)
    d = [float(v) for v in info.d]
    if model not in PLUMB_BOB_MODELS or (model == "" and any(d)):
        raise InputError(f"{where}: CameraInfo distortion_model {model!r}; expected 'plumb_bob' (Brown-Conrady k1 k2 p1 p2 k3), "
                         "or a rectified image with D all zero")
    if not all(math.isfinite(v) for v in d) or (len(d) > 5 and any(d[5:])) or len(d) not in (0, 5, 8):
        raise InputError(f"{where}: CameraInfo D = {d} ({model}); expected 5 finite plumb_bob coefficients "
                         "(or 8 rational_polynomial ones whose last three are zero)")
    dist = tuple((d + [0.0] * 5)[:5])
    return k[0], k[4], k[2], k[5], dist


def info_msg(camera: Camera, frame_id: str, t: float):
    """``sensor_msgs/CameraInfo`` of ``camera`` stamped ``t`` (s)."""
    from sensor_msgs.msg import CameraInfo

    m = CameraInfo()
    set_stamp(m.header, t)
    m.header.frame_id = frame_id
    m.width, m.height = int(camera.width), int(camera.height)
    m.distortion_model = "plumb_bob"
    m.d = [float(v) for v in camera.dist]
    m.k = [float(camera.fx), 0.0, float(camera.cx), 0.0, float(camera.fy), float(camera.cy), 0.0, 0.0, 1.0]
    m.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    m.p = [float(camera.fx), 0.0, float(camera.cx), 0.0, 0.0, float(camera.fy), float(camera.cy), 0.0, 0.0, 0.0, 1.0, 0.0]
    return m


def check_info_matches(info, camera: Camera, from_info: bool, where: str) -> None:
    """Raise unless CameraInfo ``info`` describes ``camera``: its size always; with
    ``from_info`` (the camera was made from CameraInfo) also K and D, so a camera whose
    calibration changed under a running service is refused rather than misplaced."""
    if (int(info.width), int(info.height)) != (camera.width, camera.height):
        raise InputError(f"{where}: CameraInfo says {info.width}x{info.height} but camera {camera.name!r} is "
                         f"{camera.width}x{camera.height}; the driver changed resolution: restart the service or fix [[camera]]")
    if from_info:
        fx, fy, cx, cy, dist = intrinsics_of(info, where)
        mine = (camera.fx, camera.fy, camera.cx, camera.cy) + tuple(camera.dist)
        if not np.allclose((fx, fy, cx, cy) + dist, mine, rtol=0, atol=1e-9):
            raise InputError(f"{where}: CameraInfo changed to fx={fx:g} fy={fy:g} cx={cx:g} cy={cy:g} D={list(dist)} from the "
                             f"fx={camera.fx:g} fy={camera.fy:g} cx={camera.cx:g} cy={camera.cy:g} D={list(camera.dist)} "
                             "the source started with; restart the service to take the new calibration")


# -- depth arrays -------------------------------------------------------------------------
def codes_from_mm(mm: np.ndarray, camera: Camera) -> np.ndarray:
    """uint16 millimetres -> the camera's uint16 codes (a copy; codes that do not fit are 0)."""
    if abs(camera.depth_scale - MM) < 1e-15:
        return np.array(mm, dtype=np.uint16, copy=True)
    return codes_from_m(mm.astype(np.float32) * np.float32(MM), camera)


def codes_from_m(m: np.ndarray, camera: Camera) -> np.ndarray:
    """float metres -> the camera's uint16 codes: NaN, inf, <= 0 and too far become 0."""
    c = np.rint(np.asarray(m, np.float64) / camera.depth_scale)
    ok = np.isfinite(c) & (c > 0) & (c < int(camera.max_code))
    return np.where(ok, c, 0).astype(np.uint16)


def mm_from_codes(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """The camera's uint16 codes -> uint16 millimetres for a 16UC1 image (0 = no reading; the
    camera's invalid code ``max_code`` and depths beyond 65.534 m become 0)."""
    depth = np.asarray(depth)
    if abs(camera.depth_scale - MM) < 1e-15:
        if int(camera.max_code) >= 65535:
            return depth
        return np.where(depth >= camera.max_code, 0, depth).astype(np.uint16)
    mm = np.rint(depth.astype(np.float64) * (camera.depth_scale / MM))
    ok = (depth > 0) & (depth < int(camera.max_code)) & (mm < 65535)
    return np.where(ok, mm, 0).astype(np.uint16)


_BYTES = {"16UC1": (2, np.uint16), "32FC1": (4, np.float32)}


def depth_from_image(msg, camera: Camera, where: str) -> np.ndarray:
    """The camera's uint16 (H, W) codes of ``sensor_msgs/Image`` ``msg`` (16UC1 mm or 32FC1 m)."""
    enc = str(msg.encoding)
    if enc not in _BYTES:
        hint = " (mono16 is an intensity image: publish depth as 16UC1)" if enc == "mono16" else ""
        raise InputError(f"{where}: image encoding {enc!r}{hint}; expected '16UC1' (depth in mm) or '32FC1' (depth in m)")
    bpp, dtype = _BYTES[enc]
    w, h, step = int(msg.width), int(msg.height), int(msg.step)
    if (w, h) != (camera.width, camera.height):
        raise InputError(f"{where}: image {w}x{h}; expected {camera.width}x{camera.height} for camera {camera.name!r}")
    if step < w * bpp or step % bpp:
        raise InputError(f"{where}: {enc} image step = {step} bytes; expected a multiple of {bpp} of at least width x {bpp} = {w * bpp}")
    data = np.frombuffer(msg.data, dtype=np.uint8)
    if data.size != step * h:
        raise InputError(f"{where}: {enc} image data of {data.size} bytes; expected step x height = {step} x {h} = {step * h}")
    px = data.view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")).reshape(h, step // bpp)[:, :w]
    if enc == "16UC1":
        return codes_from_mm(px.astype(np.uint16), camera)
    return codes_from_m(px, camera)


def depth_from_compressed(msg, camera: Camera, where: str) -> np.ndarray:
    """The camera's uint16 (H, W) codes of a ``compressedDepth`` ``sensor_msgs/CompressedImage``."""
    kind, img = depth_png.decode_compressed_depth(bytes(msg.data), str(msg.format), where)
    if img.shape != (camera.height, camera.width):
        raise InputError(f"{where}: compressedDepth image {img.shape[1]}x{img.shape[0]}; expected "
                         f"{camera.width}x{camera.height} for camera {camera.name!r}")
    return codes_from_mm(img, camera) if kind == "16UC1" else codes_from_m(img, camera)


def image_msg(depth: np.ndarray, camera: Camera, frame_id: str, t: float):
    """``sensor_msgs/Image`` 16UC1 (mm) of the camera's uint16 codes ``depth``, stamped ``t``."""
    from sensor_msgs.msg import Image

    mm = np.ascontiguousarray(mm_from_codes(depth, camera), dtype="<u2")
    m = Image()
    set_stamp(m.header, t)
    m.header.frame_id = frame_id
    m.height, m.width = mm.shape
    m.encoding = "16UC1"
    m.is_bigendian = 0
    m.step = 2 * mm.shape[1]
    m.data = mm.tobytes()     # bytes: rclpy copies them in C (an ndarray goes element by element)
    return m


def compressed_msg(depth: np.ndarray, camera: Camera, frame_id: str, t: float):
    """``sensor_msgs/CompressedImage`` (``compressedDepth``, 16UC1 mm in PNG) of ``depth``."""
    from sensor_msgs.msg import CompressedImage

    m = CompressedImage()
    set_stamp(m.header, t)
    m.header.frame_id = frame_id
    m.format = depth_png.DEPTH_FORMAT
    m.data = depth_png.encode_depth(np.ascontiguousarray(mm_from_codes(depth, camera), dtype=np.uint16))
    return m


def frame_id_check(image_frame: str, info_frame: Optional[str], expected: Optional[str], where: str) -> None:
    """Raise when the image's ``header.frame_id`` differs from the expected one or from its
    CameraInfo's (an image of another camera on the topic)."""
    if expected and image_frame != expected:
        raise InputError(f"{where}: image frame_id {image_frame!r}; expected {expected!r} (the frame_id option)")
    if info_frame and image_frame and info_frame != image_frame:
        raise InputError(f"{where}: image frame_id {image_frame!r} but its CameraInfo's is {info_frame!r}; "
                         "the image and camera_info topics come from different cameras")
