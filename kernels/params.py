"""Parameters of the frame pipeline: workspace, protected-point selection, fixture radius.

All positions are in the world (robot base) frame, metres.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError
from .grid import Grid
from .motion import MotionModel

SELECT_KINDS = ("all", "box", "color", "mask")


def _vec3(v, what: str) -> tuple:
    try:
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{what} = {v!r}; expected 3 numbers") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(f"{what} = {v!r}; expected 3 finite numbers")
    return tuple(float(x) for x in a)


@dataclass(frozen=True)
class Workspace:
    """Axis-aligned box in the world frame; points outside it are cropped before hashing."""

    min: tuple = (-0.5, -0.5, -0.5)
    max: tuple = (0.5, 0.5, 0.5)

    def __post_init__(self):
        lo, hi = _vec3(self.min, "workspace min"), _vec3(self.max, "workspace max")
        if not all(a < b for a, b in zip(lo, hi)):
            raise InputError(f"workspace min {lo} / max {hi}: expected min < max on every axis")
        object.__setattr__(self, "min", lo)
        object.__setattr__(self, "max", hi)


@dataclass(frozen=True)
class Selection:
    """Which points are protected (carry forbidden-region spheres).

    kind:
        ``all``: every point in the workspace; ``box``: points inside [box_min, box_max]
        (world frame, m); ``color``: points whose registered RGB colour lies in
        [color_lo, color_hi] on every channel (0-255, inclusive); ``mask``: pixels whose
        frame mask is nonzero.
    Unselected points still exist for plain haptic rendering, which uses all points.
    """

    kind: str = "all"
    box_min: tuple = (0.0, 0.0, 0.0)
    box_max: tuple = (0.0, 0.0, 0.0)
    color_lo: tuple = (0, 0, 0)
    color_hi: tuple = (255, 255, 255)

    def __post_init__(self):
        if self.kind not in SELECT_KINDS:
            raise InputError(f"selection kind {self.kind!r}; expected one of {', '.join(SELECT_KINDS)}")
        object.__setattr__(self, "box_min", _vec3(self.box_min, "selection box_min"))
        object.__setattr__(self, "box_max", _vec3(self.box_max, "selection box_max"))
        if self.kind == "box" and not all(a <= b for a, b in zip(self.box_min, self.box_max)):
            raise InputError(f"selection box_min {self.box_min} / box_max {self.box_max}: expected min <= max")
        for key in ("color_lo", "color_hi"):
            c = tuple(getattr(self, key))
            if len(c) != 3 or not all(isinstance(x, (int, np.integer)) and 0 <= x <= 255 for x in c):
                raise InputError(f"selection {key} = {c!r}; expected 3 integers 0..255 (R, G, B)")
            object.__setattr__(self, key, tuple(int(x) for x in c))


@dataclass(frozen=True)
class RadiusModel:
    """Fixture sphere radius per protected point (dissertation 6.3).

    r_f(i) = r_base + k_sigma * sqrt(lambda_max(i)) when ``adaptive``, else r_base, where
    lambda_max is the largest eigenvalue of the point's position covariance (m^2). Radii are
    clamped to ``r_max`` so that the spatial hash's cell size bounds every query's reach.
    """

    r_base: float = 0.02
    adaptive: bool = False
    k_sigma: float = 3.0
    r_max: float = 0.05

    def __post_init__(self):
        for key in ("r_base", "k_sigma", "r_max"):
            v = getattr(self, key)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise InputError(f"fixture {key} = {v!r}; expected a finite number >= 0")
        if self.r_max < self.r_base:
            raise InputError(f"fixture r_max = {self.r_max} < r_base = {self.r_base}; expected r_max >= r_base")


#: Lateral (x, y) noise of a depth pixel, in pixels (Nguyen, Izadi & Lovell 2012: ~0.8 px).
LATERAL_NOISE_PX = 0.8


@dataclass(frozen=True)
class PipelineParams:
    """Everything the frame pipeline needs besides the cameras.

    cell_size: edge of the spatial hash's cubic cells, m. It must be at least the largest
    query reach (R3 in rendering mode; r_max + R3 in fixture mode); use
    ``PipelineParams.reach(...)`` to compute it.
    max_cells: refuse grids larger than this (memory guard).
    motion: motion estimation between snapshots and fixture prediction (``kernels/motion.py``;
    off by default).
    """

    workspace: Workspace = field(default_factory=Workspace)
    selection: Selection = field(default_factory=Selection)
    radius: RadiusModel = field(default_factory=RadiusModel)
    cell_size: float = 0.03
    lateral_px: float = LATERAL_NOISE_PX
    max_cells: int = 1 << 24
    motion: MotionModel = field(default_factory=MotionModel)

    def __post_init__(self):
        if not isinstance(self.cell_size, (int, float)) or not math.isfinite(self.cell_size) or self.cell_size <= 0:
            raise InputError(f"cell_size = {self.cell_size!r}; expected a finite length > 0 m")
        if not isinstance(self.motion, MotionModel):
            raise InputError(f"motion = {self.motion!r}; expected a MotionModel")
        n = self.grid_dims()
        if n[0] * n[1] * n[2] > self.max_cells:
            raise InputError(
                f"workspace {self.workspace.min}..{self.workspace.max} at cell_size {self.cell_size} m gives "
                f"{n[0]}x{n[1]}x{n[2]} = {n[0] * n[1] * n[2]} cells (limit {self.max_cells}); "
                "shrink the workspace or enlarge the cells"
            )

    def grid(self) -> Grid:
        """The spatial hash's grid: cells of ``cell_size`` covering the workspace."""
        return Grid.covering(self.workspace.min, self.workspace.max, self.cell_size)

    def grid_dims(self) -> tuple:
        """(nx, ny, nz) cells of the spatial hash's grid."""
        return self.grid().dims

    @staticmethod
    def reach(r3: float = 0.010, radius: RadiusModel | None = None) -> float:
        """Smallest valid cell size: R3 for rendering, plus r_max for fixtures."""
        return r3 + (radius.r_max if radius is not None else 0.0)
