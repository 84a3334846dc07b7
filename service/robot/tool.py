"""The robot's own tool as capsules in the world frame (for the self-filter, kernels/selffilter.py).

The self-filter removes only what is known to be the robot (SAFETY.md S5): its real kinematics
and a tool model that was configured, never an assumed one.

* A Raven II instrument is a straight shaft through the remote centre of motion (RCM) down to
  the wrist, and a short wrist-to-tip link with the jaws; both follow from the arm's kinematics
  (the RCM and the wrist point), and the instrument's dimensions are the Raven II's own
  (``ToolModel`` defaults), so a Raven II has a tool model unless ``[robot.tool]`` says otherwise.
* Any other robot (the Cartesian point mass, a robot behind the CRTK interface) has no tool
  model until ``[robot.tool] parts`` gives its capsules in the tip frame. Without one there is
  no self-filter (``tool_model_for`` says why, and the service's status shows it): a guessed
  shaft axis would cut holes in the protected surface in front of the tool.

``[robot.tool]`` keys (m): ``shaft_radius``, ``shaft_length``, ``wrist_radius`` (RCM instruments
only) and ``parts = [[ax, ay, az, bx, by, bz, radius], ...]`` (capsules with ends a and b in the
tip frame: jaws, a retractor blade, a camera housing).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from pointfence.kernels.errors import InputError
from pointfence.kernels.selffilter import Capsule

from ..schema import parse_table, setting

#: the largest capsule radius and length accepted for a tool part (m): a "tool" larger than this
#: would hide a whole scene from the fixtures (S5, S7)
MAX_PART_RADIUS = 0.05
MAX_PART_LENGTH = 0.6
#: one ``parts`` entry in TOML: [ax, ay, az, bx, by, bz, radius] (m, tip frame)
Part = Tuple[(float,) * 7]


def _parts(v: tuple, label: str) -> tuple:
    """TOML parts (7 numbers each) -> ((a), (b), radius) capsules in the tip frame."""
    return tuple((tuple(p[:3]), tuple(p[3:6]), p[6]) for p in v)


@dataclass(frozen=True)
class ToolModel:
    """Capsule model of the instrument (m).

    shaft_radius: the shaft through the RCM (Raven II instruments: 8.3 mm diameter, about 4.2 mm).
    shaft_length: how much of the shaft to model, from the wrist back out through the RCM.
    wrist_radius: the wrist-to-tip link and the closed jaws.
    parts: extra capsules ((a, b, radius), ...) with a and b in the tip frame.

    The shaft and wrist apply only to robots whose kinematics give an RCM and a wrist point
    (Raven II); for any other robot the tool is ``parts`` alone.
    """

    TABLE = "robot.tool"
    shaft_radius: float = setting(0.0042, doc="the instrument's shaft through the RCM: radius (m; RCM robots)")
    shaft_length: float = setting(0.35, doc="modelled shaft length, from the wrist out through the RCM (m; RCM robots)")
    wrist_radius: float = setting(0.005, doc="the wrist-to-tip link and closed jaws: radius (m; RCM robots)")
    parts: tuple = setting((), toml=Tuple[Part, ...], convert=_parts, default_doc="[]",
                           doc="capsules [ax, ay, az, bx, by, bz, radius] in the tip frame (m)")

    def __post_init__(self):
        limits = {"shaft_radius": MAX_PART_RADIUS, "shaft_length": MAX_PART_LENGTH, "wrist_radius": MAX_PART_RADIUS}
        for key, top in limits.items():
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and 0 <= v <= top):
                raise InputError(f"tool {key} = {v!r}; expected a finite number in [0, {top}] m")
        for p in self.parts:
            if len(p) != 3:
                raise InputError(f"tool part {p!r}; expected (a, b, radius) in the tip frame")
            a, b, r = np.asarray(p[0], float), np.asarray(p[1], float), p[2]
            if a.shape != (3,) or b.shape != (3,) or not (np.isfinite(a).all() and np.isfinite(b).all()):
                raise InputError(f"tool part {p!r}: ends a and b must be 3 finite numbers each (m, tip frame)")
            if not (isinstance(r, (int, float)) and math.isfinite(r) and 0 < r <= MAX_PART_RADIUS):
                raise InputError(f"tool part {p!r}: radius {r!r} must be in (0, {MAX_PART_RADIUS}] m")
            if np.linalg.norm(b - a) > MAX_PART_LENGTH:
                raise InputError(f"tool part {p!r}: longer than {MAX_PART_LENGTH} m")

    def table(self) -> dict:
        """This model as a plain ``[robot.tool]`` table (JSON-able)."""
        return {"shaft_radius": self.shaft_radius, "shaft_length": self.shaft_length, "wrist_radius": self.wrist_radius,
                "parts": [[*map(float, a), *map(float, b), float(r)] for a, b, r in self.parts]}


def has_rcm(robot) -> bool:
    """Whether ``robot``'s kinematics give the instrument's axis (an RCM and a wrist point)."""
    kin = getattr(robot, "kin", None)
    return kin is not None and hasattr(kin, "wrist_point")


def parse_tool(table) -> ToolModel:
    """``[robot.tool]`` (see the module docstring) -> ToolModel; InputError naming the bad key
    (keys and types from ToolModel's fields, schema.parse_table)."""
    return parse_table(ToolModel, table, "[robot.tool]")


def tool_model_for(robot, tool=None) -> tuple:
    """(ToolModel or None, reason): the tool of ``robot`` as configured by ``tool`` (a
    ToolModel, a ``[robot.tool]`` table, or None: not configured). None where the tool is not
    known (see the module docstring)."""
    if robot is None:
        return None, "no robot (ideal robot: nothing to filter)"
    model = parse_tool(tool) if isinstance(tool, dict) else tool
    if has_rcm(robot):
        return (model if model is not None else ToolModel()), "RCM instrument (shaft, wrist) from the kinematics"
    if model is None or not model.parts:
        return None, (f"robot model {getattr(robot, 'model', type(robot).__name__)!r} has no tool model: the "
                      "self-filter is off; give the tool's capsules in [robot.tool] parts to turn it on")
    return model, f"{len(model.parts)} configured part(s) in the tip frame"


def tool_capsules(robot, q=None, model: Optional[ToolModel] = None) -> list:
    """The tool of ``robot`` at joints ``q`` (default: measured) as world-frame capsules: the
    instrument's shaft and wrist where the kinematics give them (Raven II), and ``model.parts``.
    A robot without an RCM contributes only its configured parts (none: no capsules)."""
    model = model if model is not None else ToolModel()
    if q is None:
        q = robot.measured_js().position
    T = np.asarray(robot.forward_kinematics(q), dtype=np.float64)
    tip, R = T[:3, 3], T[:3, :3]
    caps = []
    if has_rcm(robot):   # Raven II: the shaft runs through the RCM
        Twb = robot.T_world_base
        w_base, u = robot.kin.wrist_point(np.asarray(q, dtype=np.float64))
        wrist = Twb[:3, :3] @ np.asarray(w_base) + Twb[:3, 3]
        rcm = Twb[:3, 3]
        out = rcm - wrist
        n = np.linalg.norm(out)
        out = out / n if n > 1e-9 else -(Twb[:3, :3] @ np.asarray(u))
        caps.append(Capsule(tuple(wrist), tuple(wrist + model.shaft_length * out), model.shaft_radius))
        caps.append(Capsule(tuple(wrist), tuple(tip), model.wrist_radius))
    for a, b, r in model.parts:
        caps.append(Capsule(tuple(R @ np.asarray(a, float) + tip), tuple(R @ np.asarray(b, float) + tip), float(r)))
    return caps
