"""Finding the frames, poses and intrinsics of a recorded depth sequence on disk.

Layouts (auto-detected from a folder, or from a single file and its folder):

* ``tsdf``  (7-Scenes, APC / tsdf-fusion): ``frame-*.depth.png`` (16-bit, mm), optional
  ``frame-*.pose.txt`` (4x4 camera-to-world, m) and ``frame-*.color.png``; intrinsics from a
  3x3 ``camera-intrinsics.txt`` / ``intrinsics.K.txt`` / ``*intrinsics*.txt`` in the folder or
  its parent.
* ``tiff``  (PCL ImageGrabber): ``*_depth.tif(f)`` (16-bit, mm); intrinsics and depth scale
  from the matching ``*.xml`` in the folder or in a sibling ``pclzf/`` folder.
* ``pclzf`` (PCL ImageGrabber): ``*_depth.pclzf`` with the matching ``*.xml``.
* ``pcd``   organised PCD clouds (metres, NaN = no data); intrinsics fitted from the points.
* ``png``   any other 16-bit PNGs; intrinsics from a ``*intrinsics*.txt`` or the options.

Frames are sorted by file name. Options ``fx, fy, cx, cy`` (px) and ``depth_scale`` (m per
unit) override what the files say.
"""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from pointfence.kernels.camera import check_rigid
from pointfence.kernels.errors import InputError

LAYOUTS = ("tsdf", "tiff", "pclzf", "pcd", "png")


@dataclass
class Recording:
    """What is on disk: frame files, per-frame pose/colour files (None where absent),
    intrinsics (fx, fy, cx, cy) in px or None (fitted from the first PCD), depth scale (m)."""

    folder: Path
    layout: str
    frames: list
    poses: list = field(default_factory=list)
    colors: list = field(default_factory=list)
    intrinsics: Optional[tuple] = None
    depth_scale: float = 0.001
    source_of_intrinsics: str = ""


def _frame_files(folder: Path) -> dict:
    files = sorted(p for p in folder.iterdir() if p.is_file())
    low = lambda p: p.name.lower()  # noqa: E731
    is_rgb = lambda p: "rgb" in low(p) or "color" in low(p) or "colour" in low(p)  # noqa: E731
    kinds = {
        "tsdf": [p for p in files if low(p).endswith(".depth.png")],
        "pcd": [p for p in files if low(p).endswith(".pcd")],
        "tiff": [p for p in files if low(p).endswith((".tif", ".tiff")) and not is_rgb(p)],
        "pclzf": [p for p in files if low(p).endswith(".pclzf") and not is_rgb(p)],
    }
    kinds["png"] = [p for p in files if low(p).endswith(".png") and not is_rgb(p) and p not in kinds["tsdf"]]
    if kinds["tsdf"]:
        kinds["png"] = []
    return {k: v for k, v in kinds.items() if v}


def _stem(p: Path) -> str:
    """File name without the depth suffix: frame-000150.depth.png -> frame-000150,
    frame_X_depth.tiff -> frame_X."""
    name = p.name
    for suf in (".depth.png",):
        if name.lower().endswith(suf):
            return name[: -len(suf)]
    return re.sub(r"[_.-]depth$", "", p.stem, flags=re.I)


def read_matrix(path: Path, shape: tuple, what: str) -> np.ndarray:
    """Whitespace/comma separated numbers from a text file, reshaped to ``shape``."""
    try:
        text = path.read_text()
    except OSError as e:
        raise InputError(f"{path}: cannot read {what} ({e.strerror})") from None
    try:
        vals = np.array([float(v) for v in re.split(r"[\s,;]+", text.strip()) if v], dtype=np.float64)
    except ValueError:
        raise InputError(f"{path}: {what} contains non-numbers; expected {np.prod(shape)} numbers") from None
    if vals.size != int(np.prod(shape)):
        raise InputError(f"{path}: {vals.size} numbers; expected {what} as {np.prod(shape)} numbers ({shape[0]}x{shape[-1]})")
    return vals.reshape(shape)


#: Largest |R R^T - I| of a stored pose that is repaired rather than rejected. Real tracked
#: poses drift slightly off SO(3) (7-Scenes: up to ~2e-4), which check_rigid refuses.
POSE_REPAIR_TOL = 1e-2


def read_pose(path: Path) -> np.ndarray:
    """A 4x4 camera-to-world pose (m) from a text file. A rotation part that is off by at most
    ``POSE_REPAIR_TOL`` is projected onto the nearest rotation (SVD); worse is an InputError."""
    T = read_matrix(path, (4, 4), "a 4x4 pose")
    R = T[:3, :3]
    if np.all(np.isfinite(R)) and np.abs(R @ R.T - np.eye(3)).max() <= POSE_REPAIR_TOL and np.linalg.det(R) > 0:
        U, _, Vt = np.linalg.svd(R)
        T[:3, :3] = U @ Vt
    return check_rigid(T, f"{path}: pose")


