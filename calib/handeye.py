"""Hand-eye calibration of a fixed camera: ``pointfence calib hand-eye LOG``.

Finds the camera's ``T_world_cam`` (world = robot base frame, m) from the robot moving its tool
through N poses while its ``measured_cp`` (T_world_tip) is logged with a frame at each pose
(the log's layout: ``calib/handeye_log.py``, repeated below). Two methods:

* ``--method tip`` (default): a small ball on the tool tip, found in each depth frame (by its
  colour in the registered colour image, ``--tip color``, or as the nearest surface,
  ``--tip nearest``) and fitted as a sphere of ``--ball-radius``; its centres (camera frame) are
  matched to the tip positions (``measured_cp`` moved by ``--tip-offset``, the ball's centre in the
  tip frame) by Kabsch (rigid, no scale). ``--fit-offset`` estimates that offset too (the tool
  must turn between poses).
* ``--method aruco``: an ArUco marker fixed anywhere on the tool, detected in the colour (or IR)
  image, its pose by solvePnP; solved as eye-to-hand ``A X = X B`` with OpenCV's
  ``calibrateHandEye`` (Park-Martin by default, ``--solver``; where the installed OpenCV lacks the
  function, the same Park-Martin solve here), then refined with the marker's pose on the tool
  by minimising the corners' reprojection error over every pose.

Output: the 4x4 (as the ``[[camera]]`` key ``T_world_cam``, printed, ``--out``, or merged into
``--config`` with numbered backups, like every calib step), the residuals per pose (r.m.s. and
max, mm and deg: for the tip method the deg figure is the leave-one-out rotation change), and
a verdict: TRUSTED, or NOT TRUSTED with each problem and what to do (too few poses, points
nearly on a line, too little rotation, residuals above 2 mm / 0.5 deg r.m.s., an outlier pose,
a result that one pose moves by more than 1 mm / 0.25 deg). A result that is not trusted is
not written unless ``--accept-untrusted`` (exit status 3). Frames where the tip or marker is not
found are dropped and listed; ``--drop INDEX`` drops poses by hand.

Record the log with the robot still at each pose (the frame and measured_cp of one instant),
15-20 poses spread over the camera's view and the working heights, the tool tilted 20-40 deg
about different axes. ``--simulate`` renders such a log into LOG (a new folder) with a known
camera pose, calibrates it and prints the error against the truth.

Log layout::

    LOG/camera.toml      [[camera]] fx, fy, cx, cy, width, height [, dist, depth_scale, z_min, z_max]
    LOG/poses.csv        index,m00,...,m33  (measured_cp, T_world_tip row-major, m; header allowed)
    LOG/depth_0000.png   16-bit depth of pose 0 (tip method)
    LOG/color_0000.png   8-bit colour/IR of pose 0, the depth camera's view (aruco; tip --tip color)
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from . import handeye_solve as hs
from .common import make_T, pose_error, progress
from .handeye_log import HandEyeLog, load_log


@dataclass
class HandEyeResult:
    """A hand-eye result: ``T_world_cam``; per used pose ``labels`` (log indices), ``res_mm`` and
    ``res_deg`` (None for the tip method); ``se`` the jackknife standard error (mm, deg);
    ``spread_m`` / ``span_deg`` the poses' principal extents (m) / rotation spans (deg);
    ``dropped`` (index, why); ``extra`` method-specific figures; ``verdict``; ``tool``."""

    T_world_cam: np.ndarray
    method: str
    labels: list
    res_mm: np.ndarray
    res_deg: Optional[np.ndarray]
    se: tuple
    spread_m: np.ndarray
    span_deg: np.ndarray
    dropped: list = field(default_factory=list)
    extra: dict = field(default_factory=dict)
    verdict: hs.Verdict = None
    tool: Optional[np.ndarray] = None   # the tip method's ball offset (3,) m, the marker method's T_tip_marker

    def report(self) -> str:
        r = self.res_mm
        lines = [f"hand-eye ({self.method}): {len(self.labels)} poses used, {len(self.dropped)} dropped",
                 f"{'residuals' if self.res_deg is None else 'marker corner residuals across the line of sight'}: {np.sqrt(np.mean(r ** 2)):.2f} mm RMS, {r.max():.2f} mm max (pose {self.labels[int(np.argmax(r))]})"]
        if self.res_deg is not None:
            d = self.res_deg
            lines.append(f"marker orientation residuals (single-frame PnP against the model): {np.sqrt(np.mean(d ** 2)):.3f} deg RMS, {d.max():.3f} deg max "
                         f"(pose {self.labels[int(np.argmax(d))]})")
        lines.append(f"estimated uncertainty of the result (jackknife): {self.se[0]:.2f} mm, {self.se[1]:.3f} deg")
        lines.append("tip positions' RMS extents: " + ", ".join(f"{s * 100:.1f}" for s in self.spread_m)
                     + " cm; tool rotation spans: " + ", ".join(f"{s:.1f}" for s in self.span_deg) + " deg")
        for k, v in self.extra.items():
            lines.append(f"{k}: {v}")
        lines.append("camera position in the base frame: " + ", ".join(f"{x:.4f}" for x in self.T_world_cam[:3, 3]) + " m")
        lines += [f"dropped pose {i}: {why}" for i, why in self.dropped]
        lines.append(self.verdict.text())
        return "\n".join(lines)


def _kept(log: HandEyeLog, drop) -> list:
    drop = set(int(d) for d in (drop or ()))
    unknown = sorted(drop - set(log.indices.tolist()))
    if unknown:
        raise InputError(f"--drop {unknown}: no such pose in the log (indices {log.indices.min()}..{log.indices.max()})")
    return [k for k, i in enumerate(log.indices) if int(i) not in drop]


def _need(n: int, what: str) -> None:
    if n < 3:
        raise InputError(f"hand-eye: {n} usable poses ({what}); at least 3 are needed to solve and "
                         f"{hs.MIN_POSES} to trust the result: record more poses")


def calibrate_tip(log: HandEyeLog, radius: float = 0.012, tip: str = "color", lo=(150, 0, 0), hi=(255, 90, 90),
                  offset=(0.0, 0.0, 0.0), fit_offset: bool = False, drop=(), show_progress: bool = True) -> HandEyeResult:
    """The tip-ball method on a loaded log (see the module docstring)."""
    from .handeye_tip import find_ball

    if not radius > 0:
        raise InputError(f"--ball-radius {radius!r}; expected the ball's radius in m (> 0)")
    if tip not in ("color", "nearest"):
        raise InputError(f"--tip {tip!r}; expected 'color' or 'nearest'")
    rays = log.camera.ray_table()
    centres, labels, W, dropped, fits = [], [], [], [], []
    for k in progress(_kept(log, drop), "finding the tip", enabled=show_progress):
        i = int(log.indices[k])
        fit, why = find_ball(log.depth(i), log.camera, radius, log.color(i) if tip == "color" else None, lo, hi, rays)
        if fit is None:
            dropped.append((i, why))
            continue
        if fit.rms > 0.25 * radius:
            dropped.append((i, f"the blob is no ball of radius {radius * 1000:.1f} mm (fit RMS {fit.rms * 1000:.2f} mm)"))
            continue
        centres.append(fit.center)
        labels.append(i)
        W.append(log.T_world_tip[k])
        fits.append(fit.rms)
    _need(len(centres), f"the tip was found in {len(centres)} of {len(log.indices)} frames")
    P, W = np.array(centres), np.array(W)
    span = hs.rotation_span(W[:, :3, :3])
    if fit_offset and span[1] < 1.0:
        raise InputError(f"--fit-offset: the tool's rotation spans only {span.round(2).tolist()} deg; the offset cannot be "
                         "told from the camera pose without turns about two axes: measure the offset and pass --tip-offset")
    X, o, r = hs.solve_points(P, W, offset, fit_offset)
    se = hs.jackknife(lambda keep: hs.solve_points(P[keep], W[keep], o, False)[0], len(P), X)
    world = W[:, :3, :3] @ o + W[:, :3, 3]
    spread = hs.spread(world)
    res = HandEyeResult(X, "tip ball, Kabsch", labels, r * 1000.0, None, se, spread, span, dropped,
                        {"ball sphere fit": f"median {np.median(fits) * 1000:.2f} mm RMS per frame",
                         "tip offset (tip frame)": ", ".join(f"{x * 1000:.2f}" for x in o) + " mm"
                         + (" (fitted)" if fit_offset else "")})
    res.verdict = hs.judge(len(P), labels, res.res_mm, None, se, spread, span if fit_offset else None)
    res.tool = o
    return res


def marker_corners(size: float) -> np.ndarray:
    """The 4 corners (4, 3) of a marker of side ``size`` in its own frame, OpenCV's order."""
    h = size / 2.0
    return np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], dtype=np.float64)


