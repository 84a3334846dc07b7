"""The solvers of ``pointfence calib hand-eye`` and the verdict on their result.

Frames: ``X = T_world_cam`` (camera -> robot base, the unknown), ``W_i = T_world_tip`` (the
robot's measured_cp at pose i), metres and radians inside, mm and degrees in reports.

* **tip points**: the tip ball's centre ``c_i`` (camera frame) and its world position
  ``W_i o`` (``o`` the ball's offset in the tip frame) give ``X c_i = W_i o``: Kabsch/Umeyama
  without scale (``calib.extrinsics.kabsch``); with ``fit_offset`` the offset is estimated jointly
  (Gauss-Newton over X and o), which needs the tool to turn between poses.
* **marker (eye-to-hand)**: a marker fixed on the tool at unknown ``Y = T_tip_marker``, seen
  at ``C_i = T_cam_marker`` (PnP): ``W_i Y = X C_i``, so ``A X = X B`` with ``A = W_j W_i^-1``,
  ``B = C_j C_i^-1``. Solved by OpenCV's ``calibrateHandEye`` in its eye-to-hand form (base->gripper
  in, cam->base out) where the installed OpenCV has it, else by the same Park-Martin method
  here (OpenCV 5.0's Python wheel lacks the function); then X and Y are refined together by
  minimising the marker corners' reprojection error over all poses.

``judge`` gives the verdict: enough poses, enough spread (tip) or rotation (marker), residuals
within bounds, a small estimated uncertainty (jackknife over leave-one-out solves), with what to do.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from pointfence.kernels.errors import InputError

from .common import inv_T, make_T, pose_error
from .extrinsics import kabsch

#: the verdict's bounds (see ``judge``)
MIN_POSES = 8              # fewer: not trusted (at least 3 to solve at all)
MIN_SPREAD_M = 0.03        # tip: RMS extent of the tip positions along their 2nd principal axis
MIN_ROTATION_DEG = 10.0    # marker / fitted offset: RMS rotation about the 2nd principal axis
MAX_RMS_MM, MAX_WORST_MM = 2.0, 5.0
MAX_RMS_DEG, MAX_WORST_DEG = 0.5, 1.5
MAX_SE_MM, MAX_SE_DEG = 1.0, 0.25     # jackknife standard error of the result
MARKER_DEG = (2.0, 5.0)               # marker: per-pose PnP orientation residual bounds (RMS, max)


def spread(P) -> np.ndarray:
    """RMS extent (m) of points (N, 3) along their three principal axes, largest first."""
    P = np.asarray(P, dtype=np.float64)
    return np.linalg.svd(P - P.mean(axis=0), compute_uv=False) / np.sqrt(len(P))


def rotation_span(Rs) -> np.ndarray:
    """RMS rotation (deg) of rotations (N, 3, 3) away from their mean, along the three principal
    axes of their rotation vectors, largest first: a second value near 0 means all turns share
    one axis (or there are none), which leaves a hand-eye rotation undetermined."""
    rot = Rotation.from_matrix(np.asarray(Rs))
    rv = (rot.mean().inv() * rot).as_rotvec()
    return np.degrees(np.linalg.svd(rv, compute_uv=False) / np.sqrt(len(rv)))


def pose_residuals(X, Y, W, C) -> tuple:
    """Per pose: (distance mm, angle deg) between the marker pose through the robot (W_i Y) and
    through the camera (X C_i)."""
    e = np.array([pose_error(X @ c, w @ Y) for w, c in zip(W, C)])
    return e[:, 0] * 1000.0, e[:, 1]


# -- tip points -----------------------------------------------------------------------------
def solve_points(P_cam, W, offset=(0.0, 0.0, 0.0), fit_offset: bool = False) -> tuple:
    """(X, offset, residuals m (N,)) with X c_i ~ W_i offset; see the module docstring."""
    P_cam = np.asarray(P_cam, dtype=np.float64)
    W = np.asarray(W, dtype=np.float64)
    if len(P_cam) != len(W):
        raise InputError(f"hand-eye: {len(P_cam)} tip positions but {len(W)} robot poses; they must pair one to one")
    o = np.asarray(offset, dtype=np.float64)
    X = kabsch(P_cam, W[:, :3, :3] @ o + W[:, :3, 3]).T
    if fit_offset:
        def res(v):
            Xv = make_T(Rotation.from_rotvec(v[:3]).as_matrix(), v[3:6])
            return (P_cam @ Xv[:3, :3].T + Xv[:3, 3] - (W[:, :3, :3] @ v[6:] + W[:, :3, 3])).ravel()

        v0 = np.concatenate([Rotation.from_matrix(X[:3, :3]).as_rotvec(), X[:3, 3], o])
        v = least_squares(res, v0, method="lm").x
        X, o = make_T(Rotation.from_rotvec(v[:3]).as_matrix(), v[3:6]), v[6:]
    r = np.linalg.norm(P_cam @ X[:3, :3].T + X[:3, 3] - (W[:, :3, :3] @ o + W[:, :3, 3]), axis=1)
    return X, o, r


# -- marker: AX = XB --------------------------------------------------------------------------
def park_martin(W, C) -> np.ndarray:
    """X = T_world_cam from ``W_i Y = X C_i`` by Park and Martin (1994) over every pair of poses:
    rotation from the rotation axes of A and B (orthogonal Procrustes), translation by linear
    least squares."""
    W, C = np.asarray(W, dtype=np.float64), np.asarray(C, dtype=np.float64)
    i, j = np.triu_indices(len(W), 1)
    Winv, Cinv = np.linalg.inv(W), np.linalg.inv(C)
    A, B = W[j] @ Winv[i], C[j] @ Cinv[i]               # (P, 4, 4): tool motion (world), marker motion (camera)
    alpha = Rotation.from_matrix(A[:, :3, :3]).as_rotvec()
    beta = Rotation.from_matrix(B[:, :3, :3]).as_rotvec()
    M = beta.T @ alpha                                   # alpha = R beta
    U, _, Vt = np.linalg.svd(M)
    R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    lhs = (A[:, :3, :3] - np.eye(3)).reshape(-1, 3)    # (R_A - I) t = R t_B - t_A
    rhs = (B[:, :3, 3] @ R.T - A[:, :3, 3]).ravel()
    t = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    return make_T(R, t)


def opencv_hand_eye(W, C, method: str = "park") -> Optional[np.ndarray]:
    """X from ``cv2.calibrateHandEye`` in its eye-to-hand form, or None where the installed
    OpenCV lacks the function."""
    import cv2

    if not hasattr(cv2, "calibrateHandEye"):
        return None
    B2G = [inv_T(w) for w in W]
    flag = getattr(cv2, f"CALIB_HAND_EYE_{method.upper()}")
    R, t = cv2.calibrateHandEye([b[:3, :3] for b in B2G], [b[:3, 3] for b in B2G],
                                [c[:3, :3] for c in C], [c[:3, 3] for c in C], method=flag)
    return make_T(R, np.ravel(t))


def marker_offset(X, W, C) -> np.ndarray:
    """Y = T_tip_marker given X: the mean of W_i^-1 X C_i."""
    from .common import mean_pose

    return mean_pose([inv_T(w) @ X @ c for w, c in zip(W, C)])


def refine_reprojection(X, Y, W, obj, img, K, dist) -> tuple:
    """(X, Y, per-pose RMS px) minimising the reprojection of the marker corners ``obj`` (4, 3)
    (marker frame) placed by the robot (W_i Y) and seen through X^-1 against the detected
    corners ``img`` (N, 4, 2)."""
    import cv2

    W = np.asarray(W, dtype=np.float64)
    obj = np.asarray(obj, dtype=np.float64)
    img = np.asarray(img, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64)

    def unpack(v):
        return (make_T(Rotation.from_rotvec(v[:3]).as_matrix(), v[3:6]),
                make_T(Rotation.from_rotvec(v[6:9]).as_matrix(), v[9:12]))

    zero = np.zeros(3)

    def project(v):
        Xv, Yv = unpack(v)
        T = inv_T(Xv) @ W @ Yv                            # (N, 4, 4) marker -> camera
        pts = np.einsum("nij,kj->nki", T[:, :3, :3], obj) + T[:, None, :3, 3]
        p, _ = cv2.projectPoints(pts.reshape(-1, 3), zero, zero, K, dist)
        return p.reshape(len(W), len(obj), 2)

    v0 = np.concatenate([Rotation.from_matrix(X[:3, :3]).as_rotvec(), X[:3, 3],
                         Rotation.from_matrix(Y[:3, :3]).as_rotvec(), Y[:3, 3]])
    v = least_squares(lambda v: (project(v) - img).ravel(), v0, method="lm", x_scale="jac").x
    per = np.sqrt(np.mean(np.sum((project(v) - img) ** 2, axis=2), axis=1))
    X, Y = unpack(v)
    return X, Y, per


# -- stability and verdict ------------------------------------------------------------------
def jackknife(solve: Callable[[np.ndarray], np.ndarray], n: int, X: np.ndarray) -> tuple:
    """Jackknife standard errors (mm, deg) of ``X`` from the n solves ``solve(keep_mask)`` that
    each leave one pose out: sqrt((n-1)/n sum |x_k - mean|^2) over translations and rotation
    vectors; an estimate of the result's own error. (nan, nan) below 4 poses."""
    if n < 4:
        return float("nan"), float("nan")
    t, rv = [], []
    for k in range(n):
        keep = np.ones(n, bool)
        keep[k] = False
        Xk = solve(keep)
        t.append(Xk[:3, 3])
        rv.append(Rotation.from_matrix(X[:3, :3].T @ Xk[:3, :3]).as_rotvec())
    t, rv = np.array(t), np.array(rv)
    f = (n - 1) / n
    se_t = np.sqrt(f * np.sum((t - t.mean(axis=0)) ** 2))
    se_r = np.sqrt(f * np.sum((rv - rv.mean(axis=0)) ** 2))
    return float(se_t * 1000.0), float(np.degrees(se_r))


