"""Intrinsics from checkerboard images (OpenCV): ``pointfence calib intrinsics IMAGES...``.

Images are the depth camera's own view (its IR image, or a colour image registered to the
depth image). The board has ``cols`` x ``rows`` *inner* corners and squares of ``square``
metres. Prints the RMS reprojection error and the worst views: below about 0.5 px is a good
calibration; a view far above the rest is usually a blurred or mis-detected board.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError

from .common import progress


@dataclass
class IntrinsicsResult:
    width: int
    height: int
    K: np.ndarray
    dist: tuple  # k1, k2, p1, p2, k3
    rms: float  # px, over all corners
    per_view: list  # RMS reprojection error (px) of each used view
    used: list  # labels of the views with a board
    skipped: list = field(default_factory=list)  # labels of the views without one
    std: tuple = ()  # 1-sigma uncertainty of fx, fy, cx, cy (px) from the fit

    def camera_keys(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": float(self.K[0, 0]), "fy": float(self.K[1, 1]),
                "cx": float(self.K[0, 2]), "cy": float(self.K[1, 2]), "dist": [float(d) for d in self.dist]}

    def camera(self, name: str = "cam0", **kw) -> Camera:
        k = self.camera_keys()
        return Camera(name, k["width"], k["height"], k["fx"], k["fy"], k["cx"], k["cy"], dist=tuple(k["dist"]), **kw)

    def report(self) -> str:
        lines = [f"intrinsics from {len(self.used)} views ({len(self.skipped)} without a board): "
                 f"fx={self.K[0, 0]:.2f} fy={self.K[1, 1]:.2f} cx={self.K[0, 2]:.2f} cy={self.K[1, 2]:.2f} px, "
                 f"dist={[round(d, 5) for d in self.dist]}",
                 f"reprojection RMS {self.rms:.3f} px ({'good' if self.rms < 0.5 else 'check the worst views' if self.rms < 1.5 else 'poor: do not trust it'})"]
        if self.std:
            lines.append("1-sigma uncertainty: " + ", ".join(f"{k} {v:.2f}" for k, v in zip(("fx", "fy", "cx", "cy"), self.std)) + " px")
        worst = sorted(zip(self.per_view, self.used), reverse=True)[:3]
        lines.append("worst views: " + ", ".join(f"{lab} {e:.3f} px" for e, lab in worst))
        if self.skipped:
            lines.append("no board found in: " + ", ".join(self.skipped))
        return "\n".join(lines)


def board_points(cols: int, rows: int, square: float) -> np.ndarray:
    """Inner-corner coordinates (cols*rows, 3) in the board frame, OpenCV's corner order."""
    gx, gy = np.meshgrid(np.arange(cols), np.arange(rows))
    return np.stack([gx.ravel() * square, gy.ravel() * square, np.zeros(gx.size)], axis=1).astype(np.float32)


def find_corners(image: np.ndarray, cols: int, rows: int) -> Optional[np.ndarray]:
    """Sub-pixel inner corners (cols*rows, 2) of a checkerboard, or None when not found."""
    import cv2

    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if gray.dtype != np.uint8:
        gray = cv2.normalize(gray, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    # The classic detector + cornerSubPix is unbiased under strong perspective; the sector-based
    # detector finds boards the classic one misses (blur, uneven light), so it is the fallback.
    ok, corners = cv2.findChessboardCorners(gray, (cols, rows), flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        ok, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=cv2.CALIB_CB_ACCURACY)
        if not ok:
            return None
    corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4))
    return corners.reshape(-1, 2)