def calibrate_marker(log: HandEyeLog, size: float, dictionary: str = "DICT_4X4_50", marker_id: Optional[int] = None,
                     solver: str = "park", drop=(), show_progress: bool = True) -> HandEyeResult:
    """The ArUco eye-to-hand method on a loaded log (see the module docstring)."""
    import cv2

    from .extrinsics import detect_markers

    if not size > 0:
        raise InputError(f"--marker-size {size!r}; expected the black square's side in m (> 0)")
    if solver.upper() not in ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS"):
        raise InputError(f"--solver {solver!r}; expected tsai, park, horaud, andreff or daniilidis (OpenCV's hand-eye methods)")
    cam = log.camera
    K, dist = cam.K, np.asarray(cam.dist, dtype=np.float64)
    obj = marker_corners(size)
    C, W, labels, corners, dropped = [], [], [], [], []
    for k in progress(_kept(log, drop), "finding the marker", enabled=show_progress):
        i = int(log.indices[k])
        found = detect_markers(log.color(i), dictionary)
        if marker_id is None and len(found) > 1:
            raise InputError(f"pose {i}: markers {sorted(found)} are visible; pass --marker-id to say which one is on the tool")
        mid = marker_id if marker_id is not None else next(iter(found), None)
        if mid not in found:
            dropped.append((i, f"marker {marker_id if marker_id is not None else ''} ({dictionary}) not found".replace("  ", " ")))
            continue
        img = found[mid]
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if not ok:
            dropped.append((i, "the marker's pose could not be solved"))
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
        C.append(make_T(cv2.Rodrigues(rvec)[0], tvec))
        W.append(log.T_world_tip[k])
        labels.append(i)
        corners.append(img)
    _need(len(C), f"the marker was found in {len(C)} of {len(log.indices)} frames")
    C, W, corners = np.array(C), np.array(W), np.array(corners)
    span = hs.rotation_span(W[:, :3, :3])
    if span[1] < 1.0:
        raise InputError(f"hand-eye: the tool's rotation spans {span.round(2).tolist()} deg (principal axes): "
                         + ("it never turned (pure translation)" if span[0] < 1.0 else "it turned about one axis only")
                         + "; the camera's rotation cannot be solved from that. Record poses with the tool tilted "
                         "20-40 deg about at least two different axes")

    def solve(keep):
        X0 = hs.opencv_hand_eye(W[keep], C[keep], solver)
        X0 = hs.park_martin(W[keep], C[keep]) if X0 is None else X0
        Y0 = hs.marker_offset(X0, W[keep], C[keep])
        return hs.refine_reprojection(X0, Y0, W[keep], obj, corners[keep], K, dist)

    X, Y, px = solve(np.ones(len(C), bool))
    se = hs.jackknife(lambda keep: solve(keep)[0], len(C), X)
    _, deg = hs.pose_residuals(X, Y, W, C)
    depth = np.array([(np.linalg.inv(X) @ w @ Y)[2, 3] for w in W])
    mm = px * depth / np.sqrt(cam.fx * cam.fy) * 1000.0   # the reprojection residual across the line of sight, mm
    via = f"OpenCV calibrateHandEye ({solver})" if hasattr(cv2, "calibrateHandEye") else \
        "Park-Martin (this OpenCV has no calibrateHandEye)"
    res = HandEyeResult(X, f"ArUco eye-to-hand, {via}, refined on reprojection", labels, mm, deg, se,
                        hs.spread(W[:, :3, 3]), span, dropped,
                        {"marker reprojection": f"{np.sqrt(np.mean(px ** 2)):.3f} px RMS, {px.max():.3f} px max",
                         "marker on the tool (T_tip_marker translation)": ", ".join(f"{x * 1000:.1f}" for x in Y[:3, 3]) + " mm"})
    res.verdict = hs.judge(len(C), labels, mm, deg, se, None, span, hs.MARKER_DEG)
    res.tool = Y
    return res


