"""The hand-eye log: robot poses and camera frames recorded together (``pointfence calib hand-eye``).

A log is a folder::

    LOG/
      camera.toml        the camera's intrinsics: one [[camera]] table with fx, fy, cx, cy, width,
                         height (px) and optionally dist (k1 k2 p1 p2 k3), depth_scale (m per
                         depth unit, default 0.001) and z_min/z_max (m; the depth range searched
                         for the tip): what `pointfence calib intrinsics --out` writes
      poses.csv          one row per pose: index, then the robot's measured_cp at that frame
                         (T_world_tip, world = robot base frame, metres) as 16 numbers row-major:
                         index,m00,m01,m02,m03,m10,...,m33   (a header line and # comments allowed)
      depth_0000.png     16-bit depth image of pose index 0 (units: depth_scale), for --method tip
      color_0000.png     8-bit colour (or IR/grey) image of pose index 0, registered to the depth
                         camera's view (same intrinsics), for --method aruco and --tip color

Frame files are named by the pose's index, zero-padded to 4 digits. Every pose row needs the frames
its method reads, and every frame file needs a pose row: a mismatch is an error naming the
indices. ``--intrinsics FILE`` replaces ``camera.toml``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

import numpy as np

from pointfence.kernels.camera import Camera, check_rigid
from pointfence.kernels.errors import InputError

POSES = "poses.csv"
CAMERA = "camera.toml"
KINDS = ("depth", "color")
_FRAME = re.compile(r"^(depth|color)_(\d+)\.png$")


def frame_name(kind: str, index: int) -> str:
    """File name of frame ``index`` of ``kind`` ("depth" or "color")."""
    return f"{kind}_{int(index):04d}.png"


@dataclass
class HandEyeLog:
    """A loaded log: ``camera`` (intrinsics), ``indices`` (N,), ``T_world_tip`` (N, 4, 4) the
    robot's measured_cp per pose (m), ``folder``. Frames are read on demand (``depth``, ``color``)."""

    folder: Path
    camera: Camera
    indices: np.ndarray
    T_world_tip: np.ndarray

    def path(self, kind: str, index: int) -> Path:
        return self.folder / frame_name(kind, index)

    def depth(self, index: int) -> np.ndarray:
        """The (H, W) uint16 depth image of pose ``index``."""
        return _read_png(self.path("depth", index), self.camera, 2)

    def color(self, index: int) -> np.ndarray:
        """The (H, W, 3) BGR or (H, W) grey uint8 image of pose ``index``."""
        return _read_png(self.path("color", index), self.camera, 1)


def _read_png(path: Path, camera: Camera, itemsize: int) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: missing or not a readable PNG")
    if img.shape[:2] != (camera.height, camera.width):
        raise InputError(f"{path}: {img.shape[1]}x{img.shape[0]}; expected {camera.width}x{camera.height} like the camera's "
                         "intrinsics (frames must be the calibrated camera's own view)")
    if img.dtype.itemsize != itemsize:
        want = "16-bit depth" if itemsize == 2 else "8-bit colour or grey"
        raise InputError(f"{path}: {img.dtype} pixels; expected {want}")
    return img


