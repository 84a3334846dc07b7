"""Analytic synthetic scenes in WORLD coordinates (metres, seconds).

World frame: z up, the table top is the plane z = 0, the workspace origin (0, 0, 0) is on the
table under the default camera (``synthetic.default_camera`` looks down from 0.6 m).

Every scene exposes its exact geometry at any time ``t`` (s):

* ``distance(points, t)``: signed distance (m) of world points (N, 3) to the true surface,
  positive on the free (camera-visible) side.
* ``normal(points, t)``: unit gradient of that distance (the outward surface normal near it).
* ``protected(points, t)``: True where a surface point belongs to the scene's protected object
  (rendered red in colour images; white otherwise).
* ``surface_points(t, spacing, half_extent)``: exact surface points seen from straight above.
* ``cast(origins, dirs, t)``: ray parameter of the first surface hit (``inf`` when none).

Make one with ``make_scene(name, **options)``; ``SCENES`` lists the names. Options are the
dataclass fields of each scene; ``position`` is always the world point (m) that anchors the
scene's main feature.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import ClassVar, Optional

import numpy as np

from pointfence.kernels.errors import InputError

from .geometry import Ball, Convex, HalfSpace, PlaneMinusBall, Solid, Union

Z_UP = np.array([0.0, 0.0, 1.0])
_TOL = 1e-4  # m: how far from a protected part a surface point may be and still count


def _rot(axis, angle: float) -> np.ndarray:
    """Rotation matrix about unit ``axis`` by ``angle`` rad (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def _vec3(value, what: str) -> np.ndarray:
    if isinstance(value, str):
        value = [v for v in value.replace(";", ",").split(",") if v.strip()]
    try:
        v = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        v = np.array([])
    if v.shape == (2,):
        v = np.append(v, 0.0)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InputError(f"{what} = {value!r}; expected 3 finite numbers x, y, z in metres (world frame)")
    return v


@dataclass
class Scene:
    """Base class. Subclasses set ``name``, define options as fields and build ``solid(t)``."""

    name: ClassVar[str] = ""
    position: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        self.position = _vec3(self.position, f"scene {self.name!r}: position")
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "position" or isinstance(v, (bool, np.ndarray)) or v is None:
                continue
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise InputError(f"scene {self.name!r}: {f.name} = {v!r}; expected a number") from None
            if not math.isfinite(v):
                raise InputError(f"scene {self.name!r}: {f.name} = {v!r}; expected a finite number")
            setattr(self, f.name, v)
        self._static = None
        self.check()

    # -- to override ---------------------------------------------------------------------
    def check(self) -> None:
        """Validate options (raise InputError)."""

    def solid(self, t: float) -> Solid:
        raise NotImplementedError

    def protected(self, points, t: float = 0.0) -> np.ndarray:
        """True where a surface point (N, 3) lies on the protected (red) object."""
        return np.zeros(len(np.atleast_2d(points)), dtype=bool)

    moving: ClassVar[bool] = False

    # -- common --------------------------------------------------------------------------
    def _solid(self, t: float) -> Solid:
        if self.moving:
            return self.solid(float(t))
        if self._static is None:
            self._static = self.solid(0.0)
        return self._static

    def distance(self, points, t: float = 0.0) -> np.ndarray:
        """Signed distance (m) of world points (N, 3) to the true surface at time ``t`` (s)."""
        return self._solid(t).sdf(np.atleast_2d(np.asarray(points, dtype=np.float64)))

    def normal(self, points, t: float = 0.0, h: float = 1e-6) -> np.ndarray:
        """Outward unit normals (N, 3): central-difference gradient of ``distance``."""
        p = np.atleast_2d(np.asarray(points, dtype=np.float64))
        g = np.stack([self.distance(p + h * e, t) - self.distance(p - h * e, t) for e in np.eye(3)], axis=1)
        return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-300)

    def cast(self, origins, dirs, t: float = 0.0) -> np.ndarray:
        """Ray parameter s of the first hit of ``origins + s * dirs`` (``inf``: no hit)."""
        return self._solid(t).enter(origins, dirs)

    def surface_points(self, t: float = 0.0, spacing: float = 0.005, half_extent: float = 0.2) -> np.ndarray:
        """Exact surface points (N, 3) on a square x-y grid of ``spacing`` (m) around
        ``position``, seen from straight above (vertical rays from z = 2 m)."""
        g = np.arange(-half_extent, half_extent + 1e-12, spacing)
        x, y = np.meshgrid(g + self.position[0], g + self.position[1])
        o = np.stack([x.ravel(), y.ravel(), np.full(x.size, 2.0)], axis=1)
        d = np.tile(-Z_UP, (len(o), 1))
        s = self.cast(o, d, t)
        ok = np.isfinite(s)
        return o[ok] + s[ok, None] * d[ok]