# -- CLI ------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("log", help="the hand-eye log folder (camera.toml, poses.csv, depth_/color_NNNN.png); with --simulate, a new folder")
    p.add_argument("--method", choices=("tip", "aruco"), default="tip", help="tip: a ball on the tool tip in depth (default); "
                   "aruco: a marker on the tool, OpenCV hand-eye")
    p.add_argument("--tip", choices=("color", "nearest"), default="color",
                   help="find the ball by colour (default) or as the nearest surface (depth only)")
    p.add_argument("--ball-radius", type=float, default=0.012, help="tip ball radius, m (default 0.012)")
    p.add_argument("--color-lo", type=int, nargs=3, default=(150, 0, 0), metavar=("R", "G", "B"), help="ball colour, lowest RGB")
    p.add_argument("--color-hi", type=int, nargs=3, default=(255, 90, 90), metavar=("R", "G", "B"), help="ball colour, highest RGB")
    p.add_argument("--tip-offset", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                   help="the ball's centre in the tip frame of measured_cp, m (default 0 0 0)")
    p.add_argument("--fit-offset", action="store_true", help="estimate the ball's offset from the tip too (needs turns)")
    p.add_argument("--dictionary", default="DICT_4X4_50", help="ArUco dictionary (default DICT_4X4_50)")
    p.add_argument("--marker-id", type=int, help="the tool marker's id (default: the only one visible)")
    p.add_argument("--marker-size", type=float, default=0.05, help="marker side (the black square), m (default 0.05)")
    p.add_argument("--solver", default="park", help="OpenCV hand-eye method: tsai, park (default), horaud, andreff, daniilidis")
    p.add_argument("--drop", type=int, nargs="+", default=(), metavar="INDEX", help="poses to leave out")
    p.add_argument("--intrinsics", help="TOML with the camera's [[camera]] intrinsics (default LOG/camera.toml)")
    p.add_argument("--accept-untrusted", action="store_true", help="write the result even when the verdict is NOT TRUSTED")
    p.add_argument("--simulate", action="store_true", help="render a synthetic log into LOG (new folder) and calibrate it")
    p.add_argument("--poses", type=int, default=16, help="--simulate: number of poses (default 16)")
    p.add_argument("--seed", type=int, default=0, help="--simulate: random seed")
    p.add_argument("--name", default="cam0", help="camera name of the [[camera]] entry (default cam0)")
    p.add_argument("--source", help="source spec for a new [[camera]] entry")
    p.add_argument("--out", help="also write the [[camera]] snippet to this file")
    p.add_argument("--config", help="merge T_world_cam into this scene configuration (earlier versions kept as .bak, .bak.2, ...)")


