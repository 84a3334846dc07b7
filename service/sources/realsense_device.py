"""What the RealSense source asks of librealsense (``pyrealsense2``) before it streams.

Device lookup by serial number, recordings opened as playback devices, the depth stream's mode
(profile), the visual preset, the intrinsics and depth scale as a pointfence ``Camera``, and the
mapping of frame timestamps to the service's time base. Every function takes the ``rs`` module
(``import_realsense()``) or objects made by it, so it runs on software devices and recordings
as on a camera.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

from pointfence.kernels.camera import Camera, NoiseModel
from pointfence.kernels.errors import InputError, PointfenceError

INSTALL_HINT = ("install Intel's RealSense SDK for Python: `pip install 'pointfence[realsense]'` (pyrealsense2 >= 2.55; "
                "wheels for x86-64 Linux and Windows) and, on Linux, the SDK's udev rules (99-realsense-libusb.rules) so "
                "the camera is accessible without root")
#: file name endings of the SDK's recordings: ROS 1 bags (SDK < 2.56 writes them) and ROS 2 bags (SQLite)
RECORDING_SUFFIXES = (".bag", ".db3")
#: timestamp domains on the host's clock (librealsense: milliseconds on the host's system clock,
#: global time being the device's clock mapped onto it by the SDK); anything else is the device's own
HOST_DOMAINS = ("global_time", "system_time")


class RealSenseUnavailable(PointfenceError, RuntimeError):
    """pyrealsense2 is not installed (the message says how to install it)."""


def import_realsense():
    """The ``pyrealsense2`` module; raises RealSenseUnavailable with install instructions when missing."""
    try:
        import pyrealsense2 as rs
    except ImportError as e:
        raise RealSenseUnavailable(f"the RealSense library pyrealsense2 is not importable ({e}); {INSTALL_HINT}") from None
    if not hasattr(rs, "context"):  # the namespace package left by a broken install
        raise RealSenseUnavailable(f"pyrealsense2 at {getattr(rs, '__path__', '?')} has no librealsense in it; "
                                   f"reinstall it: {INSTALL_HINT}")
    return rs


def is_recording_target(target: str) -> bool:
    """True when ``target`` names a file (a recording) rather than a serial number."""
    target = str(target or "").strip()
    return bool(target) and (target.lower().endswith(RECORDING_SUFFIXES) or "/" in target or Path(target).exists())


def _info(rs, dev, key: str) -> str:
    info = getattr(rs.camera_info, key)
    return str(dev.get_info(info)) if dev.supports(info) else ""


def describe_device(rs, dev) -> str:
    """``"<serial> (<name>, firmware <version>)"`` of a device."""
    extra = ", ".join(x for x in (_info(rs, dev, "name"), "firmware " + _info(rs, dev, "firmware_version")
                                  if _info(rs, dev, "firmware_version") else "") if x)
    return f"{_info(rs, dev, 'serial_number') or '?'}" + (f" ({extra})" if extra else "")


def list_devices(rs=None) -> list:
    """Readable descriptions (serial, name, firmware) of the RealSense cameras attached now."""
    rs = rs or import_realsense()
    return [describe_device(rs, d) for d in rs.context().query_devices()]


def find_device(rs, context, serial: str = ""):
    """The attached device with serial number ``serial`` (empty: the first one).

    Raises InputError listing the cameras attached when none matches."""
    devices = list(context.query_devices())
    serial = str(serial or "").strip()
    if not devices:
        raise InputError(f"realsense source: no RealSense camera attached{' with serial ' + repr(serial) if serial else ''} "
                         "(cameras attached: none). Plug the camera into a USB 3 port, install the SDK's udev rules, "
                         "or pass a recording (realsense:<file.bag or file.db3>)")
    if not serial:
        return devices[0]
    for dev in devices:
        if _info(rs, dev, "serial_number") == serial:
            return dev
    listing = "; ".join(describe_device(rs, d) for d in devices)
    raise InputError(f"realsense source: no RealSense camera with serial {serial!r}; cameras attached: {listing}")


def load_recording(rs, context, path: str):
    """The playback device of the SDK recording ``path`` (.bag or .db3).

    Raises InputError when the file is missing or is not a RealSense recording."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"realsense source: recording {path!r} not found; pass an existing .bag or .db3 file written by "
                         "the RealSense SDK (realsense-viewer, rs-record, rs.recorder), or a camera's serial number")
    if p.is_dir():
        raise InputError(f"realsense source: {path!r} is a folder; expected a .bag or .db3 recording of the RealSense SDK "
                         "(a folder of depth images is `recorded:<folder>`)")
    try:
        dev = context.load_device(str(p))
    except RuntimeError as e:
        raise InputError(f"realsense source: {path!r} is not a RealSense recording the SDK can play (librealsense: {e}); "
                         "expected a .bag or .db3 file written by the RealSense SDK (realsense-viewer, rs-record, rs.recorder)"
                         ) from None
    if not dev.is_playback():
        raise InputError(f"realsense source: {path!r} did not open as a recording")
    return dev


