"""Axial noise model sigma_z = a + b Z^2 from captures of a plane: ``pointfence calib noise``.

Point the camera at a flat wall or table (matte, filling the central part of the image) at
several distances (at least two; five between the nearest and farthest working distance are
better) and capture a few frames at each. For every frame a plane is fitted to the central
region (least squares, then again without points beyond 3 sigma); the axial residual of each
pixel is its depth minus the plane's depth along the same ray. Per capture the residual
variance, less the depth-code quantisation (depth_scale^2 / 12), gives sigma_z at the mean
depth Z; a non-negative least-squares fit of sigma = a + b Z^2 over the captures gives a and b
(dissertation 6.2, eq. 6.1; SPEC section 1). Disparity quantisation of structured-light
sensors is part of what the sensor delivers and stays in the model. The captures' distinct depths
also give such a sensor's depth step in inverse depth (``service/depth_steps.py``): written as
``depth_step_inv`` where the depths come on disparity levels, for ``near_reading``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import nnls

from pointfence.kernels.camera import Camera, NoiseModel
from pointfence.kernels.errors import InputError

from .common import progress


@dataclass
class PlaneSample:
    label: str
    z: float  # mean depth of the plane's inliers, m
    sigma: float  # axial residual std (quantisation removed), m
    n: int  # inlier pixels
    tilt_deg: float  # angle between the plane normal and the optical axis


@dataclass
class NoiseFit:
    a: float
    b: float
    samples: list = field(default_factory=list)

    @property
    def model(self) -> NoiseModel:
        return NoiseModel(self.a, self.b)

    def report(self) -> str:
        lines = [f"noise model sigma_z = {self.a * 1000:.3f} mm + {self.b * 1000:.4f} mm/m^2 * Z^2  (a = {self.a:.3e} m, b = {self.b:.3e} 1/m)",
                 "   Z (m)   measured (mm)   model (mm)   residual   pixels   tilt"]
        for s in sorted(self.samples, key=lambda s: s.z):
            m = self.a + self.b * s.z ** 2
            lines.append(f"  {s.z:6.3f}   {s.sigma * 1000:13.3f}   {m * 1000:10.3f}   {100 * (s.sigma - m) / m:+7.1f} %  {s.n:7d}  {s.tilt_deg:5.1f}")
        return "\n".join(lines)


def plane_residuals(depth: np.ndarray, camera: Camera, roi: float = 0.5, label: str = "frame"):
    """(axial residuals (N,), depths (N,), unit normal) of the plane fitted to the central ``roi``
    fraction of a depth image."""
    d = np.asarray(depth)
    if d.shape != (camera.height, camera.width):
        raise InputError(f"{label}: depth {d.shape}; expected ({camera.height}, {camera.width}) for camera {camera.name!r}")
    h, w = d.shape
    y0, y1 = int(h * (1 - roi) / 2), int(h * (1 + roi) / 2)
    x0, x1 = int(w * (1 - roi) / 2), int(w * (1 + roi) / 2)
    rays = camera.ray_table()[y0:y1, x0:x1].reshape(-1, 2).astype(np.float64)
    code = d[y0:y1, x0:x1].reshape(-1)
    z = code.astype(np.float64) * camera.depth_scale
    ok = (code > 0) & (code < camera.max_code) & (z >= camera.z_min) & (z <= camera.z_max)
    need = max(200, int(0.05 * code.size))
    if ok.sum() < need:
        raise InputError(f"{label}: only {int(ok.sum())} valid depth pixels in the central {roi:.0%} of the image (need {need}); "
                         "degenerate plane fit: point the camera at a flat surface that fills the image centre, within z_min..z_max")
    r = np.concatenate([rays[ok], np.ones((ok.sum(), 1))], axis=1)
    z = z[ok]
    P = r * z[:, None]
    inl = np.ones(len(P), dtype=bool)
    for _ in range(3):
        c = P[inl].mean(axis=0)
        _, sv, vt = np.linalg.svd(P[inl] - c, full_matrices=False)
        if sv[1] < 1e-3 * sv[0] * np.sqrt(max(inl.sum(), 1)) / np.sqrt(inl.sum()) or sv[1] <= 1e-9:
            raise InputError(f"{label}: the valid points lie along a line (singular values {sv.round(6).tolist()}); "
                             "degenerate plane fit: the plane must cover a 2-D region of the image")
        n = vt[2]
        dist = (P - c) @ n
        s = 1.4826 * np.median(np.abs(dist[inl]))
        inl = np.abs(dist) < 3 * max(s, 1e-6)
    nr = r @ n
    if np.min(np.abs(nr[inl])) < 1e-3:
        raise InputError(f"{label}: the fitted plane contains the camera's rays (seen edge-on); degenerate plane fit: face the plane")
    z_plane = (c @ n) / nr
    res = (z - z_plane)[inl]
    tilt = float(np.degrees(np.arccos(min(1.0, abs(n[2])))))
    if tilt > 75:
        raise InputError(f"{label}: the plane is tilted {tilt:.0f} deg from the optical axis; degenerate plane fit: face the plane "
                         "(under about 45 deg)")
    return res, z[inl], n


def capture_frames(cap) -> list:
    """The depth images of one capture: a list of frames of one plane, or a single image."""
    return list(cap) if isinstance(cap, (list, tuple)) else [cap]


def fit_noise(captures: Sequence, camera: Camera, labels=None, roi: float = 0.5, show_progress: bool = True) -> NoiseFit:
    """Fit sigma_z = a + b Z^2. ``captures``: a list of depth images, or of lists of depth images
    (several frames of the same plane at one distance, pooled)."""
    labels = list(labels) if labels is not None else [f"capture {i}" for i in range(len(captures))]
    samples = []
    q2 = camera.depth_scale ** 2 / 12.0
    for cap, lab in progress(list(zip(captures, labels)), "fitting planes", enabled=show_progress):
        frames = capture_frames(cap)
        res, zs, tilts = [], [], []
        for k, f in enumerate(frames):
            r, z, n = plane_residuals(f, camera, roi, f"{lab}" + (f" frame {k}" if len(frames) > 1 else ""))
            res.append(r)
            zs.append(z)
            tilts.append(np.degrees(np.arccos(min(1.0, abs(n[2])))))
        r = np.concatenate(res)
        var = max(float(np.mean(r ** 2)) - q2, 0.0)
        samples.append(PlaneSample(lab, float(np.mean(np.concatenate(zs))), float(np.sqrt(var)), int(r.size), float(np.mean(tilts))))
    zs = np.array([s.z for s in samples])
    if len(samples) < 2 or zs.max() - zs.min() < 0.1 * zs.mean():
        raise InputError(f"noise fit: captures at depths {np.round(zs, 3).tolist()} m; a + b Z^2 needs planes at 2 or more distances "
                         "at least 10 % apart (e.g. 0.6, 1.0, 1.5, 2.0 m)")
    sig = np.array([s.sigma for s in samples])
    # relative (weighted) least squares: each capture counts by its relative error
    A = np.stack([np.ones_like(zs), zs ** 2], axis=1) / sig[:, None]
    (a, b), _ = nnls(A, np.ones_like(zs))
    return NoiseFit(float(a), float(b), samples)


def synthetic_captures(distances=(0.6, 1.0, 1.5, 2.0, 2.5), frames: int = 2, a: float = 0.0, b: float = 1.42e-3,
                       tilt_deg: float = 10.0, camera: Camera = None, seed: int = 0):
    """Depth frames of a flat table seen from ``distances`` (m) by the synthetic Kinect-like source
    with noise a + b Z^2 (no disparity quantisation), for tests and ``--demo``."""
    from pointfence.service.sources import SyntheticSource, default_camera

    out = []
    for k, zd in enumerate(distances):
        eye = (np.tan(np.radians(tilt_deg)) * zd, 0.0, zd)
        cam = default_camera("noise", eye=eye, width=320, height=240, noise=NoiseModel(a, b)) if camera is None else camera
        src = SyntheticSource("plane", cam, seed=seed + k, quantize=False, shadows=False, dropout=0.01)
        out.append([src.read().depth for _ in range(frames)])
        cam_used = src.camera
    return out, cam_used


# -- CLI ------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("captures", nargs="*", help="depth captures of a plane: one folder or 16-bit image per distance "
                                               "(a folder's frames are pooled)")
    p.add_argument("--intrinsics", help="TOML with this camera's intrinsics (from `calib intrinsics`), else 640x480 Kinect defaults")
    p.add_argument("--depth-scale", type=float, default=0.001, help="metres per depth unit of the images (default 0.001)")
    p.add_argument("--roi", type=float, default=0.5, help="central fraction of the image that sees the plane (default 0.5)")
    p.add_argument("--demo", action="store_true", help="fit synthetic captures of known noise (a=0, b=1.42e-3)")
    p.add_argument("--name", default="cam0", help="camera name of the [[camera]] entry (default cam0)")
    p.add_argument("--source", help="source spec for a new [[camera]] entry")
    p.add_argument("--out", help="also write the [[camera]] snippet to this file")
    p.add_argument("--config", help="merge the result into this scene configuration file (only the keys calibrated change; earlier versions kept as .bak, .bak.2, ...)")


def run(args) -> int:
    from dataclasses import replace
    from pathlib import Path

    from .output import emit

    if args.demo:
        captures, camera = synthetic_captures()
        labels = [f"plane {i}" for i in range(len(captures))]
    else:
        if len(args.captures) < 2:
            raise InputError("calib noise: pass captures of a plane at 2 or more distances (folders or depth images), or --demo")
        if args.intrinsics:
            from .extrinsics import camera_from_toml

            camera = replace(camera_from_toml(args.intrinsics, args.name), depth_scale=args.depth_scale)
        else:
            from pointfence.service.sources import default_camera

            camera = default_camera(args.name, depth_scale=args.depth_scale)
        from pointfence.service.sources.imagefiles import read_depth_image

        captures, labels = [], []
        for c in args.captures:
            p = Path(c)
            files = sorted(q for q in p.iterdir() if q.suffix.lower() in (".png", ".tif", ".tiff")) if p.is_dir() else [p]
            if not files:
                raise InputError(f"{p}: no 16-bit PNG/TIFF depth images in it")
            captures.append([read_depth_image(f) for f in files])
            labels.append(p.name)
    fit = fit_noise(captures, camera, labels, args.roi)
    print(fit.report())
    from pointfence.service.depth_steps import DepthSteps

    images = [np.asarray(f) for cap in captures for f in capture_frames(cap)]
    steps = DepthSteps.fit_frames(images, camera.depth_scale, camera.max_code)
    print(f"depth steps: {steps.describe()}")
    keys = {"noise": {"a": fit.a, "b": fit.b}}
    if steps.disparity:
        keys["depth_step_inv"] = round(steps.inv_step, 7)
    emit(args, args.name, keys,
         f"pointfence calib noise: {len(fit.samples)} distances {min(s.z for s in fit.samples):.2f}-{max(s.z for s in fit.samples):.2f} m")
    return 0
