"""Recorded depth sequences played back as a depth source.

``RecordedSource(path)`` plays the frames of a recording (see ``recording`` for the layouts)
in name order, at ``rate_hz`` (default 30), looping by default. Frame ``seq`` shows file
``seq % n`` with timestamp ``start_time + seq / rate_hz`` (s); when the recording has poses,
``DepthFrame.T_world_cam`` is that frame's camera-to-world pose (m). ``camera_from_recording``
builds the ``Camera`` from the files so users need not type intrinsics.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError
from pointfence.kernels.frame import DepthFrame

from .base import DepthSource
from .imagefiles import read_color_image, read_depth_image
from .pcd import depth_from_cloud, fit_intrinsics, read_pcd
from .recording import Recording, read_pose, scan_recording

_SCAN_KEYS = ("layout", "fx", "fy", "cx", "cy", "depth_scale")
_CAMERA_KEYS = ("noise", "z_min", "z_max", "dist", "max_code")


def _split(options: dict, what: str):
    unknown = sorted(set(options) - set(_SCAN_KEYS) - set(_CAMERA_KEYS))
    if unknown:
        raise InputError(f"{what}: unknown option(s) {', '.join(unknown)}; it accepts: {', '.join(_SCAN_KEYS + _CAMERA_KEYS)}")
    return ({k: v for k, v in options.items() if k in _SCAN_KEYS}, {k: v for k, v in options.items() if k in _CAMERA_KEYS})


def _load(rec: Recording, i: int, want_color: bool):
    """(depth uint16, color uint8 or None, pose 4x4 or None) of frame ``i``."""
    f = rec.frames[i]
    color = None
    if rec.layout == "pcd":
        cloud = read_pcd(f)
        depth = depth_from_cloud(cloud, rec.depth_scale)
        color = cloud.rgb if want_color else None
    else:
        depth = read_depth_image(f)
        if want_color and rec.colors[i] is not None:
            color = read_color_image(rec.colors[i])
            if color.shape[:2] != depth.shape:
                color = None  # not registered to the depth image: leave it out
    pose = read_pose(rec.poses[i]) if rec.poses[i] is not None else None
    return depth, color, pose


def _camera(rec: Recording, name: str, camera_options: dict) -> Camera:
    pose = read_pose(rec.poses[0]) if rec.poses[0] is not None else None
    k = rec.intrinsics
    if rec.layout == "pcd":
        cloud = read_pcd(rec.frames[0])
        h, w = cloud.xyz.shape[:2]
        if k is None:  # the organised points define the projection exactly
            k = fit_intrinsics(cloud)
    else:
        h, w = read_depth_image(rec.frames[0]).shape
    return Camera(name, w, h, *k, depth_scale=rec.depth_scale,
                  T_world_cam=np.eye(4) if pose is None else pose, **camera_options)


def camera_from_recording(path, name: str = "cam0", **options) -> Camera:
    """The ``Camera`` of the recording at ``path``: image size of the first frame, intrinsics
    from the files (or fitted from an organised PCD), depth scale, and the first frame's pose
    as ``T_world_cam`` (identity when there are no poses).

    Options: layout, fx, fy, cx, cy (px), depth_scale (m/unit) override the files; noise,
    z_min, z_max, dist, max_code go to ``Camera``.
    """
    scan, cam = _split(options, f"camera_from_recording({path})")
    return _camera(scan_recording(path, **scan), name, cam)


class RecordedSource(DepthSource):
    """Depth frames from files on disk.

    Args:
        path: folder of frames (layout auto-detected) or one frame file.
        camera: the camera to report; default ``camera_from_recording(path, name)``.
        name: camera name when ``camera`` is not given.
        loop: start again after the last frame (default True); False ends the stream.
        rate_hz, realtime: see ``DepthSource``.
        start_time: timestamp (s) of frame 0.
        color: None (default) gives colour only where it is registered and free (PCD);
            True also loads colour image files beside the frames (when their size matches).
        cache: keep decoded frames in memory (default True; PCD decoding is slow).
        **options: layout, fx, fy, cx, cy, depth_scale, noise, z_min, z_max, dist, max_code.
    """

    def __init__(self, path, camera: Optional[Camera] = None, *, name: str = "cam0", loop: bool = True,
                 rate_hz: float = 30.0, realtime: bool = False, start_time: float = 0.0,
                 color: Optional[bool] = None, cache: bool = True, **options):
        scan, cam_opts = _split(options, f"recorded source {path}")
        rec = scan_recording(path, **scan)
        if camera is None:
            camera = _camera(rec, name, cam_opts)
        super().__init__(camera, rate_hz, realtime)
        self.recording = rec
        self.path = Path(path)
        self.loop = bool(loop)
        self.start_time = float(start_time)
        self._want_color = rec.layout == "pcd" if color is None else bool(color)
        self._cache: Optional[dict] = {} if cache else None

    def __len__(self) -> int:
        """Number of frame files in the recording."""
        return len(self.recording.frames)

    def load(self, index: int):
        """(depth, color, pose) of file ``index`` (0-based, name order), checked against the camera."""
        if self._cache is not None and index in self._cache:
            return self._cache[index]
        item = _load(self.recording, index, self._want_color)
        cam = self.camera
        if item[0].shape != (cam.height, cam.width):
            raise InputError(
                f"{self.recording.frames[index]}: depth image {item[0].shape[1]}x{item[0].shape[0]}; "
                f"expected {cam.width}x{cam.height} like camera {cam.name!r} (all frames of a recording must have one size)"
            )
        if self._cache is not None:
            self._cache[index] = item
        return item

    def _frame(self, seq: int) -> Optional[DepthFrame]:
        n = len(self)
        if seq >= n and not self.loop:
            return None
        depth, color, pose = self.load(seq % n)
        # Copies: a consumer that edits its frame in place must not change the cached one.
        return DepthFrame(self.camera.name, depth.copy(), self.start_time + seq / self.rate_hz, seq,
                          color=None if color is None else color.copy(),
                          T_world_cam=None if pose is None else pose.copy())

    def _close(self) -> None:
        self._cache = None if self._cache is None else {}

    def __repr__(self) -> str:
        return f"RecordedSource({str(self.path)!r}, layout={self.recording.layout!r}, frames={len(self)}, camera={self.camera.name!r})"