def describe_profile(p) -> str:
    """``"Depth 848x480@30 Z16"`` of a stream profile."""
    name = str(p.stream_type()).split(".")[-1].capitalize()
    fmt = str(p.format()).split(".")[-1].upper()
    if p.is_video_stream_profile():
        v = p.as_video_stream_profile()
        return f"{name} {v.width()}x{v.height()}@{p.fps()} {fmt}"
    return f"{name}@{p.fps()} {fmt}"


def depth_profiles(rs, dev) -> list:
    """[(sensor, video profile)] of every Z16 depth stream the device (or recording) offers."""
    out = []
    for sensor in dev.query_sensors():
        for p in sensor.get_stream_profiles():
            if p.stream_type() == rs.stream.depth and p.format() == rs.format.z16 and p.is_video_stream_profile():
                out.append((sensor, p.as_video_stream_profile()))
    return out


def pick_depth_profile(rs, dev, where: str, width: Optional[int] = None, height: Optional[int] = None,
                       fps: Optional[int] = None):
    """(sensor, profile) of the depth stream ``width`` x ``height`` at ``fps`` (each None: any;
    all None: the device's default depth mode, else its first).

    Raises InputError naming the streams there are when there is no such depth stream."""
    found = depth_profiles(rs, dev)
    if not found:
        have = [describe_profile(p) for s in dev.query_sensors() for p in s.get_stream_profiles()]
        raise InputError(f"realsense source {where}: no depth (Z16) stream; it has {', '.join(have) or 'no streams'}. "
                         "Record the depth stream, or pick a camera with a depth sensor")
    want = {k: v for k, v in (("width", width), ("height", height), ("fps", fps)) if v is not None}
    for key, v in want.items():
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise InputError(f"realsense source {where}: {key} = {v!r}; expected a positive integer")
    match = [(s, p) for s, p in found if (width is None or p.width() == width) and (height is None or p.height() == height)
             and (fps is None or p.fps() == fps)]
    if not match:
        have = sorted({f"{p.width()}x{p.height()}@{p.fps()}" for _, p in found})
        asked = f"{width or '*'}x{height or '*'}@{fps or '*'}"
        raise InputError(f"realsense source {where}: no depth stream {asked}; it offers {', '.join(have)} "
                         "(set the width, height and fps options to one of these)")
    if not want:
        default = [(s, p) for s, p in match if p.is_default()]
        return (default or match)[0]
    return match[0]


def preset_name(text: str) -> str:
    """A preset as the source names it: "High Accuracy" -> "high_accuracy"."""
    return "_".join(str(text).strip().lower().replace("-", " ").split())


def visual_presets(rs, sensor) -> dict:
    """{preset name: option value} of the sensor's visual presets (names as the device describes
    them, lower case with underscores: "high_accuracy"); empty when it has none."""
    opt = rs.option.visual_preset
    if not sensor.supports(opt):
        return {}
    r = sensor.get_option_range(opt)
    known = {int(v): k for k, v in rs.rs400_visual_preset.__members__.items()}
    out = {}
    v = float(r.min)
    while v <= r.max + 1e-9:
        try:
            desc = sensor.get_option_value_description(opt, v)
        except RuntimeError:
            desc = None
        name = preset_name(desc) if desc else known.get(int(round(v)))
        if name:
            out.setdefault(name, v)
        v += r.step if r.step > 0 else 1.0
    return out


