"""Camera-to-camera refinement by ICP: ``pointfence calib multi``.

Given depth frames of two cameras that see a common (static) part of the scene and a rough
``T_ref_cam`` (from markers, a tape measure, or the configuration), point-to-plane ICP aligns
the second camera's cloud onto the reference camera's cloud. The reference cloud's normals come
from its organised depth image; correspondences are nearest neighbours (scipy cKDTree) within a
distance that shrinks over the iterations (coarse to fine), with a Huber-like cut of outliers.
The result is written as the second camera's ``T_world_cam = T_world_ref @ T_ref_cam``.

Prints the RMS point-to-plane residual and the overlap (fraction of points with a partner):
a residual near the sensor noise and an overlap above ~30 % mean the alignment can be trusted.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pointfence.kernels.camera import Camera, check_rigid
from pointfence.kernels.errors import InputError

from .common import make_T, progress


def cloud_from_depth(depth: np.ndarray, camera: Camera, step: int = 1):
    """(points (N, 3) in camera coordinates, organised xyz (H', W', 3) with NaN holes) of a depth
    image, every ``step``-th pixel."""
    d = np.asarray(depth)
    if d.shape != (camera.height, camera.width):
        raise InputError(f"depth image {d.shape}; expected ({camera.height}, {camera.width}) for camera {camera.name!r}")
    rays = camera.ray_table()[::step, ::step].astype(np.float64)
    z = d[::step, ::step].astype(np.float64) * camera.depth_scale
    valid = (d[::step, ::step] > 0) & (d[::step, ::step] < camera.max_code) & (z >= camera.z_min) & (z <= camera.z_max)
    z = np.where(valid, z, np.nan)
    xyz = np.stack([rays[..., 0] * z, rays[..., 1] * z, z], axis=-1)
    return xyz[valid], xyz


def organised_normals(xyz: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) of an organised cloud from central differences (NaN where undefined),
    oriented towards the camera."""
    dx = np.full_like(xyz, np.nan)
    dy = np.full_like(xyz, np.nan)
    dx[:, 1:-1] = xyz[:, 2:] - xyz[:, :-2]
    dy[1:-1] = xyz[2:] - xyz[:-2]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
        flip = np.sum(n * xyz, axis=-1) > 0
    n[flip] *= -1
    # reject normals across depth discontinuities (long difference vectors)
    with np.errstate(invalid="ignore"):
        z = xyz[..., 2]
        jump = (np.linalg.norm(dx, axis=-1) > 0.05 * z) | (np.linalg.norm(dy, axis=-1) > 0.05 * z)
    n[jump] = np.nan
    return n


@dataclass
class ICPResult:
    T: np.ndarray  # T_ref_cam
    rms: float  # point-to-plane RMS residual of the inliers, m
    overlap: float  # fraction of source points with a partner within the final distance
    iterations: int
    history: list  # (max distance m, rms m, inliers) per iteration

    def report(self) -> str:
        trust = "good" if self.overlap > 0.3 and self.rms < 0.01 else "doubtful: check the overlap and the starting pose"
        return (f"ICP: {self.iterations} iterations, point-to-plane RMS {self.rms * 1000:.2f} mm over "
                f"{self.overlap * 100:.0f} % of the points ({trust})")