def read_camera(path, name: Optional[str] = None) -> Camera:
    """Intrinsics (and depth_scale) of camera ``name`` (or the only one) in a TOML file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"intrinsics {str(p)!r} not found; put the camera's [[camera]] table there "
                         "(`pointfence calib intrinsics ... --out` writes one) or pass --intrinsics FILE")
    try:
        doc = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{p}: not valid TOML ({e})") from None
    cams = doc.get("camera", [])
    pick = [c for c in cams if c.get("name") == name] if name else []
    if not pick:
        pick = cams if len(cams) == 1 else []
    if not pick:
        raise InputError(f"{p}: no [[camera]] named {name!r} (have {[c.get('name') for c in cams]}); pass --name")
    c = pick[0]
    missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in c]
    if missing:
        raise InputError(f"{p}: camera {c.get('name')!r} lacks {', '.join(missing)} (px); run `pointfence calib intrinsics` first")
    return Camera(str(c.get("name", name or "cam0")), int(c["width"]), int(c["height"]), float(c["fx"]), float(c["fy"]),
                  float(c["cx"]), float(c["cy"]), depth_scale=float(c.get("depth_scale", 0.001)),
                  dist=tuple(float(x) for x in c.get("dist", (0.0,) * 5)), z_min=float(c.get("z_min", 0.1)),
                  z_max=float(c.get("z_max", 10.0)))


def read_poses(path) -> tuple:
    """(indices (N,), T_world_tip (N, 4, 4)) from a poses CSV; every matrix must be rigid."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"pose file {str(p)!r} not found; a hand-eye log needs {POSES} (index + 16 numbers per row)")
    idx, mats = [], []
    header_seen = False
    for n, line in enumerate(p.read_text().splitlines(), 1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        parts = [x for x in re.split(r"[,\s]+", s) if x]
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            if not idx and not header_seen:
                header_seen = True
                continue  # the header
            raise InputError(f"{p}:{n}: {line.strip()!r}; expected index and 16 numbers (measured_cp row-major, m)") from None
        if len(vals) != 17:
            raise InputError(f"{p}:{n}: {len(vals)} values; expected 17 (index, then measured_cp's 16 numbers row-major, m)")
        if vals[0] != int(vals[0]) or vals[0] < 0:
            raise InputError(f"{p}:{n}: index {parts[0]!r}; expected a non-negative integer (the frames' number)")
        i = int(vals[0])
        if i in idx:
            raise InputError(f"{p}:{n}: index {i} appears twice")
        idx.append(i)
        mats.append(check_rigid(np.array(vals[1:]).reshape(4, 4), f"{p}:{n}: measured_cp of pose {i}", tol=1e-3))
    if not idx:
        raise InputError(f"{p}: no poses")
    return np.array(idx), np.array(mats)


def load_log(folder, kinds=("depth",), intrinsics=None, name: Optional[str] = None) -> HandEyeLog:
    """Read a log's camera and poses and check that the frames of ``kinds`` match the poses
    one to one (see the module docstring)."""
    f = Path(folder)
    if not f.is_dir():
        raise InputError(f"hand-eye log {str(f)!r} is not a folder; see `pointfence calib hand-eye --help` for its layout")
    camera = read_camera(intrinsics if intrinsics else f / CAMERA, name)
    indices, T = read_poses(f / POSES)
    have = {k: set() for k in KINDS}
    for q in f.iterdir():
        m = _FRAME.match(q.name)
        if m:
            have[m.group(1)].add(int(m.group(2)))
    want = set(indices.tolist())
    for k in kinds:
        missing, extra = sorted(want - have[k]), sorted(have[k] - want)
        if missing or extra:
            raise InputError(f"{f}: {len(want)} poses in {POSES} but {len(have[k])} {k} frames"
                             + (f"; poses without {k}_NNNN.png: {missing[:10]}" if missing else "")
                             + (f"; {k} frames without a pose row: {extra[:10]}" if extra else "")
                             + "; every pose needs its frame and every frame its measured_cp")
    return HandEyeLog(f, camera, indices, T)


def write_log(folder, camera: Camera, T_world_tip, depth=None, color=None) -> Path:
    """Write a log (poses 0..N-1; ``depth``/``color`` lists of images or None) into ``folder``,
    which must be new or empty."""
    import cv2

    from .output import camera_snippet

    f = Path(folder)
    if f.exists() and any(f.iterdir()):
        raise InputError(f"{f} is not empty; give a new folder for the log")
    f.mkdir(parents=True, exist_ok=True)
    keys = {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy, "width": camera.width,
            "height": camera.height, "depth_scale": camera.depth_scale, "dist": list(camera.dist)}
    (f / CAMERA).write_text(camera_snippet(camera.name, keys))
    rows = ["index," + ",".join(f"m{r}{c}" for r in range(4) for c in range(4))]
    rows += [f"{i}," + ",".join(repr(float(x)) for x in np.asarray(T).ravel()) for i, T in enumerate(T_world_tip)]
    (f / POSES).write_text("\n".join(rows) + "\n")
    for kind, images in (("depth", depth), ("color", color)):
        for i, img in enumerate(images or []):
            if not cv2.imwrite(str(f / frame_name(kind, i)), img):
                raise InputError(f"could not write {f / frame_name(kind, i)}")
    return f
