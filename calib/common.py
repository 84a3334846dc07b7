"""Helpers shared by the calibration steps: progress display, rotations, pose errors."""
from __future__ import annotations

import math
import sys
import time
from typing import Iterable, Iterator, Optional, TypeVar

import numpy as np
from scipy.spatial.transform import Rotation

T = TypeVar("T")


def progress(items: Iterable[T], label: str, total: Optional[int] = None, stream=None, enabled: bool = True) -> Iterator[T]:
    """Yield ``items`` while printing ``label i/total`` to stderr (one line on a terminal,
    about ten lines otherwise), then the elapsed time."""
    stream = sys.stderr if stream is None else stream
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    tty = hasattr(stream, "isatty") and stream.isatty()
    t0 = time.monotonic()
    step = max(1, (total or 10) // 10)
    i = 0
    for i, item in enumerate(items, 1):
        yield item
        if enabled and (tty or i % step == 0 or i == total):
            msg = f"{label}: {i}/{total}" if total else f"{label}: {i}"
            stream.write(("\r" + msg) if tty else msg + "\n")
            stream.flush()
    if enabled:
        stream.write(f"{chr(13) if tty else ''}{label}: {i}{'/' + str(total) if total else ''} done in {time.monotonic() - t0:.1f} s\n")
        stream.flush()


def make_T(R, t) -> np.ndarray:
    T_ = np.eye(4)
    T_[:3, :3] = np.asarray(R, dtype=np.float64)
    T_[:3, 3] = np.asarray(t, dtype=np.float64).ravel()
    return T_


def inv_T(T_: np.ndarray) -> np.ndarray:
    R, t = T_[:3, :3], T_[:3, 3]
    return make_T(R.T, -R.T @ t)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle (deg) of a rotation matrix."""
    c = (np.trace(R) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple:
    """(translation error m, rotation error deg) between two 4x4 transforms."""
    D = inv_T(T_true) @ T_est
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), rotation_angle_deg(D[:3, :3])


def mean_pose(Ts, weights=None) -> np.ndarray:
    """Average of rigid transforms: weighted mean translation, chordal mean rotation."""
    Ts = np.asarray(Ts, dtype=np.float64)
    w = np.ones(len(Ts)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    t = (w[:, None] * Ts[:, :3, 3]).sum(axis=0)
    R = Rotation.from_matrix(Ts[:, :3, :3]).mean(weights=w).as_matrix()
    return make_T(R, t)


def perturb(T_: np.ndarray, trans_m: float, rot_deg: float, seed: int = 0) -> np.ndarray:
    """``T_`` moved by ``trans_m`` along a random direction and turned ``rot_deg`` about a random axis."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=3)
    a = rng.normal(size=3)
    R = Rotation.from_rotvec(math.radians(rot_deg) * a / np.linalg.norm(a)).as_matrix()
    out = T_.copy()
    out[:3, :3] = R @ T_[:3, :3]
    out[:3, 3] = T_[:3, 3] + trans_m * d / np.linalg.norm(d)
    return out
