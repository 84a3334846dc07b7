"""The robot's own tool as capsules in the world frame (for the self-filter, kernels/selffilter.py).

A Raven II instrument is a straight shaft through the remote centre of motion (RCM) down to the
wrist, and a short wrist-to-tip link with the jaws; other robots carry a shaft along their tip
frame's +z axis. Extra parts (jaws, a retractor blade, a camera housing) are capsules given in
the tip frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pointfence.kernels.errors import InputError
from pointfence.kernels.selffilter import Capsule


@dataclass(frozen=True)
class ToolModel:
    """Capsule model of the instrument (m).

    shaft_radius: the shaft (Raven II instruments: 8.3 mm diameter, about 4.2 mm).
    shaft_length: how much of the shaft to model, from the wrist back out through the RCM.
    wrist_radius: the wrist-to-tip link and the closed jaws.
    parts: extra capsules ((a, b, radius), ...) with a and b in the tip frame.
    """

    shaft_radius: float = 0.0042
    shaft_length: float = 0.35
    wrist_radius: float = 0.005
    parts: tuple = ()

    def __post_init__(self):
        for key in ("shaft_radius", "shaft_length", "wrist_radius"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                raise InputError(f"tool {key} = {v!r}; expected a finite number >= 0 m")
        for p in self.parts:
            if len(p) != 3:
                raise InputError(f"tool part {p!r}; expected (a, b, radius) in the tip frame")


def tool_capsules(robot, q=None, model: ToolModel | None = None) -> list:
    """The tool of ``robot`` at joints ``q`` (default: measured) as world-frame capsules."""
    model = model if model is not None else ToolModel()
    if q is None:
        q = robot.measured_js().position
    T = np.asarray(robot.forward_kinematics(q), dtype=np.float64)
    tip, R = T[:3, 3], T[:3, :3]
    caps = []
    kin = getattr(robot, "kin", None)
    if kin is not None and hasattr(kin, "wrist_point"):  # Raven II: shaft through the RCM
        Twb = robot.T_world_base
        w_base, u = kin.wrist_point(np.asarray(q, dtype=np.float64))
        wrist = Twb[:3, :3] @ np.asarray(w_base) + Twb[:3, 3]
        rcm = Twb[:3, 3]
        out = rcm - wrist
        n = np.linalg.norm(out)
        out = out / n if n > 1e-9 else -(Twb[:3, :3] @ np.asarray(u))
        caps.append(Capsule(tuple(wrist), tuple(wrist + model.shaft_length * out), model.shaft_radius))
        caps.append(Capsule(tuple(wrist), tuple(tip), model.wrist_radius))
    else:  # a shaft along the tip frame's +z
        caps.append(Capsule(tuple(tip), tuple(tip + model.shaft_length * R[:, 2]), model.shaft_radius))
    for a, b, r in model.parts:
        caps.append(Capsule(tuple(R @ np.asarray(a, float) + tip), tuple(R @ np.asarray(b, float) + tip), float(r)))
    return caps