def icp(src: np.ndarray, dst: np.ndarray, dst_normals: np.ndarray, T_init, distances=(0.10, 0.05, 0.03, 0.02, 0.01),
        iters_per_distance: int = 8, tol: float = 1e-6, show_progress: bool = False,
        src_normals: Optional[np.ndarray] = None, max_normal_angle: float = 30.0) -> ICPResult:
    """Point-to-plane ICP: the T that maps ``src`` points (N, 3) onto the surface of ``dst`` (M, 3)
    with normals ``dst_normals`` (M, 3), starting from ``T_init``.

    With ``src_normals`` the residual is symmetric (along n_src + n_dst, Rusinkiewicz 2019) and
    pairs whose normals differ by more than ``max_normal_angle`` degrees are rejected: both keep
    ICP from sliding along large planes into a wrong minimum.
    """
    T = check_rigid(T_init, "ICP starting pose").copy()
    src = np.asarray(src, dtype=np.float64)
    if src_normals is not None:
        keep = np.all(np.isfinite(src_normals), axis=1)
        src, src_normals = src[keep], np.asarray(src_normals, dtype=np.float64)[keep]
    cos_max = np.cos(np.radians(max_normal_angle))
    ok = np.all(np.isfinite(dst_normals), axis=1) & np.all(np.isfinite(dst), axis=1)
    dst, nrm = np.asarray(dst, dtype=np.float64)[ok], np.asarray(dst_normals, dtype=np.float64)[ok]
    if len(src) < 100 or len(dst) < 100:
        raise InputError(f"ICP: {len(src)} source and {len(dst)} target points with normals; expected at least 100 each "
                         "(are the depth images empty or outside z_min..z_max?)")
    tree = cKDTree(dst)
    history = []
    schedule = [d for d in distances for _ in range(iters_per_distance)]
    it = 0
    rms = float("nan")
    frac = 0.0
    for dmax in progress(schedule, "ICP", enabled=show_progress):
        it += 1
        p = src @ T[:3, :3].T + T[:3, 3]
        dist, j = tree.query(p, distance_upper_bound=dmax)
        m = np.isfinite(dist)
        if m.sum() < 50:
            raise InputError(f"ICP: only {int(m.sum())} points within {dmax * 100:.0f} cm of the other cloud; the starting pose is "
                             "too far off or the views do not overlap")
        pm, q, n = p[m], dst[j[m]], nrm[j[m]]
        if src_normals is not None:
            ns = src_normals[m] @ T[:3, :3].T
            agree = np.sum(ns * n, axis=1) > cos_max
            pm, q, n, ns = pm[agree], q[agree], n[agree], ns[agree]
            n = n + ns
            n /= np.linalg.norm(n, axis=1, keepdims=True)
        r = np.sum((pm - q) * n, axis=1)
        # robust weights: cut residuals beyond 3 median absolute deviations
        mad = np.median(np.abs(r)) * 1.4826 + 1e-6
        w = (np.abs(r) < 3 * mad + 1e-4).astype(np.float64)
        A = np.concatenate([np.cross(pm, n), n], axis=1)
        Aw = A * w[:, None]
        x = np.linalg.lstsq(Aw.T @ A + 1e-9 * np.eye(6), -(Aw.T @ r), rcond=None)[0]
        dT = make_T(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:])
        T = dT @ T
        rms = float(np.sqrt(np.sum(w * r ** 2) / max(w.sum(), 1)))
        frac = float(m.mean())
        history.append((dmax, rms, int(w.sum())))
        if np.linalg.norm(x) < tol and dmax == distances[-1]:
            break
    return ICPResult(T, rms, frac, it, history)


def refine_pair(depth_ref: np.ndarray, cam_ref: Camera, depth_cam: np.ndarray, cam: Camera, T_ref_cam_rough,
                src_step: int = 4, dst_step: int = 2, **icp_options) -> ICPResult:
    """ICP of camera ``cam`` against camera ``cam_ref`` from one depth frame each; returns T_ref_cam."""
    _, sorg = cloud_from_depth(depth_cam, cam, src_step)
    snormals = organised_normals(sorg)
    svalid = np.all(np.isfinite(sorg), axis=-1)
    _, org = cloud_from_depth(depth_ref, cam_ref, dst_step)
    normals = organised_normals(org)
    valid = np.all(np.isfinite(org), axis=-1)
    return icp(sorg[svalid], org[valid], normals[valid], T_ref_cam_rough, src_normals=snormals[svalid], **icp_options)