def calibrate(images: Sequence[np.ndarray], cols: int, rows: int, square: float, labels: Optional[Sequence[str]] = None,
              fix_k3: bool = True, show_progress: bool = True) -> IntrinsicsResult:
    """Calibrate from checkerboard ``images`` (uint8 grey or BGR, one size)."""
    import cv2

    if cols < 2 or rows < 2 or not square > 0:
        raise InputError(f"checkerboard {cols}x{rows} inner corners, square {square} m; expected at least 2x2 corners and square > 0")
    labels = list(labels) if labels is not None else [f"image {i}" for i in range(len(images))]
    if not len(images):
        raise InputError("calib intrinsics: no images given; pass checkerboard images (PNG/JPG) of the depth camera's view")
    shape = images[0].shape[:2]
    obj = board_points(cols, rows, square)
    objpts, imgpts, used, skipped = [], [], [], []
    for img, lab in progress(list(zip(images, labels)), "finding checkerboards", enabled=show_progress):
        if img.shape[:2] != shape:
            raise InputError(f"{lab}: size {img.shape[1]}x{img.shape[0]}; expected {shape[1]}x{shape[0]} like the first image")
        c = find_corners(img, cols, rows)
        if c is None:
            skipped.append(lab)
            continue
        objpts.append(obj)
        imgpts.append(c.astype(np.float32).reshape(-1, 1, 2))
        used.append(lab)
    if not used:
        raise InputError(f"no checkerboard of {cols}x{rows} inner corners found in any of the {len(images)} images; check --cols/--rows "
                         "(count inner corners, not squares), focus and lighting")
    if len(used) < 3:
        raise InputError(f"a checkerboard was found in only {len(used)} image(s) ({', '.join(used)}); at least 3 views at different "
                         "tilts are needed")
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    h, w = shape
    rms, K, dist, rvecs, tvecs, std, _, _ = cv2.calibrateCameraExtended(objpts, imgpts, (w, h), None, None, flags=flags)
    per_view = []
    for o, ip, r, t in zip(objpts, imgpts, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        per_view.append(float(np.sqrt(np.mean(np.sum((proj - ip) ** 2, axis=-1)))))
    d = np.asarray(dist, dtype=np.float64).ravel()[:5]
    d = np.concatenate([d, np.zeros(5 - len(d))])
    return IntrinsicsResult(w, h, K, tuple(float(x) for x in d), float(rms), per_view, used, skipped,
                            tuple(float(x) for x in np.asarray(std).ravel()[:4]))


def read_images(paths) -> tuple:
    """(images, labels) from image files; errors name the unreadable file."""
    import cv2

    imgs, labels = [], []
    files = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            files += sorted(q for q in p.iterdir() if q.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"))
        else:
            files.append(p)
    for f in files:
        if not f.is_file():
            raise InputError(f"image {str(f)!r} not found")
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"image {str(f)!r} could not be decoded; expected PNG, JPEG, BMP or TIFF")
        if img.ndim == 3:
            img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
        imgs.append(img)
        labels.append(f.name)
    return imgs, labels


# -- CLI -----------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("images", nargs="*", help="checkerboard images (files or folders) of the depth camera's view")
    p.add_argument("--cols", type=int, default=9, help="inner corners along the board's width (default 9)")
    p.add_argument("--rows", type=int, default=6, help="inner corners along the board's height (default 6)")
    p.add_argument("--square", type=float, default=0.025, help="square side, m (default 0.025)")
    p.add_argument("--k3", action="store_true", help="also fit the 6th-order radial term k3 (wide-angle lenses)")
    p.add_argument("--demo", action="store_true", help="calibrate synthetic renders of a known camera instead of images")
    _output_arguments(p)


def _output_arguments(p) -> None:
    p.add_argument("--name", default="cam0", help="camera name of the [[camera]] entry (default cam0)")
    p.add_argument("--source", help="source spec for a new [[camera]] entry, e.g. openni2:any")
    p.add_argument("--out", help="also write the [[camera]] snippet to this file")
    p.add_argument("--config", help="merge the result into this scene configuration file (only the keys calibrated change; earlier versions kept as .bak, .bak.2, ...)")


def run(args) -> int:
    from .output import emit

    if args.demo:
        from .render import checkerboard_views

        truth = Camera("truth", 640, 480, 600.0, 602.0, 322.0, 241.0, dist=(-0.08, 0.05, 0.0005, -0.0004, 0.0))
        images, _ = checkerboard_views(truth, args.cols, args.rows, args.square, n=12)
        labels = [f"render {i}" for i in range(len(images))]
        print(f"# demo: renders of fx=600 fy=602 cx=322 cy=241 dist={list(truth.dist)}")
    else:
        if not args.images:
            raise InputError("calib intrinsics: no images given; pass image files or a folder (or --demo)")
        images, labels = read_images(args.images)
    res = calibrate(images, args.cols, args.rows, args.square, labels, fix_k3=not args.k3)
    print(res.report())
    emit(args, args.name, res.camera_keys(), f"pointfence calib intrinsics: {len(res.used)} views, reprojection RMS {res.rms:.3f} px")
    return 0