def _disc(points, center, normal, radius) -> np.ndarray:
    """True for points within ``radius`` of ``center`` measured in the plane of ``normal``."""
    w = np.atleast_2d(points) - center
    return np.linalg.norm(w - np.outer(w @ normal, normal), axis=1) <= radius


@dataclass
class PlaneScene(Scene):
    """A horizontal table top through ``position`` (default z = 0) with a red disc of
    ``disc_radius`` (m) painted around ``position``."""

    name: ClassVar[str] = "plane"
    disc_radius: float = 0.05

    def solid(self, t):
        return HalfSpace(Z_UP, self.position)

    def protected(self, points, t=0.0):
        return _disc(points, self.position, Z_UP, self.disc_radius)


@dataclass
class InclinedPlaneScene(Scene):
    """A plane through ``position`` tilted by ``angle_deg`` about the world y axis (it rises
    towards -x), with a red disc of ``disc_radius`` (m) around ``position``."""

    name: ClassVar[str] = "inclined_plane"
    angle_deg: float = 20.0
    disc_radius: float = 0.05

    def check(self):
        if not 0 <= abs(self.angle_deg) < 80:
            raise InputError(f"scene 'inclined_plane': angle_deg = {self.angle_deg}; expected |angle| < 80 deg (visible from above)")

    @property
    def n(self):
        return _rot([0, 1, 0], math.radians(self.angle_deg)) @ Z_UP

    def solid(self, t):
        return HalfSpace(self.n, self.position)

    def protected(self, points, t=0.0):
        return _disc(points, self.position, self.n, self.disc_radius)


@dataclass
class SphereScene(Scene):
    """A red balloon of ``radius`` (m) resting on a white table (z = 0). ``position`` is the
    balloon centre; by default (0, 0, radius)."""

    name: ClassVar[str] = "sphere"
    radius: float = 0.06
    position: tuple = None

    def __post_init__(self):
        if self.position is None:
            self.position = (0.0, 0.0, float(self.radius))
        super().__post_init__()

    def check(self):
        if self.radius <= 0:
            raise InputError(f"scene 'sphere': radius = {self.radius}; expected > 0 m")

    def solid(self, t):
        return Union([HalfSpace(Z_UP, [0, 0, 0]), Ball(self.position, self.radius)])

    def protected(self, points, t=0.0):
        return np.linalg.norm(np.atleast_2d(points) - self.position, axis=1) <= self.radius + _TOL


@dataclass
class LedgeScene(Scene):
    """Two horizontal levels ``step`` (m) apart: the table z = position.z for x < position.x
    and a raised (red, protected) level z = position.z + step for x > position.x; the step
    edge runs along world y."""

    name: ClassVar[str] = "ledge"
    step: float = 0.005

    def check(self):
        if self.step <= 0:
            raise InputError(f"scene 'ledge': step = {self.step}; expected > 0 m (default 0.005)")

    def solid(self, t):
        p = self.position
        upper = Convex([HalfSpace(Z_UP, p + [0, 0, self.step]), HalfSpace([-1, 0, 0], p)])
        return Union([HalfSpace(Z_UP, p), upper])

    def protected(self, points, t=0.0):
        p = np.atleast_2d(points)
        return (p[:, 0] >= self.position[0] - _TOL) & (p[:, 2] >= self.position[2] + self.step / 2)