# -- CLI ------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("--config", required=False, help="scene configuration with both cameras; the result updates --camera there")
    p.add_argument("--reference", help="name of the reference camera (its T_world_cam is kept)")
    p.add_argument("--camera", help="name of the camera to refine (its T_world_cam is the rough pose)")
    p.add_argument("--frames", type=int, default=1, help="frames of each camera to use (their clouds are merged; default 1)")
    p.add_argument("--demo", action="store_true", help="two frames of ../shared/data/7scenes_kitchen_50f as a two-camera rig, "
                                                        "starting 2 cm / 3 deg off")
    p.add_argument("--out", help="also write the refined [[camera]] snippet to this file")


def run(args) -> int:
    from .common import inv_T, pose_error, perturb
    from .output import camera_snippet, update_config, write_snippet

    if args.demo:
        from pathlib import Path

        from pointfence.service.sources import RecordedSource

        root = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes_kitchen_50f"
        if not root.is_dir():
            raise InputError(f"--demo needs {root} (the shared data folder beside the project)")
        rec = RecordedSource(root, name="ref", loop=False)
        d0, _, T0 = rec.load(20)  # frames 170 and 175: 19 mm / 3.2 deg apart
        d1, _, T1 = rec.load(25)
        cam = rec.camera
        T_true = inv_T(T0) @ T1
        T_rough = perturb(T_true, 0.02, 3.0, seed=1)
        res = refine_pair(d0, cam, d1, cam, T_rough, show_progress=True)
        print(res.report())
        e0, e1 = pose_error(T_rough, T_true), pose_error(res.T, T_true)
        print(f"# demo: start {e0[0] * 1000:.1f} mm / {e0[1]:.2f} deg off the recorded pose, after ICP "
              f"{e1[0] * 1000:.2f} mm / {e1[1]:.3f} deg")
        return 0
    if not (args.config and args.reference and args.camera):
        raise InputError("calib multi: pass --config scene.toml --reference NAME --camera NAME (or --demo)")
    from pointfence.service import config

    cfg = config.load(args.config)
    by = {c.camera.name: c for c in cfg.cameras}
    for n in (args.reference, args.camera):
        if n not in by:
            raise InputError(f"calib multi: no camera {n!r} in {args.config} (cameras: {sorted(by)})")
    ref, mov = by[args.reference], by[args.camera]
    depth = {}
    for c in (ref, mov):
        src = config_source(c)
        try:
            frames = [src.read() for _ in range(max(1, args.frames))]
        finally:
            src.close()
        frames = [f for f in frames if f is not None]
        if not frames:
            raise InputError(f"calib multi: camera {c.camera.name!r} delivered no frame")
        # several frames: the per-pixel median suppresses noise and flicker
        stack = np.stack([f.depth for f in frames]).astype(np.float64)
        stack[stack == 0] = np.nan
        with np.errstate(all="ignore"):
            med = np.nanmedian(stack, axis=0)
        depth[c.camera.name] = np.nan_to_num(med, nan=0).astype(np.uint16)
    T_ref_cam = inv_T(ref.camera.T_world_cam) @ mov.camera.T_world_cam
    res = refine_pair(depth[ref.camera.name], ref.camera, depth[mov.camera.name], mov.camera, T_ref_cam, show_progress=True)
    print(res.report())
    dt, dr = pose_error(res.T, T_ref_cam)
    print(f"correction to the rough pose: {dt * 1000:.1f} mm, {dr:.2f} deg")
    T_world = ref.camera.T_world_cam @ res.T
    snippet = camera_snippet(mov.camera.name, {"T_world_cam": T_world}, None,
                             f"pointfence calib multi: ICP against {ref.camera.name!r}, RMS {res.rms * 1000:.2f} mm")
    print(snippet, end="")
    if args.out:
        print(f"# {write_snippet(args.out, snippet)}")
    res = update_config(args.config, mov.camera.name, {"T_world_cam": T_world})
    print(f"# updated [[camera]] {mov.camera.name!r} in {args.config}; {res.describe(args.config)}")
    return 0


def config_source(c):
    from pointfence.service.sources import open_source

    return open_source(c.source, c.camera, **c.options)