def apply_preset(rs, sensor, preset: str, where: str) -> float:
    """Set the sensor's visual preset by name; returns the option value set."""
    presets = visual_presets(rs, sensor)
    if not presets:
        raise InputError(f"realsense source {where}: the depth sensor has no visual presets; leave out the preset option")
    name = preset_name(preset)
    if name not in presets:
        raise InputError(f"realsense source {where}: preset = {preset!r}; this camera offers {', '.join(presets)}")
    sensor.set_option(rs.option.visual_preset, presets[name])
    return presets[name]


def enable_global_time(rs, sensor) -> bool:
    """Ask the sensor to stamp frames in global time (the device clock mapped onto the host's by
    the SDK); False when the sensor cannot (its frames keep the device's hardware clock)."""
    opt = rs.option.global_time_enabled
    if not sensor.supports(opt) or sensor.is_option_read_only(opt):
        return False
    sensor.set_option(opt, 1.0)
    return sensor.get_option(opt) == 1.0


#: librealsense distortion models whose coefficients are OpenCV's Brown-Conrady (k1 k2 p1 p2 k3)
_BROWN_CONRADY = ("brown_conrady",)


def dist_of(rs, intrinsics, where: str) -> tuple:
    """pointfence's ``dist`` (Brown-Conrady k1 k2 p1 p2 k3, OpenCV order) of librealsense intrinsics.

    librealsense's ``brown_conrady`` model is OpenCV's (pixel = distort(undistorted ray)); a model
    with all-zero coefficients is none. Other models (inverse / modified Brown-Conrady, F-theta,
    Kannala-Brandt) with non-zero coefficients are refused: pointfence would deproject them wrong."""
    coeffs = tuple(float(c) for c in intrinsics.coeffs)[:5]
    coeffs += (0.0,) * (5 - len(coeffs))
    model = str(intrinsics.model).split(".")[-1]
    if not any(coeffs) or model == "none":
        return (0.0,) * 5
    if model in _BROWN_CONRADY:
        return coeffs
    raise InputError(f"realsense source {where}: the depth stream's lens model is {model} with coefficients "
                     f"{list(coeffs)}, which pointfence's Brown-Conrady deprojection does not represent; calibrate the "
                     "camera (`pointfence calib intrinsics`) and give fx, fy, cx, cy, dist in its [[camera]] entry "
                     "(or the dist option)")


def camera_from_profile(rs, profile, depth_scale: float, where: str, name: str = "cam0", **camera_options) -> Camera:
    """The ``Camera`` of a depth stream profile: its intrinsics (px, the SDK's float32 values
    exactly), distortion (``dist_of``, unless ``dist`` is given) and depth scale (m per unit)."""
    intr = profile.get_intrinsics()
    kw = dict(camera_options)
    if "noise" in kw and not isinstance(kw["noise"], NoiseModel):
        kw["noise"] = NoiseModel(**kw["noise"]) if isinstance(kw["noise"], dict) else NoiseModel(*kw["noise"])
    if "dist" not in kw:
        kw["dist"] = dist_of(rs, intr, where)
    if not (depth_scale > 0):
        raise InputError(f"realsense source {where}: the depth sensor reports a depth scale of {depth_scale}; "
                         "give depth_scale in the [[camera]] entry")
    return Camera(name, int(intr.width), int(intr.height), float(intr.fx), float(intr.fy), float(intr.ppx),
                  float(intr.ppy), depth_scale=float(depth_scale), **kw)


def wall_minus_monotonic() -> float:
    """The host's system clock minus its monotonic clock, s (sampled now; the mapping of host
    time stamps onto ``time.monotonic``)."""
    m0 = time.monotonic_ns()
    w = time.time_ns()
    m1 = time.monotonic_ns()
    return (w - (m0 + m1) // 2) * 1e-9


def domain_name(domain) -> str:
    """``"global_time"`` of ``rs.timestamp_domain.global_time``."""
    return str(domain).split(".")[-1]


def host_monotonic(timestamp_ms: float, offset_s: Optional[float] = None) -> float:
    """A frame time stamp on the host's system clock (ms since the Unix epoch: librealsense's
    global and system time) as ``time.monotonic`` seconds."""
    return timestamp_ms / 1000.0 - (wall_minus_monotonic() if offset_s is None else offset_s)
