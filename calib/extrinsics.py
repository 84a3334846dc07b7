"""Camera-to-robot-base extrinsics (``T_world_cam``; the world frame is the robot base).

Two ways:

* **markers** (``pointfence calib extrinsics --layout markers.toml IMAGES...``): ArUco or AprilTag
  markers fixed at known poses in the base frame (dissertation 3.5.2 used AR markers at fixed
  poses). Each image gives one pose from all visible marker corners at once (PnP); the per-image
  poses pass through the dissertation's low-pass filter (``LowPassPose``), and frames whose
  reprojection error is far above the others are dropped first. Images are the depth camera's
  view (IR image or colour registered to depth) and use its intrinsics.
* **points** (``--points pairs.csv``): the same physical points measured in the camera frame
  (e.g. picked in the point cloud) and in the base frame (e.g. touched with the robot's tool
  tip); the rigid fit is Kabsch's (SVD), with per-point residuals.

The marker layout file (TOML)::

    dictionary = "DICT_4X4_50"     # any cv2.aruco predefined dictionary, e.g. DICT_APRILTAG_36h11
    size = 0.06                    # marker side (the black square), m; a marker may override it
    [[marker]]
    id = 3
    position = [0.30, 0.10, 0.0]   # marker centre in the base frame, m
    rotation_deg = [0, 0, 90]      # extrinsic x-y-z Euler angles, deg (or T_base_marker = 16 numbers)

The marker frame is OpenCV's: origin at the marker centre, x right, y up (as printed), z out of
the marker towards the viewer.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

import numpy as np
from scipy.spatial.transform import Rotation

from pointfence.kernels.camera import Camera, check_rigid
from pointfence.kernels.errors import InputError

from .common import inv_T, make_T, pose_error, progress


# -- the low-pass filter on the transform ---------------------------------------------------
class LowPassPose:
    """First-order low-pass filter on a rigid transform (dissertation 3.5.2).

    Translation: t += a (t_meas - t); rotation: R = R exp(a log(R^T R_meas)) (the same step on
    the rotation manifold). The gain starts as 1/k (a running mean of the first frames, so a
    calibration of N frames is their average) and settles at ``alpha`` (an exponential filter with
    time constant 1/alpha frames) for live re-registration.
    """

    def __init__(self, alpha: float = 0.1):
        if not 0 < alpha <= 1:
            raise InputError(f"low-pass alpha = {alpha!r}; expected 0 < alpha <= 1 (the filter gain per frame)")
        self.alpha = float(alpha)
        self.T: Optional[np.ndarray] = None
        self.count = 0

    def update(self, T_meas) -> np.ndarray:
        T_meas = check_rigid(T_meas, "LowPassPose.update: measured transform")
        self.count += 1
        a = max(1.0 / self.count, self.alpha)
        if self.T is None:
            self.T = T_meas.copy()
            return self.T.copy()
        R = self.T[:3, :3]
        dR = Rotation.from_matrix(R.T @ T_meas[:3, :3]).as_rotvec()
        R_new = R @ Rotation.from_rotvec(a * dR).as_matrix()
        t_new = self.T[:3, 3] + a * (T_meas[:3, 3] - self.T[:3, 3])
        self.T = make_T(R_new, t_new)
        return self.T.copy()


# -- Kabsch ---------------------------------------------------------------------------------
@dataclass
class RigidFit:
    T: np.ndarray  # maps the "from" points onto the "to" points
    residuals: np.ndarray  # per point, m
    rms: float

    def report(self, what: str = "points") -> str:
        r = self.residuals
        worst = int(np.argmax(r))
        return (f"rigid fit of {len(r)} {what}: RMS residual {self.rms * 1000:.2f} mm, max {r.max() * 1000:.2f} mm "
                f"(point {worst}){' - check that point' if r.max() > 3 * max(self.rms, 1e-4) else ''}")


def kabsch(P_from, P_to) -> RigidFit:
    """Least-squares rigid transform T with T @ P_from ~ P_to (Kabsch/Umeyama without scale)."""
    A = np.asarray(P_from, dtype=np.float64)
    B = np.asarray(P_to, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 3 or A.shape != B.shape:
        raise InputError(f"point correspondences: shapes {A.shape} and {B.shape}; expected two (N, 3) arrays of the same N")
    if len(A) < 3:
        raise InputError(f"point correspondences: {len(A)} pairs; at least 3 non-collinear pairs are needed (6 or more advised)")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
        raise InputError("point correspondences contain NaN or infinity")
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    sv = np.linalg.svd(A - ca, compute_uv=False)
    if sv[1] < 1e-6 * max(sv[0], 1e-12) or sv[1] < 1e-4:
        raise InputError(f"point correspondences are (nearly) collinear (spread {sv.round(5).tolist()} m); "
                         "use at least 3 points that span a triangle, ideally spread over the workspace")
    H = (A - ca).T @ (B - cb)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = make_T(R, cb - R @ ca)
    res = np.linalg.norm(A @ R.T + T[:3, 3] - B, axis=1)
    return RigidFit(T, res, float(np.sqrt(np.mean(res ** 2))))


def read_point_pairs(path) -> tuple:
    """(P_cam, P_base) from a CSV/whitespace file of rows x_cam y_cam z_cam x_base y_base z_base (m);
    lines starting with # and a header line are skipped."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"point file {str(p)!r} not found")
    rows = []
    for i, line in enumerate(p.read_text().splitlines(), 1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        parts = s.replace(",", " ").split()
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            if not rows:
                continue  # a header
            raise InputError(f"{p}:{i}: {line!r}; expected 6 numbers x_cam y_cam z_cam x_base y_base z_base (m)") from None
        if len(vals) != 6:
            raise InputError(f"{p}:{i}: {len(vals)} numbers; expected 6 (x_cam y_cam z_cam x_base y_base z_base, m)")
        rows.append(vals)
    a = np.array(rows, dtype=np.float64).reshape(-1, 6)
    return a[:, :3], a[:, 3:]


# -- markers --------------------------------------------------------------------------------
@dataclass
class MarkerLayout:
    dictionary: str
    markers: dict  # id -> (T_base_marker 4x4, size m)

    def corners_base(self, marker_id: int) -> np.ndarray:
        """The 4 corners (4, 3) of marker ``marker_id`` in the base frame, OpenCV's order
        (top-left, top-right, bottom-right, bottom-left as printed)."""
        T, s = self.markers[marker_id]
        h = s / 2.0
        local = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
        return local @ T[:3, :3].T + T[:3, 3]


def load_layout(path_or_doc) -> MarkerLayout:
    """A ``MarkerLayout`` from a TOML file (or an already parsed dict); see the module docstring."""
    if isinstance(path_or_doc, dict):
        doc, where = path_or_doc, "marker layout"
    else:
        p = Path(path_or_doc)
        if not p.is_file():
            raise InputError(f"marker layout {str(p)!r} not found; see `pointfence calib extrinsics --help` for its format")
        try:
            doc = tomllib.loads(p.read_text())
        except tomllib.TOMLDecodeError as e:
            raise InputError(f"{p}: not valid TOML ({e})") from None
        where = str(p)
    unknown = set(doc) - {"dictionary", "size", "marker"}
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(sorted(unknown))}; expected dictionary, size, [[marker]]")
    from .render import get_dictionary

    dictionary = str(doc.get("dictionary", "DICT_4X4_50"))
    get_dictionary(dictionary)  # validates the name
    default_size = doc.get("size")
    markers = {}
    entries = doc.get("marker", [])
    if not entries:
        raise InputError(f"{where}: no [[marker]] entries; give each marker's id and pose in the robot base frame")
    for i, m in enumerate(entries):
        w = f"{where} [[marker]] #{i + 1}"
        bad = set(m) - {"id", "size", "position", "rotation_deg", "T_base_marker"}
        if bad:
            raise InputError(f"{w}: unknown key(s) {', '.join(sorted(bad))}; expected id, size, position, rotation_deg or T_base_marker")
        if not isinstance(m.get("id"), int) or m["id"] < 0:
            raise InputError(f"{w}: id = {m.get('id')!r}; expected the marker's integer id")
        size = m.get("size", default_size)
        if not isinstance(size, (int, float)) or not size > 0:
            raise InputError(f"{w} (id {m['id']}): size = {size!r}; expected the black square's side in m (> 0)")
        if "T_base_marker" in m:
            T = check_rigid(m["T_base_marker"], f"{w}: T_base_marker")
        else:
            pos, rot = m.get("position"), m.get("rotation_deg", [0, 0, 0])
            if not (isinstance(pos, list) and len(pos) == 3) or not (isinstance(rot, list) and len(rot) == 3):
                raise InputError(f"{w} (id {m['id']}): position = {pos!r}, rotation_deg = {rot!r}; expected 3 numbers each "
                                 "(or T_base_marker = 16 numbers)")
            T = make_T(Rotation.from_euler("xyz", rot, degrees=True).as_matrix(), pos)
        if m["id"] in markers:
            raise InputError(f"{w}: marker id {m['id']} appears twice")
        markers[m["id"]] = (T, float(size))
    return MarkerLayout(dictionary, markers)


