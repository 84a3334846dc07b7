"""Synthetic depth camera: ray-cast analytic scenes with Kinect-like sensor effects.

Each frame is rendered exactly, one ray per pixel (vectorised numpy), then degraded as a
structured-light (Kinect v1 class) sensor would:

1. shadows: a pixel whose surface point the projector cannot see (projector ``baseline`` m
   along the camera's +x axis) reads 0;
2. axial noise: Z + N(0, sigma_z(Z)) with sigma_z = a + b Z^2 from ``camera.noise``;
3. disparity quantisation: disparity fx * baseline / Z (pixels) rounded to
   ``disparity_step`` (1/8 px), so depth steps grow as Z^2 / (8 fx baseline);
4. random holes: each pixel reads 0 with probability ``dropout``;
5. range: readings outside [camera.z_min, camera.z_max] or not below ``camera.max_code`` read 0.

Frame ``seq`` has timestamp ``start_time + seq / rate_hz`` (s) and draws its noise from
``numpy.random.default_rng([seed, seq])``, so a frame depends only on (seed, seq, options).
"""
from __future__ import annotations

from typing import Optional, Union

import numpy as np

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError
from pointfence.kernels.frame import DepthFrame

from .base import DepthSource
from .scenes import SCENES, Scene, make_scene
from .scenes import scene_options as scene_options_of

KINECT_BASELINE = 0.075  # m, emitter-to-IR-camera distance of a Kinect v1
KINECT_DISPARITY_STEP = 1.0 / 8.0  # px, sub-pixel disparity resolution of a Kinect v1
WHITE = (235, 235, 235)
SOURCE_OPTIONS = ("rate_hz", "realtime", "seed", "start_time", "noise", "quantize", "baseline", "disparity_step",
                  "dropout", "shadows", "color", "mask", "max_frames")
RED = (220, 30, 30)


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_world_cam (4x4) of a camera at ``eye`` whose optical axis (+z) points at ``target``
    and whose image "up" (-y) is as close to world ``up`` as possible (world metres). Looking
    straight along ``up``, image up is world +y."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    if np.linalg.norm(z) == 0:
        raise InputError(f"look_at: eye {eye.tolist()} equals target; expected distinct points")
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
        if np.linalg.norm(x) < 1e-9:
            x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def default_camera(
    name: str = "cam0",
    eye=(0.0, 0.0, 0.6),
    target=(0.0, 0.0, 0.0),
    width: int = 640,
    height: int = 480,
    fx: Optional[float] = None,
    fy: Optional[float] = None,
    cx: Optional[float] = None,
    cy: Optional[float] = None,
    **camera_options,
) -> Camera:
    """A Kinect-v1-like depth camera looking down at the workspace origin from 0.6 m.

    Defaults: 640x480, fx = fy = 575.8 px, cx = 319.5, cy = 239.5, millimetre depth, Kinect
    noise (b = 1.42e-3 1/m). For other sizes the focal length scales with ``width`` (same field
    of view) and the principal point is the image centre unless given. ``camera_options`` go to
    ``Camera`` (depth_scale, noise, z_min, z_max, dist, max_code).
    """
    fx = 575.8 * width / 640 if fx is None else fx
    fy = fx if fy is None else fy
    cx = (width - 1) / 2 if cx is None else cx
    cy = (height - 1) / 2 if cy is None else cy
    return Camera(name, int(width), int(height), float(fx), float(fy), float(cx), float(cy),
                  T_world_cam=look_at(eye, target), **camera_options)