def _intrinsics_txt(folder: Path) -> Optional[tuple]:
    for where in (folder, folder.parent):
        cands = [where / "camera-intrinsics.txt", where / "intrinsics.K.txt"]
        cands += sorted(p for p in where.glob("*intrinsic*.txt") if p not in cands)
        for p in cands:
            if p.is_file():
                K = read_matrix(p, (3, 3), "a 3x3 intrinsic matrix")
                return (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), str(p)
    return None


def _pcl_xml(frame: Path) -> Optional[tuple]:
    """(fx, fy, cx, cy), depth_scale, path from the PCL ImageGrabber xml of ``frame``."""
    stem = _stem(frame)
    for where in (frame.parent, frame.parent.parent / "pclzf"):
        p = where / f"{stem}.xml"
        if not p.is_file():
            continue
        try:
            root = ET.fromstring("<root>" + re.sub(r"<\?xml[^>]*\?>", "", p.read_text()) + "</root>")
            d = root.find("depth")
            if d is None:
                d = root.find("rgb")
            get = lambda k: float(d.find(k).text)  # noqa: E731
            k = (get("focal_length_x"), get("focal_length_y"), get("principal_point_x"), get("principal_point_y"))
            zf = d.find("z_multiplication_factor")
            return k, (float(zf.text) if zf is not None else None), str(p)
        except (ET.ParseError, AttributeError, ValueError, TypeError) as e:
            raise InputError(f"{p}: cannot parse camera parameters ({e}); expected <depth><focal_length_x>... as PCL writes") from None
    return None


def scan_recording(path, layout: Optional[str] = None, fx=None, fy=None, cx=None, cy=None, depth_scale=None) -> Recording:
    """Find the frames and metadata of the recording at ``path`` (a folder or one frame file)."""
    path = Path(path).expanduser()
    if not path.exists():
        raise InputError(f"recording {path}: no such file or folder; expected a folder of depth frames or one frame file")
    if path.is_dir():
        folder, kinds = path, _frame_files(path)
    else:
        folder, kinds = path.parent, {k: [path] for k, v in _frame_files(path.parent).items() if path in v}
        if not kinds:
            raise InputError(f"recording {path}: not a depth frame file; expected .depth.png, .png, .tif(f), .pclzf or .pcd")
    if layout is not None:
        if layout not in LAYOUTS:
            raise InputError(f"layout = {layout!r}; expected one of {', '.join(LAYOUTS)}")
        kinds = {layout: kinds.get(layout, [])}
    kinds = {k: v for k, v in kinds.items() if v}
    if not kinds:
        subs = sorted(p.name for p in folder.iterdir() if p.is_dir() and _frame_files(p))
        hint = f"; its subfolders {', '.join(subs)} hold frames: open one of them (e.g. recorded:{folder / subs[0]})" if subs else ""
        want = f"{layout} frames" if layout else "depth frames (*.depth.png, *.png, *.tif(f), *.pclzf, *.pcd)"
        raise InputError(f"recording {folder}: no {want} found{hint}")
    if len(kinds) > 1:
        raise InputError(
            f"recording {folder}: holds several kinds of frames ({', '.join(kinds)}); choose one with the option layout=<kind>"
        )
    (kind, frames), = kinds.items()
    rec = Recording(folder, kind, frames)
    rec.poses = [q if (q := f.parent / f"{_stem(f)}.pose.txt").is_file() else None for f in frames]
    if kind == "tsdf":
        rec.colors = [q if (q := f.parent / f"{_stem(f)}.color.png").is_file() else None for f in frames]
    elif kind in ("tiff", "pclzf"):
        rec.colors = [next((q for q in f.parent.glob(f"{_stem(f)}_rgb.tif*")), None) for f in frames]
    else:
        rec.colors = [None] * len(frames)
    found = None
    if kind in ("tiff", "pclzf"):
        xml = _pcl_xml(frames[0])
        if xml is not None:
            k, zscale, src = xml
            found = (k, src)
            if zscale:
                rec.depth_scale = zscale
    if found is None and kind != "pcd":
        found = _intrinsics_txt(folder)
    if found is not None:
        rec.intrinsics, rec.source_of_intrinsics = tuple(float(v) for v in found[0]), found[1]
    if fx is not None or cx is not None or cy is not None or fy is not None:
        if fx is None or cx is None or cy is None:
            raise InputError(f"intrinsics options fx={fx}, fy={fy}, cx={cx}, cy={cy}; expected at least fx, cx and cy in pixels (fy defaults to fx)")
        rec.intrinsics = (float(fx), float(fx if fy is None else fy), float(cx), float(cy))
        rec.source_of_intrinsics = "options"
    if rec.intrinsics is None and kind != "pcd":
        raise InputError(
            f"recording {folder}: no intrinsics found (looked for camera-intrinsics.txt, intrinsics.K.txt, "
            "*intrinsic*.txt and PCL *.xml beside the frames); pass fx, fy, cx, cy options (pixels) or a camera"
        )
    if depth_scale is not None:
        if not float(depth_scale) > 0:
            raise InputError(f"depth_scale = {depth_scale!r}; expected > 0 m per depth unit (0.001 for mm)")
        rec.depth_scale = float(depth_scale)
    return rec