def detect_markers(image: np.ndarray, dictionary: str):
    """{id: corners (4, 2)} of the markers found in ``image`` (sub-pixel corners)."""
    import cv2

    from .render import get_dictionary

    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(get_dictionary(dictionary), params)
    corners, ids, _ = det.detectMarkers(gray)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2).astype(np.float64) for i, c in zip(ids.ravel(), corners)}


@dataclass
class FramePose:
    label: str
    T_world_cam: np.ndarray
    rms_px: float
    ids: list


def pose_from_markers(found: dict, layout: MarkerLayout, camera: Camera, label: str = "image",
                      ignore_unknown: bool = False) -> FramePose:
    """The camera pose in the base frame from the markers ``found`` in one image (all corners in
    one PnP, refined by Levenberg-Marquardt)."""
    import cv2

    unknown = sorted(set(found) - set(layout.markers))
    if unknown and not ignore_unknown:
        raise InputError(f"{label}: marker id(s) {unknown} are not in the layout (layout ids: {sorted(layout.markers)}); "
                         "add them to the layout with their pose, cover them, or pass --ignore-unknown")
    ids = sorted(set(found) & set(layout.markers))
    if not ids:
        raise InputError(f"{label}: none of the layout's markers {sorted(layout.markers)} is visible")
    obj = np.concatenate([layout.corners_base(i) for i in ids])
    img = np.concatenate([found[i] for i in ids])
    K, dist = camera.K, np.asarray(camera.dist, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise InputError(f"{label}: the marker pose could not be solved (markers {ids})")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    T_cam_base = make_T(cv2.Rodrigues(rvec)[0], tvec)
    return FramePose(label, inv_T(T_cam_base), rms, ids)


@dataclass
class ExtrinsicsResult:
    T_world_cam: np.ndarray
    frames: list  # FramePose of each used frame
    dropped: list = field(default_factory=list)  # (label, why)
    spread_mm: float = 0.0  # RMS distance of per-frame positions from the result
    spread_deg: float = 0.0  # RMS rotation of per-frame poses from the result

    def report(self) -> str:
        rms = [f.rms_px for f in self.frames]
        lines = [f"camera pose from {len(self.frames)} frame(s) ({len(self.dropped)} dropped), low-pass filtered",
                 f"marker reprojection RMS per frame: median {np.median(rms):.3f} px, max {max(rms):.3f} px",
                 f"frame-to-frame spread: {self.spread_mm:.2f} mm, {self.spread_deg:.3f} deg RMS "
                 f"({'steady' if self.spread_mm < 2 and self.spread_deg < 0.5 else 'noisy: use more frames or larger markers'})",
                 "camera position in the base frame: " + ", ".join(f"{x:.4f}" for x in self.T_world_cam[:3, 3]) + " m"]
        lines += [f"dropped {lab}: {why}" for lab, why in self.dropped]
        return "\n".join(lines)


def extrinsics_from_markers(images: Sequence[np.ndarray], layout: MarkerLayout, camera: Camera,
                            labels: Optional[Sequence[str]] = None, alpha: float = 0.1, ignore_unknown: bool = False,
                            show_progress: bool = True) -> ExtrinsicsResult:
    """``T_world_cam`` from marker images (see the module docstring)."""
    labels = list(labels) if labels is not None else [f"image {i}" for i in range(len(images))]
    if not len(images):
        raise InputError("calib extrinsics: no images given")
    poses, dropped = [], []
    for img, lab in progress(list(zip(images, labels)), "locating markers", enabled=show_progress):
        if img.shape[:2] != (camera.height, camera.width):
            raise InputError(f"{lab}: {img.shape[1]}x{img.shape[0]}; expected {camera.width}x{camera.height} like camera "
                             f"{camera.name!r} (images must be the depth camera's view)")
        found = detect_markers(img, layout.dictionary)
        if not found:
            dropped.append((lab, "no marker found"))
            continue
        try:
            poses.append(pose_from_markers(found, layout, camera, lab, ignore_unknown))
        except InputError as e:
            if "not in the layout" in str(e):
                raise
            dropped.append((lab, str(e)))
    if not poses:
        raise InputError(f"no layout marker ({layout.dictionary}, ids {sorted(layout.markers)}) found in any of the "
                         f"{len(images)} images; check the dictionary name, lighting and focus")
    med = float(np.median([p.rms_px for p in poses]))
    keep = [p for p in poses if p.rms_px <= max(3 * med, 0.5)]
    dropped += [(p.label, f"reprojection RMS {p.rms_px:.2f} px, far above the median {med:.2f} px") for p in poses if p not in keep]
    lp = LowPassPose(alpha)
    for p in keep:
        T = lp.update(p.T_world_cam)
    errs = np.array([pose_error(p.T_world_cam, T) for p in keep])
    return ExtrinsicsResult(T, keep, dropped, float(np.sqrt(np.mean(errs[:, 0] ** 2)) * 1000),
                            float(np.sqrt(np.mean(errs[:, 1] ** 2))))


# -- CLI ------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("images", nargs="*", help="images of the markers from the depth camera's view (files or folders)")
    p.add_argument("--layout", help="marker layout TOML: dictionary, size, [[marker]] id + pose in the base frame")
    p.add_argument("--points", help="instead of markers: file of rows x_cam y_cam z_cam x_base y_base z_base (m), Kabsch fit")
    p.add_argument("--intrinsics", help="configuration or snippet TOML holding this camera's fx, fy, cx, cy, width, height[, dist]")
    p.add_argument("--alpha", type=float, default=0.1, help="low-pass filter gain per frame once past 1/alpha frames (default 0.1)")
    p.add_argument("--ignore-unknown", action="store_true", help="ignore detected markers whose id is not in the layout")
    p.add_argument("--demo", action="store_true", help="run on synthetic renders of a known layout and camera pose")
    p.add_argument("--name", default="cam0", help="camera name of the [[camera]] entry (default cam0)")
    p.add_argument("--source", help="source spec for a new [[camera]] entry")
    p.add_argument("--out", help="also write the [[camera]] snippet to this file")
    p.add_argument("--config", help="merge the result into this scene configuration file (only the keys calibrated change; earlier versions kept as .bak, .bak.2, ...)")


def camera_from_toml(path, name: str) -> Camera:
    """The intrinsics of camera ``name`` (or the only camera) in a TOML configuration or snippet."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"intrinsics file {str(p)!r} not found; run `pointfence calib intrinsics ... --out {p}` first")
    doc = tomllib.loads(p.read_text())
    cams = doc.get("camera", [])
    pick = [c for c in cams if c.get("name") == name] or (cams if len(cams) == 1 else [])
    if not pick:
        raise InputError(f"{p}: no [[camera]] named {name!r} (have {[c.get('name') for c in cams]}); pass --name")
    c = pick[0]
    missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in c]
    if missing:
        raise InputError(f"{p}: camera {c.get('name')!r} lacks {', '.join(missing)}; run `pointfence calib intrinsics` first")
    return Camera(name, int(c["width"]), int(c["height"]), float(c["fx"]), float(c["fy"]), float(c["cx"]), float(c["cy"]),
                  dist=tuple(c.get("dist", (0.0,) * 5)))


def demo_scene():
    """(camera, layout, true T_world_cam, images) of a synthetic marker setup: four 6 cm markers
    on the table and two on a 45-degree stand, seen from about 0.6 m with image noise."""
    from .render import get_dictionary, marker_plane, render_planes, supersampled_rays

    camera = Camera("demo", 640, 480, 575.8, 575.8, 319.5, 239.5)
    doc = {"dictionary": "DICT_4X4_50", "size": 0.06, "marker": [
        {"id": 0, "position": [-0.12, -0.09, 0.0]}, {"id": 1, "position": [0.12, -0.09, 0.0]},
        {"id": 2, "position": [-0.12, 0.09, 0.0]}, {"id": 3, "position": [0.12, 0.09, 0.0]},
        {"id": 4, "position": [0.0, 0.17, 0.04], "rotation_deg": [45, 0, 0]},
        {"id": 5, "position": [0.0, -0.17, 0.04], "rotation_deg": [-45, 0, 0]}]}
    layout = load_layout(doc)
    from pointfence.service.sources.synthetic import look_at

    T_true = look_at((0.25, -0.35, 0.55), (0.0, 0.0, 0.0))
    d = get_dictionary(layout.dictionary)
    planes = [marker_plane(d, i, s, T) for i, (T, s) in layout.markers.items()]
    rays = supersampled_rays(camera, 2)
    rng = np.random.default_rng(1)
    images = [render_planes(camera, T_true, planes, background=90, noise_std=3.0, rng=rng, rays=rays) for _ in range(8)]
    return camera, layout, T_true, images


def run(args) -> int:
    from .intrinsics import read_images
    from .output import emit

    if args.points:
        P_cam, P_base = read_point_pairs(args.points)
        fit = kabsch(P_cam, P_base)
        print(fit.report("point pairs"))
        emit(args, args.name, {"T_world_cam": fit.T}, f"pointfence calib extrinsics --points: {len(P_cam)} pairs, "
                                                        f"RMS residual {fit.rms * 1000:.2f} mm")
        return 0
    if args.demo:
        camera, layout, T_true, images = demo_scene()
        labels = [f"render {i}" for i in range(len(images))]
    else:
        if not args.layout:
            raise InputError("calib extrinsics: pass --layout markers.toml with images, or --points pairs.csv (or --demo)")
        if not args.intrinsics:
            raise InputError("calib extrinsics: pass --intrinsics with this camera's intrinsics (a TOML from `calib intrinsics`)")
        layout = load_layout(args.layout)
        camera = camera_from_toml(args.intrinsics, args.name)
        if not args.images:
            raise InputError("calib extrinsics: no images given")
        images, labels = read_images(args.images)
    res = extrinsics_from_markers(images, layout, camera, labels, args.alpha, args.ignore_unknown)
    print(res.report())
    if args.demo:
        dt, dr = pose_error(res.T_world_cam, T_true)
        print(f"# demo: error against the true pose {dt * 1000:.2f} mm, {dr:.3f} deg")
    emit(args, args.name, {"T_world_cam": res.T_world_cam},
         f"pointfence calib extrinsics: {len(res.frames)} frames, spread {res.spread_mm:.2f} mm / {res.spread_deg:.3f} deg")
    return 0
