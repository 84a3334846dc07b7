"""A synthetic scene with the robot's tool in it: the tool's capsules are part of what the
cameras see (they occlude and cast projector shadows), but not of the protected object."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from .geometry import Solid, Union
from .scenes import Scene


class CapsuleSolid(Solid):
    """Material within ``radius`` of the segment a-b."""

    def __init__(self, a, b, radius):
        self.a = np.asarray(a, np.float64)
        self.b = np.asarray(b, np.float64)
        self.r = float(radius)

    def sdf(self, p):
        from pointfence.kernels.selffilter import segment_distance

        return segment_distance(p, self.a, self.b) - self.r

    def enter(self, o, d):
        """First parameter s >= 0 with o + s d inside (cylinder side, then both end spheres)."""
        d = np.atleast_2d(np.asarray(d, np.float64))
        o = np.broadcast_to(np.atleast_2d(np.asarray(o, np.float64)), d.shape)
        n = len(d)
        ba = self.b - self.a
        L2 = float(ba @ ba)
        best = np.full(n, np.inf)
        inside = self.sdf(o) <= 0
        oa = o - self.a
        if L2 > 0:  # infinite cylinder, clipped to the segment
            baba, bard, baoa = L2, d @ ba, oa @ ba
            rdoa, oaoa, rdrd = np.einsum("ij,ij->i", d, oa), np.einsum("ij,ij->i", oa, oa), np.einsum("ij,ij->i", d, d)
            A = baba * rdrd - bard * bard
            B = baba * rdoa - baoa * bard
            C = baba * oaoa - baoa * baoa - self.r * self.r * baba
            disc = B * B - A * C
            ok = (A > 1e-18) & (disc >= 0)
            with np.errstate(invalid="ignore", divide="ignore"):
                s = (-B - np.sqrt(np.maximum(disc, 0))) / np.where(ok, A, 1.0)
            y = baoa + s * bard
            hit = ok & (s >= 0) & (y > 0) & (y < baba)
            best = np.where(hit, s, best)
        for c in (self.a, self.b):  # end spheres
            oc = o - c
            bb = np.einsum("ij,ij->i", d, oc)
            aa = np.einsum("ij,ij->i", d, d)
            cc = np.einsum("ij,ij->i", oc, oc) - self.r * self.r
            disc = bb * bb - aa * cc
            with np.errstate(invalid="ignore", divide="ignore"):
                s = (-bb - np.sqrt(np.maximum(disc, 0))) / aa
            hit = (disc >= 0) & (s >= 0)
            best = np.where(hit & (s < best), s, best)
        return np.where(inside, 0.0, best)


@dataclass
class ToolInScene(Scene):
    """``base`` (a Scene) plus the tool ``capsules`` (kernels.selffilter.Capsule, world frame),
    which may be replaced between frames (the robot moves)."""

    name: ClassVar[str] = "tool_in_scene"
    moving: ClassVar[bool] = True
    base: Scene = None
    capsules: list = field(default_factory=list)

    def __post_init__(self):
        self.position = np.asarray(self.base.position, np.float64)
        self._static = None

    def solid(self, t):
        parts = [self.base._solid(t)] + [CapsuleSolid(c.a, c.b, c.radius) for c in self.capsules]
        return Union(parts)

    def protected(self, points, t=0.0):
        p = np.atleast_2d(points)
        prot = self.base.protected(p, t)
        for c in self.capsules:
            prot &= c.distance(p) > 1e-4
        return prot

    def tool_distance(self, points) -> np.ndarray:
        """Distance of points (N, 3) to the tool's surface (inf without a tool)."""
        p = np.atleast_2d(points)
        d = np.full(len(p), np.inf)
        for c in self.capsules:
            d = np.minimum(d, c.distance(p))
        return d