@dataclass
class Verdict:
    """``trusted`` and, when not, ``problems``: each what is wrong and what to do."""

    trusted: bool
    problems: list = field(default_factory=list)

    def text(self) -> str:
        if self.trusted:
            return "verdict: TRUSTED (every check within its bound)"
        return "verdict: NOT TRUSTED\n" + "\n".join(f"  - {p}" for p in self.problems)


def judge(n: int, labels, res_mm, res_deg=None, se=(float("nan"), float("nan")), spread_m=None, span_deg=None,
          deg_bounds=(MAX_RMS_DEG, MAX_WORST_DEG)) -> Verdict:
    """The verdict on a hand-eye result (bounds at the top of this module): ``labels`` name the
    poses, ``res_mm``/``res_deg`` their residuals (``deg_bounds``: RMS and max), ``se`` the
    jackknife standard errors (mm, deg),
    ``spread_m`` the tip points' principal extents, ``span_deg`` the tool rotations' principal spans."""
    p = []
    if n < MIN_POSES:
        p.append(f"only {n} usable poses; record at least {MIN_POSES} (15-20 advised) spread over the camera's view")
    if spread_m is not None and spread_m[1] < MIN_SPREAD_M:
        p.append(f"the tip positions lie nearly on a line (RMS extents {', '.join(f'{s * 100:.1f}' for s in spread_m)} cm); "
                 f"move the tip over an area at least {MIN_SPREAD_M * 100:.0f} cm RMS wide in two directions, ideally at "
                 "several heights")
    if span_deg is not None and span_deg[1] < MIN_ROTATION_DEG:
        p.append(f"the tool turned too little or about one axis only (RMS rotation spans {', '.join(f'{s:.1f}' for s in span_deg)} "
                 f"deg); tilt it by 20-40 deg about at least two different axes between poses")
    res_mm = np.asarray(res_mm)
    rms, worst = float(np.sqrt(np.mean(res_mm ** 2))), float(res_mm.max())
    k = int(np.argmax(res_mm))
    if rms > MAX_RMS_MM or worst > MAX_WORST_MM:
        p.append(f"residuals {rms:.2f} mm RMS, {worst:.2f} mm max (pose {labels[k]}), above {MAX_RMS_MM} / {MAX_WORST_MM} mm; "
                 "check the measured_cp timing against the frames (the robot must be still at each frame), the camera's "
                 "intrinsics, and the tip/marker detection")
    elif worst > 3 * max(rms, 0.3) and n > 4:
        p.append(f"pose {labels[k]} is an outlier ({worst:.2f} mm against {rms:.2f} mm RMS); look at its frame and drop it "
                 f"with --drop {labels[k]}")
    if res_deg is not None:
        res_deg = np.asarray(res_deg)
        drms, dworst = float(np.sqrt(np.mean(res_deg ** 2))), float(res_deg.max())
        if drms > deg_bounds[0] or dworst > deg_bounds[1]:
            p.append(f"rotation residuals {drms:.2f} deg RMS, {dworst:.2f} deg max (pose {labels[int(np.argmax(res_deg))]}), "
                     f"above {deg_bounds[0]} / {deg_bounds[1]} deg; check that measured_cp's orientation is the tool's (frame "
                     "conventions), and use a larger marker, closer, in sharper images")
    if not np.isfinite(se[0]):
        p.append("too few poses to estimate the result's uncertainty (leave-one-out needs 4 or more)")
    elif se[0] > MAX_SE_MM or se[1] > MAX_SE_DEG:
        p.append(f"estimated uncertainty {se[0]:.2f} mm / {se[1]:.3f} deg (jackknife; bounds {MAX_SE_MM} mm, {MAX_SE_DEG} deg): "
                 "the poses do not pin the result down; add poses, spread wider and turned more")
    return Verdict(not p, p)