class SyntheticSource(DepthSource):
    """Depth frames of an analytic ``scene`` seen by ``camera`` (default: ``default_camera()``).

    Options (SI units): rate_hz (30), realtime (False), seed (0), start_time (0 s),
    noise (True), quantize (True), baseline (0.075 m), disparity_step (1/8 px),
    dropout (0.01, fraction of random holes), shadows (True), color (False: add an RGB image
    with the protected object red on white), mask (False: add the protected-object mask),
    max_frames (None: endless). Any other keyword is a scene option (see ``scenes``).
    Every synthetic camera stamps its frames on the scene's clock (``clock_domain``).
    """

    clock_domain = "synthetic scene"

    def __init__(
        self,
        scene: Union[str, Scene] = "plane",
        camera: Optional[Camera] = None,
        *,
        rate_hz: float = 30.0,
        realtime: bool = False,
        seed: int = 0,
        start_time: float = 0.0,
        noise: bool = True,
        quantize: bool = True,
        baseline: float = KINECT_BASELINE,
        disparity_step: float = KINECT_DISPARITY_STEP,
        dropout: float = 0.01,
        shadows: bool = True,
        color: bool = False,
        mask: bool = False,
        max_frames: Optional[int] = None,
        **scene_options,
    ):
        super().__init__(camera if camera is not None else default_camera(), rate_hz, realtime)
        if isinstance(scene, Scene):
            if scene_options:
                raise InputError(f"scene options {sorted(scene_options)} given with a ready Scene object; set them on the scene instead")
            self.scene = scene
        else:
            name = str(scene)
            if name in SCENES:
                unknown = sorted(set(scene_options) - set(scene_options_of(name)))
                if unknown:
                    raise InputError(
                        f"synthetic scene {name!r}: unknown option(s) {', '.join(unknown)}; scene options: "
                        f"{', '.join(scene_options_of(name))}; source options: {', '.join(SOURCE_OPTIONS)}"
                    )
            self.scene = make_scene(name, **scene_options)
        if not 0 <= float(dropout) < 1:
            raise InputError(f"dropout = {dropout!r}; expected a fraction of pixels in [0, 1)")
        if float(baseline) <= 0 or float(disparity_step) <= 0:
            raise InputError(f"baseline = {baseline!r} m, disparity_step = {disparity_step!r} px; expected both > 0")
        if int(seed) < 0:
            raise InputError(f"seed = {seed!r}; expected an integer >= 0")
        if max_frames is not None and int(max_frames) < 0:
            raise InputError(f"max_frames = {max_frames!r}; expected None (endless) or an integer >= 0")
        self.seed = int(seed)
        self.start_time = float(start_time)
        self.noise, self.quantize, self.shadows = bool(noise), bool(quantize), bool(shadows)
        self.baseline, self.disparity_step, self.dropout = float(baseline), float(disparity_step), float(dropout)
        self.color, self.mask = bool(color), bool(mask)
        self.max_frames = None if max_frames is None else int(max_frames)
        cam = self.camera
        T = cam.T_world_cam
        rays = cam.ray_table().reshape(-1, 2).astype(np.float64)
        rays_cam = np.concatenate([rays, np.ones((len(rays), 1))], axis=1)
        self._origin = T[:3, 3].copy()
        # World ray directions with unit camera-z component: the ray parameter is the depth Z.
        self._dirs = rays_cam @ T[:3, :3].T
        self._projector = self._origin + self.baseline * T[:3, 0]

    def time_of(self, seq: int) -> float:
        """Timestamp (s) of frame ``seq``."""
        return self.start_time + seq / self.rate_hz

    def true_depth(self, t: float) -> np.ndarray:
        """Exact depth Z (m) along the optical axis per pixel at time ``t``, inf where no surface."""
        cam = self.camera
        return self.scene.cast(self._origin, self._dirs, t).reshape(cam.height, cam.width)

    def render(self, t: float, rng: Optional[np.random.Generator] = None):
        """(depth uint16 (H, W), color uint8 (H, W, 3) or None, mask uint8 (H, W) or None) at
        time ``t``; ``rng`` drives noise and holes (default: seeded by ``seed`` only)."""
        cam = self.camera
        rng = np.random.default_rng(self.seed) if rng is None else rng
        z = self.scene.cast(self._origin, self._dirs, t)
        hit = np.isfinite(z) & (z > 0)
        pts = self._origin + np.where(hit, z, 0.0)[:, None] * self._dirs
        valid = hit.copy()
        if self.shadows and hit.any():
            s = self.scene.cast(self._projector, pts[hit] - self._projector, t)
            valid[hit] = s >= 1.0 - 1e-6
        zm = np.where(valid, z, 1.0)
        if self.noise:
            zm = zm + cam.noise.sigma_z(zm) * rng.standard_normal(zm.shape)
        if self.quantize:
            fb = cam.fx * self.baseline
            disparity = np.round(fb / np.maximum(zm, 1e-6) / self.disparity_step) * self.disparity_step
            with np.errstate(divide="ignore"):
                zm = np.where(disparity > 0, fb / disparity, np.inf)
        if self.dropout > 0:
            valid &= rng.random(zm.shape) >= self.dropout
        valid &= (zm >= cam.z_min) & (zm <= cam.z_max)
        code = np.round(np.where(valid, zm, 0.0) / cam.depth_scale)
        code = np.where(valid & (code < cam.max_code), code, 0).astype(np.uint16)
        color = mask = None
        if self.color or self.mask:
            prot = np.zeros(len(z), dtype=bool)
            prot[hit] = self.scene.protected(pts[hit], t)
            if self.color:
                color = np.zeros((len(z), 3), dtype=np.uint8)
                color[hit] = WHITE
                color[prot] = RED
                color = color.reshape(cam.height, cam.width, 3)
            if self.mask:
                mask = prot.astype(np.uint8).reshape(cam.height, cam.width)
        return code.reshape(cam.height, cam.width), color, mask

    def _frame(self, seq: int) -> Optional[DepthFrame]:
        if self.max_frames is not None and seq >= self.max_frames:
            return None
        t = self.time_of(seq)
        depth, color, mask = self.render(t, np.random.default_rng([self.seed, seq]))
        return DepthFrame(self.camera.name, depth, t, seq, color=color, mask=mask)

    def __repr__(self) -> str:
        return f"SyntheticSource(scene={self.scene.name!r}, camera={self.camera.name!r}, rate_hz={self.rate_hz:g})"


__all__ = ["SyntheticSource", "default_camera", "look_at", "KINECT_BASELINE", "KINECT_DISPARITY_STEP"]
