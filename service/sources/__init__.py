"""Depth sources: one interface (``DepthSource``) yielding ``DepthFrame`` objects.

``open_source(spec, camera=None, **options)`` opens a source from a string:

* ``synthetic:<scene>``: an analytic scene (``scenes.SCENES``) ray-cast with Kinect-like noise;
* ``recorded:<path>``: a folder of depth frames (layout auto-detected) or one frame file;
* ``openni2:<device uri | any | file.oni>``: an OpenNI2 camera or recording (``openni2.py``);
* ``depthai:<device id or empty>``: a Luxonis OAK stereo camera (``depthai_source.py``);
* ``ros2:<namespace or image topic>``: a ROS 2 camera driver's depth topics (``ros2/camera_source.py``).
* ``realsense:<serial or empty | file.bag | file.db3>``: an Intel RealSense camera or SDK recording (``realsense.py``).

Options may also follow the spec as a query string, ``synthetic:sphere?radius=0.05&seed=3``;
keyword options win over query options. The live-camera modules import their vendor library
only when a source of that scheme is opened.
"""
from __future__ import annotations

from typing import Callable, Optional

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError

from .base import DepthSource
from .recorded import RecordedSource, camera_from_recording
from .scenes import SCENES, Scene, make_scene
from .synthetic import SyntheticSource, default_camera, look_at

#: scheme -> callable(target, camera, **options) -> DepthSource
SCHEMES: dict[str, Callable[..., DepthSource]] = {
    "synthetic": lambda target, camera, **o: SyntheticSource(target, camera, **o),
    "recorded": lambda target, camera, **o: RecordedSource(target, camera, **o),
    "openni2": lambda target, camera, **o: _openni2_source(target, camera, **o),
    "depthai": lambda target, camera, **o: _depthai_source(target, camera, **o),
    "ros2": lambda target, camera, **o: _ros2_source(target, camera, **o),
    "realsense": lambda target, camera, **o: _realsense_source(target, camera, **o),
}
#: schemes announced but not implemented yet (named in error messages).
PLANNED: tuple = ()


def _openni2_source(target, camera, **options) -> DepthSource:
    from .openni2 import OpenNI2Source

    return OpenNI2Source(target, camera, **options)


def _depthai_source(target, camera, **options) -> DepthSource:
    from .depthai_source import DepthAISource

    return DepthAISource(target, camera, **options)


def _ros2_source(target, camera, **options) -> DepthSource:
    from ..ros2.camera_source import RosDepthSource

    return RosDepthSource(target, camera, **options)
def _realsense_source(target, camera, **options) -> DepthSource:
    from .realsense import RealSenseSource

    return RealSenseSource(target, camera, **options)


def _value(text: str):
    """A query-string value as bool, int, float or str."""
    low = text.strip().lower()
    if low in ("true", "yes", "on"):
        return True
    if low in ("false", "no", "off"):
        return False
    if low in ("none", "null"):
        return None
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def parse_spec(spec: str) -> tuple[str, str, dict]:
    """``"scheme:target?k=v&k2=v2"`` -> (scheme, target, options)."""
    if not isinstance(spec, str) or ":" not in spec:
        raise InputError(
            f"source spec {spec!r}; expected '<scheme>:<target>' with scheme one of {', '.join(SCHEMES)} "
            "(e.g. 'synthetic:sphere' or 'recorded:/path/to/frames')"
        )
    scheme, _, rest = spec.partition(":")
    target, _, query = rest.partition("?")
    options = {}
    for item in filter(None, query.split("&")):
        key, eq, val = item.partition("=")
        if not eq or not key:
            raise InputError(f"source spec {spec!r}: option {item!r}; expected key=value pairs after '?'")
        options[key.strip()] = _value(val)
    return scheme.strip().lower(), target, options


def open_source(spec: str, camera: Optional[Camera] = None, **options) -> DepthSource:
    """Open the depth source described by ``spec`` (see the module docstring)."""
    scheme, target, query = parse_spec(spec)
    if scheme not in SCHEMES:
        later = f" ({', '.join(p + ':' for p in PLANNED)} come later)" if PLANNED else ""
        raise InputError(f"unknown source scheme {scheme!r} in {spec!r}; known: {', '.join(s + ':' for s in SCHEMES)}{later}")
    if not target and scheme not in ("openni2", "depthai", "realsense"):  # live cameras: empty = the first one attached
        raise InputError(f"source spec {spec!r} names no {'scene' if scheme == 'synthetic' else 'target'} after '{scheme}:'")
    try:
        return SCHEMES[scheme](target, camera, **{**query, **options})
    except TypeError as e:  # a bad keyword for that source; anything else is a bug: re-raise
        if "argument" not in str(e):
            raise
        raise InputError(f"source {spec!r}: {e}") from None


__all__ = [
    "DepthSource", "SyntheticSource", "RecordedSource", "open_source", "parse_spec", "camera_from_recording",
    "default_camera", "look_at", "make_scene", "Scene", "SCENES", "SCHEMES",
]
