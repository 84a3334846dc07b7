"""Depth camera model: intrinsics, distortion, pose in the world, noise and validity.

Frames: camera coordinates are x right, y down, z forward (optical axis), metres.
``T_world_cam`` maps camera coordinates to the world (robot base) frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError

#: Kinect-class axial noise, sigma_z = a + b * Z^2 (dissertation 2.1.3, SPEC 1).
KINECT_NOISE_A = 0.0
KINECT_NOISE_B = 1.42e-3


@dataclass(frozen=True)
class NoiseModel:
    """Axial depth noise sigma_z = a + b * Z^2, with a in m and b in 1/m."""

    a: float = KINECT_NOISE_A
    b: float = KINECT_NOISE_B

    def sigma_z(self, z):
        """Standard deviation of a depth reading at depth ``z`` (m)."""
        return self.a + self.b * np.asarray(z) ** 2


@dataclass(frozen=True)
class Camera:
    """One depth camera.

    Attributes:
        name: unique name; its index in the rig is the point's camera id.
        width, height: image size in pixels.
        fx, fy, cx, cy: pinhole intrinsics of the depth image, pixels.
        depth_scale: metres per depth unit (0.001 for millimetre images).
        T_world_cam: 4x4 rigid transform, camera -> world.
        dist: Brown-Conrady coefficients (k1, k2, p1, p2, k3), OpenCV order.
        noise: axial noise model.
        z_min, z_max: valid depth range, m; readings outside are dropped.
        max_code: the sensor's "no reading" saturation code (dropped, as is 0).
        depth_step_inv: a disparity camera's depth step in inverse depth, 1/m (its readings
            come on levels of 1/z this far apart: inv_step * z^2 m apart in depth; a Kinect v1
            0.0029, 9 mm at 1.8 m); 0: the readings are one code (``depth_scale``) apart.
        near_reading: take each reading at the near end of the depth step it stands for,
            z - max(depth_scale, depth_step_inv z^2) / 2 (``near_bias``): the true surface lies
            within half a step of the reading along the ray, so a fixture built on readings
            moved this way is not entered through the sensor's quantisation; it stands half a
            step further from the surface (submittance).
    """

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = 0.001
    T_world_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    dist: tuple = (0.0, 0.0, 0.0, 0.0, 0.0)
    noise: NoiseModel = NoiseModel()
    z_min: float = 0.1
    z_max: float = 10.0
    max_code: int = 65535
    depth_step_inv: float = 0.0
    near_reading: bool = False

    def __post_init__(self):
        for key in ("width", "height"):
            v = getattr(self, key)
            if not isinstance(v, (int, np.integer)) or v <= 0:
                raise InputError(f"camera {self.name!r}: {key} = {v!r}; expected a positive integer")
        for key in ("fx", "fy", "cx", "cy", "depth_scale", "z_min", "z_max"):
            v = getattr(self, key)
            if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v):
                raise InputError(f"camera {self.name!r}: {key} = {v!r}; expected a finite number")
        if self.fx <= 0 or self.fy <= 0:
            raise InputError(f"camera {self.name!r}: focal lengths fx={self.fx}, fy={self.fy}; expected > 0 pixels")
        if self.depth_scale <= 0:
            raise InputError(f"camera {self.name!r}: depth_scale = {self.depth_scale}; expected > 0 m per unit")
        if not 0 <= self.z_min < self.z_max:
            raise InputError(f"camera {self.name!r}: z range [{self.z_min}, {self.z_max}]; expected 0 <= z_min < z_max")
        dist = tuple(float(d) for d in self.dist)
        if len(dist) != 5 or not all(math.isfinite(d) for d in dist):
            raise InputError(f"camera {self.name!r}: dist = {self.dist!r}; expected 5 finite numbers (k1, k2, p1, p2, k3)")
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "T_world_cam", check_rigid(self.T_world_cam, f"camera {self.name!r}: T_world_cam"))
        if not (math.isfinite(self.noise.a) and math.isfinite(self.noise.b)) or self.noise.a < 0 or self.noise.b < 0:
            raise InputError(f"camera {self.name!r}: noise = {self.noise}; expected finite a >= 0, b >= 0")
        if not 0 < int(self.max_code) <= 65535:
            raise InputError(f"camera {self.name!r}: max_code = {self.max_code}; expected 1..65535")
        v = self.depth_step_inv
        if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v) or not 0 <= v < 1.0:
            raise InputError(f"camera {self.name!r}: depth_step_inv = {v!r}; expected a finite step in inverse depth "
                             "0 <= step < 1 1/m (0: readings one code apart; a Kinect v1: about 0.0029)")
        if not isinstance(self.near_reading, (bool, np.bool_)):
            raise InputError(f"camera {self.name!r}: near_reading = {self.near_reading!r}; expected true or false")

    @property
    def near_bias(self) -> tuple:
        """(a m, b 1/m): a reading z is taken at z - max(a, b z^2), the near end of its depth
        step with ``near_reading`` (half a code, half the disparity step), else (0, 0): as read."""
        if not self.near_reading:
            return 0.0, 0.0
        return 0.5 * float(self.depth_scale), 0.5 * float(self.depth_step_inv)

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def ray_table(self) -> np.ndarray:
        """Undistorted normalised rays (x/z, y/z) for every pixel centre, shape (H, W, 2), float32.

        Pixel (u, v) has its centre at integer coordinates, as OpenCV's. With distortion the
        Brown-Conrady model is inverted by fixed-point iteration (as cv::undistortPoints) to
        below 1e-9 in normalised coordinates; the table is built once per camera, so the
        per-frame kernels only look rays up.
        """
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        xd = (u - self.cx) / self.fx
        yd = (v - self.cy) / self.fy
        x, y = xd.copy(), yd.copy()
        if any(self.dist):
            k1, k2, p1, p2, k3 = self.dist
            for _ in range(100):
                r2 = x * x + y * y
                radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
                dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
                dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
                xn = (xd - dx) / radial
                yn = (yd - dy) / radial
                step = max(np.abs(xn - x).max(), np.abs(yn - y).max())
                x, y = xn, yn
                if step < 1e-12:
                    break
        return np.stack([x, y], axis=-1).astype(np.float32)

    def with_pose(self, T_world_cam) -> "Camera":
        """A copy of this camera at another pose."""
        from dataclasses import replace

        return replace(self, T_world_cam=np.asarray(T_world_cam, dtype=np.float64))


def check_rigid(T, what: str, tol: float = 1e-4) -> np.ndarray:
    """Validate a 4x4 rigid transform and return it as float64.

    Raises InputError naming ``what`` when the matrix has the wrong shape, is not finite,
    has a rotation part that is not orthonormal with determinant +1 (within ``tol``), or a
    bottom row other than (0, 0, 0, 1).
    """
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{what}: {e}; expected a 4x4 numeric matrix") from None
    if T.shape == (16,):
        T = T.reshape(4, 4)
    if T.shape != (4, 4):
        raise InputError(f"{what}: shape {T.shape}; expected 4x4 (or 16 numbers, row-major)")
    if not np.all(np.isfinite(T)):
        raise InputError(f"{what}: contains NaN or infinity; expected a finite rigid transform")
    R = T[:3, :3]
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > tol or abs(np.linalg.det(R) - 1) > tol:
        raise InputError(
            f"{what}: rotation part is not a rotation (|R R^T - I| = {err:.2e}, det = {np.linalg.det(R):.4f}); "
            "expected an orthonormal matrix with det +1 (no scale, shear or reflection)"
        )
    if np.abs(T[3] - [0, 0, 0, 1]).max() > tol:
        raise InputError(f"{what}: bottom row {T[3].tolist()}; expected [0, 0, 0, 1]")
    return T