@dataclass
class BowlScene(Scene):
    """A concave spherical bowl (radius of curvature ``radius``, ``depth`` m deep) cut into the
    table z = position.z, centred on ``position``; the inside of the bowl is red."""

    name: ClassVar[str] = "bowl"
    radius: float = 0.08
    depth: float = 0.03

    def check(self):
        if not 0 < self.depth < self.radius:
            raise InputError(f"scene 'bowl': depth = {self.depth}, radius = {self.radius}; expected 0 < depth < radius (m)")

    @property
    def rim_radius(self) -> float:
        return math.sqrt(self.radius**2 - (self.radius - self.depth) ** 2)

    def solid(self, t):
        c = self.position + [0, 0, self.radius - self.depth]
        return PlaneMinusBall(HalfSpace(Z_UP, self.position), Ball(c, self.radius))

    def protected(self, points, t=0.0):
        p = np.atleast_2d(points)
        return _disc(p, self.position, Z_UP, self.rim_radius + _TOL) & (p[:, 2] <= self.position[2] + _TOL)


@dataclass
class BumpScene(Scene):
    """A convex spherical cap (radius of curvature ``radius``, ``height`` m tall) on the table
    z = position.z, centred on ``position``; the cap is red."""

    name: ClassVar[str] = "bump"
    radius: float = 0.06
    height: float = 0.02

    def check(self):
        if not 0 < self.height <= self.radius:
            raise InputError(f"scene 'bump': height = {self.height}, radius = {self.radius}; expected 0 < height <= radius (m)")

    @property
    def center(self):
        return self.position + [0, 0, self.height - self.radius]

    def solid(self, t):
        return Union([HalfSpace(Z_UP, self.position), Ball(self.center, self.radius)])

    def protected(self, points, t=0.0):
        p = np.atleast_2d(points)
        return (np.linalg.norm(p - self.center, axis=1) <= self.radius + _TOL) & (p[:, 2] > self.position[2] + _TOL)


@dataclass
class CornerScene(Scene):
    """Two planes meeting at a sharp edge along world y through ``position``, with a dihedral
    angle of ``angle_deg`` (default 90). ``concave=False``: a ridge (convex edge, faces sloping
    down to both sides); ``concave=True``: a V groove. Default position: the edge at z = 0.1 m
    (ridge) or z = -0.1 m (groove). The +x face is red."""

    name: ClassVar[str] = "corner"
    angle_deg: float = 90.0
    concave: bool = False
    position: tuple = None

    def __post_init__(self):
        if isinstance(self.concave, str):
            self.concave = self.concave.lower() in ("1", "true", "yes")
        if self.position is None:
            self.position = (0.0, 0.0, -0.1 if self.concave else 0.1)
        super().__post_init__()

    def check(self):
        if not 20 <= self.angle_deg <= 160:
            raise InputError(f"scene 'corner': angle_deg = {self.angle_deg}; expected 20..160 deg")

    def _normals(self):
        half = math.radians(90 - self.angle_deg / 2)  # face tilt from horizontal
        s = -1.0 if self.concave else 1.0
        n_pos = _rot([0, 1, 0], s * half) @ Z_UP  # face on the +x side
        n_neg = _rot([0, 1, 0], -s * half) @ Z_UP
        return n_pos, n_neg

    def solid(self, t):
        n_pos, n_neg = self._normals()
        halves = [HalfSpace(n_pos, self.position), HalfSpace(n_neg, self.position)]
        return Union(halves) if self.concave else Convex(halves)

    def protected(self, points, t=0.0):
        return np.atleast_2d(points)[:, 0] >= self.position[0]


