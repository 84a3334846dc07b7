"""A rig: the cameras of one snapshot, their ray tables and their packed per-frame parameters."""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from .camera import Camera, check_rigid
from .errors import InputError
from .frame import DepthFrame

#: floats per camera in the packed parameter block (see ``Rig.pack``)
CAM_FLOATS = 24
#: ints per camera: pixel offset, pixel count, max_code, camera index
CAM_INTS = 4
MAX_CAMERAS = 255


class Rig:
    """Cameras in a fixed order; a point's camera id is its camera's index here."""

    def __init__(self, cameras: Sequence[Camera]):
        cameras = list(cameras)
        if not cameras:
            raise InputError("no cameras given; a snapshot needs at least one [[camera]]")
        if len(cameras) > MAX_CAMERAS:
            raise InputError(f"{len(cameras)} cameras; at most {MAX_CAMERAS} fit the uint8 camera id")
        names = [c.name for c in cameras]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise InputError(f"camera names must be unique; repeated: {', '.join(sorted(dup))}")
        self.cameras = cameras
        self.index = {c.name: i for i, c in enumerate(cameras)}
        sizes = [c.width * c.height for c in cameras]
        self.offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self.n_pixels = int(self.offsets[-1])
        self.rays = np.concatenate([c.ray_table().reshape(-1, 2) for c in cameras]).astype(np.float32)
        self.ints = np.array(
            [[self.offsets[i], c.width * c.height, c.max_code, i] for i, c in enumerate(cameras)], dtype=np.int32
        )

    def __len__(self):
        return len(self.cameras)

    def order(self, frames) -> list:
        """The frames as a list in rig order, validated; one frame per camera is required."""
        if isinstance(frames, DepthFrame):
            frames = [frames]
        if isinstance(frames, Mapping):
            frames = list(frames.values())
        out = [None] * len(self.cameras)
        for f in frames:
            if not isinstance(f, DepthFrame):
                raise InputError(f"expected DepthFrame objects, got {type(f).__name__}")
            i = self.index.get(f.camera)
            if i is None:
                raise InputError(f"frame from unknown camera {f.camera!r}; the rig has {', '.join(self.index)}")
            if out[i] is not None:
                raise InputError(f"two frames from camera {f.camera!r} in one snapshot; give one per camera")
            cam = self.cameras[i]
            f.check(cam.width, cam.height)
            out[i] = f
        missing = [c.name for c, f in zip(self.cameras, out) if f is None]
        if missing:
            raise InputError(f"no frame for camera(s) {', '.join(missing)}; a snapshot needs one frame per camera")
        return out

    def poses(self, frames: list) -> list:
        """World pose of each camera for these frames (a frame's own pose wins)."""
        poses = []
        for cam, f in zip(self.cameras, frames):
            if f.T_world_cam is not None:
                poses.append(check_rigid(f.T_world_cam, f"frame {f.seq} from {cam.name!r}: T_world_cam"))
            else:
                poses.append(cam.T_world_cam)
        return poses

    def pack(self, frames: list, lateral_px: float) -> np.ndarray:
        """float32 (n_cameras, CAM_FLOATS): R (9, row-major), t (3), the near bias a, b
        (``Camera.near_bias``: a reading z is taken at z - max(a, b z^2)), 2 unused, then
        depth_scale, z_min, z_max, noise a, noise b, lateral footprint (lateral_px / min(fx, fy),
        m per m of depth), has colour (0/1), has mask (0/1). Columns 0-15 and 16-23 are the
        device kernels' ``pose`` (float16) and ``cam`` (float8) arguments."""
        out = np.zeros((len(self.cameras), CAM_FLOATS), dtype=np.float32)
        for i, (cam, T, f) in enumerate(zip(self.cameras, self.poses(frames), frames)):
            out[i, 0:9] = T[:3, :3].reshape(-1)
            out[i, 9:12] = T[:3, 3]
            out[i, 12:14] = cam.near_bias
            out[i, 16:24] = [cam.depth_scale, cam.z_min, cam.z_max, cam.noise.a, cam.noise.b,
                             lateral_px / min(cam.fx, cam.fy), f.color is not None, f.mask is not None]
        return out