def simulate(args) -> np.ndarray:
    """Render a synthetic log for ``args`` into ``args.log``; the true T_world_cam."""
    from . import handeye_sim
    from .handeye_log import write_log

    if args.method == "aruco":
        sim = handeye_sim.marker_log(args.poses, args.seed, size=args.marker_size, dictionary=args.dictionary,
                                     marker_id=7 if args.marker_id is None else args.marker_id)
        write_log(args.log, sim["camera"], sim["T_world_tip"], color=sim["color"])
    else:
        sim = handeye_sim.tip_log(args.poses, args.seed, radius=args.ball_radius, offset=args.tip_offset,
                                  nearest=args.tip == "nearest")
        write_log(args.log, sim["camera"], sim["T_world_tip"], depth=sim["depth"], color=sim["color"])
    print(f"# simulate: wrote a {args.poses}-pose log to {args.log}")
    return sim["T_world_cam"]


def run(args) -> int:
    from .output import emit

    T_true = simulate(args) if args.simulate else None
    kinds = ("color",) if args.method == "aruco" else (("depth", "color") if args.tip == "color" else ("depth",))
    log = load_log(args.log, kinds, args.intrinsics, args.name if args.intrinsics else None)
    if args.method == "aruco":
        res = calibrate_marker(log, args.marker_size, args.dictionary, args.marker_id, args.solver, args.drop)
    else:
        res = calibrate_tip(log, args.ball_radius, args.tip, args.color_lo, args.color_hi, args.tip_offset,
                            args.fit_offset, args.drop)
    print(res.report())
    if T_true is not None:
        dt, dr = pose_error(res.T_world_cam, T_true)
        print(f"# simulate: error against the true pose {dt * 1000:.2f} mm, {dr:.3f} deg")
    r = res.res_mm
    comment = (f"pointfence calib hand-eye ({res.method}): {len(res.labels)} poses, residuals {np.sqrt(np.mean(r ** 2)):.2f} mm "
               f"RMS / {r.max():.2f} mm max, {'trusted' if res.verdict.trusted else 'NOT TRUSTED'}")
    if not res.verdict.trusted and not args.accept_untrusted:
        from .output import camera_snippet

        print(camera_snippet(args.name, {"T_world_cam": res.T_world_cam}, None, comment), end="")
        if args.out or args.config:
            print("# not written: the verdict is NOT TRUSTED; fix the problems above and record again, "
                  "or pass --accept-untrusted to write it anyway")
        return 3
    emit(args, args.name, {"T_world_cam": res.T_world_cam}, comment)
    return 0