@dataclass
class TranslatingPlaneScene(Scene):
    """A horizontal plane moving along its normal (world z) at ``speed`` m/s, starting through
    ``position`` at t = 0 and moving up. With ``travel`` > 0 (m) it reverses at
    position.z +- travel/2 (a triangle wave); with ``travel`` = 0 it keeps going. A red disc of
    ``disc_radius`` around the moving anchor point is protected. ``start`` (s, None: always
    moving): the scene time at which the motion begins; before it the plane rests through
    ``position``. A live experiment sets it once its loop runs (``math.inf`` until then), so
    the motion begins with the experiment whatever the start-up (kernel builds) took."""

    name: ClassVar[str] = "translating_plane"
    speed: float = 0.08
    travel: float = 0.2
    disc_radius: float = 0.05
    start: Optional[float] = None
    moving: ClassVar[bool] = True

    def check(self):
        if self.travel < 0:
            raise InputError(f"scene 'translating_plane': travel = {self.travel}; expected >= 0 m (0: no reversal)")

    def offset(self, t: float) -> float:
        """Displacement (m) of the plane along +z at time ``t`` (s)."""
        if self.start is not None:
            if not t > self.start:
                return 0.0
            t = t - self.start
        u = self.speed * t
        if self.travel <= 0 or self.speed == 0:
            return u
        a = self.travel / 2
        u = u % (4 * a)
        if u < a:
            return u
        if u < 3 * a:
            return 2 * a - u
        return u - 4 * a

    def anchor(self, t):
        return self.position + [0, 0, self.offset(t)]

    def solid(self, t):
        return HalfSpace(Z_UP, self.anchor(t))

    def protected(self, points, t=0.0):
        return _disc(points, self.anchor(t), Z_UP, self.disc_radius)


@dataclass
class RockingPlatformScene(Scene):
    """A flat platform on a rocking mixer (dissertation fig. 3.10): a plane through the pivot
    ``position`` (default 5 cm above the table) tilting about ``axis`` (default world y) by
    angle(t) = amplitude_deg * sin(2 pi t / period + phase) (deg, s, rad). A red plate of
    ``disc_radius`` (m) around the pivot is protected."""

    name: ClassVar[str] = "rocking_platform"
    amplitude_deg: float = 10.0
    period: float = 3.0
    phase: float = 0.0
    axis: tuple = (0.0, 1.0, 0.0)
    disc_radius: float = 0.1
    position: tuple = (0.0, 0.0, 0.05)
    moving: ClassVar[bool] = True

    def __post_init__(self):
        self.axis = _vec3(self.axis, "scene 'rocking_platform': axis")
        super().__post_init__()

    def check(self):
        if self.period <= 0:
            raise InputError(f"scene 'rocking_platform': period = {self.period}; expected > 0 s")
        if np.linalg.norm(self.axis) == 0 or abs(self.amplitude_deg) >= 80:
            raise InputError(
                f"scene 'rocking_platform': axis = {self.axis.tolist()}, amplitude_deg = {self.amplitude_deg}; "
                "expected a non-zero axis and |amplitude| < 80 deg"
            )

    def angle(self, t: float) -> float:
        """Tilt angle (rad) at time ``t`` (s)."""
        return math.radians(self.amplitude_deg) * math.sin(2 * math.pi * t / self.period + self.phase)

    def n(self, t):
        return _rot(self.axis, self.angle(t)) @ Z_UP

    def solid(self, t):
        return HalfSpace(self.n(t), self.position)

    def protected(self, points, t=0.0):
        return _disc(points, self.position, self.n(t), self.disc_radius)


SCENES = {
    cls.name: cls
    for cls in (
        PlaneScene,
        InclinedPlaneScene,
        SphereScene,
        LedgeScene,
        BowlScene,
        BumpScene,
        CornerScene,
        TranslatingPlaneScene,
        RockingPlatformScene,
    )
}


def scene_options(name: str) -> list[str]:
    """Option names the scene ``name`` accepts."""
    return [f.name for f in fields(SCENES[name])]


def make_scene(name: str, **options) -> Scene:
    """Build the scene ``name`` (one of ``SCENES``) with its options (see each class)."""
    if name not in SCENES:
        raise InputError(f"unknown synthetic scene {name!r}; expected one of: {', '.join(SCENES)}")
    unknown = sorted(set(options) - set(scene_options(name)))
    if unknown:
        raise InputError(
            f"scene {name!r}: unknown option(s) {', '.join(unknown)}; "
            f"it accepts: {', '.join(scene_options(name))}"
        )
    return SCENES[name](**options)
