"""The ``[robot]`` table, typed: the model, that model's options and ``[robot.tool]``.

TOML shape: ``model`` and the model's options side by side in ``[robot]`` (see factory.py), the
tool in ``[robot.tool]``. Each model's options are a dataclass whose fields are the keyword
options of its constructor (a test keeps them equal); a default is the constructor's own (read
from its signature) or, for the Raven II's per-joint vectors, its ``raven2.DEFAULTS``. The
values' ranges and shapes are checked by the constructors when the robot is built
(``factory.robot_from_config``); here keys and types.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Literal, Optional, Tuple, Union

from pointfence.kernels.errors import InputError

from ..schema import check_value, parse_table, rows, setting, unknown_key
from .crtk import CrtkRobot
from .point_mass import PointMass
from .raven2 import DEFAULTS as RAVEN2_DEFAULTS
from .raven2 import Raven2
from .raven_itp import RavenItpRobot
from .tool import ToolModel, parse_tool

Vec = Tuple[float, ...]
Vec3 = Tuple[float, float, float]


def _default(cls, name: str):
    """The constructor default of option ``name`` of robot class ``cls``."""
    return inspect.signature(cls.__init__).parameters[name].default


def _per_joint(name: str) -> str:
    return "[" + ", ".join(f"{x:g}" for x in RAVEN2_DEFAULTS[name]) + "]"


@dataclass(frozen=True)
class Raven2Options:
    """``[robot]`` options of model "raven2" (raven2.Raven2): SI units; per-joint lists have 6
    values (shoulder, elbow, insertion, tool roll, wrist, grasper yaw)."""

    TABLE = "robot"
    arm: Literal["right", "left"] = setting(_default(Raven2, "arm"), doc='"right" (green) or "left" (gold) arm')
    q0: Optional[Vec] = setting(None, doc="start joints (rad, rad, m, rad, rad, rad)", default_doc="the Raven's home")
    T_world_base: Optional[Vec] = setting(None, doc="mount: base-to-world transform, 16 numbers row-major",
                                          default_doc="identity")
    mount_tool_down: Optional[Vec3] = setting(None, doc="or: the RCM at this world point (m), shaft pointing down at q0",
                                              default_doc="none")
    joint_lower: Optional[Vec] = setting(None, doc="lower joint limits, within the Raven's", default_doc="the Raven's")
    joint_upper: Optional[Vec] = setting(None, doc="upper joint limits, within the Raven's", default_doc="the Raven's")
    workspace_min: Optional[Vec] = setting(None, doc="world box the tip must stay in: lower corner (m)",
                                           default_doc="none")
    workspace_max: Optional[Vec] = setting(None, doc="world box the tip must stay in: upper corner (m)",
                                           default_doc="none")
    inertia: Optional[Vec] = setting(None, doc="per joint (kg m^2 / kg)", default_doc=_per_joint("inertia"))
    damping: Optional[Vec] = setting(None, doc="per joint viscous damping (N m s/rad / N s/m)",
                                     default_doc=_per_joint("damping"))
    bandwidth: Optional[Vec] = setting(None, doc="per joint servo bandwidth (rad/s); or kp / kd / ki",
                                       default_doc=_per_joint("bandwidth"))
    damping_ratio: Optional[Vec] = setting(None, doc="per joint servo damping ratio",
                                           default_doc=_per_joint("damping_ratio"))
    integral_rate: Optional[Vec] = setting(None, doc="per joint integral rate (1/s)",
                                           default_doc=_per_joint("integral_rate"))
    kp: Optional[Vec] = setting(None, doc="per joint proportional gain", default_doc="from bandwidth")
    ki: Optional[Vec] = setting(None, doc="per joint integral gain", default_doc="from integral_rate")
    kd: Optional[Vec] = setting(None, doc="per joint derivative gain", default_doc="from damping_ratio")
    max_torque: Optional[Vec] = setting(None, doc="per joint torque / force limit (N m / N)",
                                        default_doc=_per_joint("max_torque"))
    max_velocity: Optional[Vec] = setting(None, doc="per joint velocity limit (rad/s / m/s)",
                                          default_doc=_per_joint("max_velocity"))
    fault_error: Optional[Vec] = setting(None, doc="per joint following error that faults the arm (rad / m)",
                                         default_doc=_per_joint("fault_error"))
    integral_band: Optional[Vec] = setting(None, doc="per joint error band of the integral term (rad / m)",
                                           default_doc=_per_joint("integral_band"))
    gravity: bool = setting(_default(Raven2, "gravity"), doc="simulate gravity on the arm")
    gravity_vector: Vec3 = setting(_default(Raven2, "gravity_vector"), doc="gravity, world frame (m/s^2)")
    tool_mass: float = setting(_default(Raven2, "tool_mass"), doc="instrument mass (kg)")
    gravity_compensation: float = setting(_default(Raven2, "gravity_compensation"),
                                          doc="fraction of gravity the controller compensates")
    control_rate_hz: float = setting(_default(Raven2, "control_rate_hz"), doc="the arm controller's rate (Hz)")


@dataclass(frozen=True)
class PointMassOptions:
    """``[robot]`` options of model "point-mass" (point_mass.PointMass): a Cartesian mass."""

    TABLE = "robot"
    mass: float = setting(_default(PointMass, "mass"), doc="mass (kg)")
    damping: float = setting(_default(PointMass, "damping"), doc="viscous damping (N s/m)")
    bandwidth: float = setting(_default(PointMass, "bandwidth"), doc="servo bandwidth (rad/s); or kp / kd")
    damping_ratio: float = setting(_default(PointMass, "damping_ratio"), doc="servo damping ratio")
    kp: Optional[float] = setting(None, doc="proportional gain (N/m)", default_doc="mass bandwidth^2")
    kd: Optional[float] = setting(None, doc="derivative gain (N s/m)", default_doc="from damping_ratio")
    max_force: float = setting(_default(PointMass, "max_force"), doc="actuator force limit (N)")
    max_velocity: float = setting(_default(PointMass, "max_velocity"), doc="velocity limit (m/s)")
    workspace_min: Vec3 = setting(_default(PointMass, "workspace_min"), doc="box the mass may occupy: lower corner (m, base)")
    workspace_max: Vec3 = setting(_default(PointMass, "workspace_max"), doc="box the mass may occupy: upper corner (m, base)")
    x0: Optional[Vec3] = setting(None, doc="start position (m, base frame)", default_doc="the box's centre")
    T_world_base: Optional[Vec] = setting(None, doc="mount: base-to-world transform, 16 numbers row-major",
                                          default_doc="identity")
    fault_error: float = setting(_default(PointMass, "fault_error"), doc="following error that faults it (m; 0: never)")
    control_rate_hz: float = setting(_default(PointMass, "control_rate_hz"), doc="the controller's rate (Hz)")


@dataclass(frozen=True)
class CrtkOptions:
    """``[robot]`` options of model "crtk" (robot/crtk.CrtkRobot): an arm behind CRTK over
    ROS 2 (a dVRK PSM ...): setpoints out on servo_cp, state in from measured_cp, measured_js,
    operating_state (service/robot/README.md)."""

    TABLE = "robot"
    namespace: str = setting(_default(CrtkRobot, "namespace"), doc="the arm's ROS namespace (its topics' prefix)")
    frame_id: str = setting("", doc="header.frame_id of its poses (its base frame)", default_doc='"<namespace>_base"')
    dof: int = setting(_default(CrtkRobot, "dof"), doc="joints in its measured_js")
    T_world_base: Optional[Vec] = setting(None, doc="the arm's base frame in the world, 16 numbers row-major",
                                          default_doc="identity")
    workspace_min: Optional[Vec] = setting(None, doc="world box the tip must stay in: lower corner (m)",
                                           default_doc="none")
    workspace_max: Optional[Vec] = setting(None, doc="world box the tip must stay in: upper corner (m)",
                                           default_doc="none")
    measured_timeout_s: float = setting(_default(CrtkRobot, "measured_timeout_s"), positive=True,
                                        doc="watchdog: FAULT without a fresh measured_cp for this long (s)")
    operating_state_type: Literal["crtk", "string", "none"] = setting(
        _default(CrtkRobot, "operating_state_type"),
        doc='"crtk" (crtk_msgs/OperatingState) | "string" (std_msgs/String) | "none" (no state topic)')
    servo_cp_topic: str = setting("", doc="command topic (relative: under namespace)", default_doc='"servo_cp"')
    measured_cp_topic: str = setting("", doc="measured pose topic", default_doc='"measured_cp"')
    measured_js_topic: str = setting("", doc="measured joints topic", default_doc='"measured_js"')
    operating_state_topic: str = setting("", doc="operating state topic", default_doc='"operating_state"')
    connect_timeout_s: float = setting(_default(CrtkRobot, "connect_timeout_s"), positive=True,
                                       doc="wait for the arm's first valid state at start (s; then FAULT)")
    control_rate_hz: float = setting(_default(CrtkRobot, "control_rate_hz"), doc="the rate servo_cp is streamed at (Hz)")
    jaw: bool = setting(False, doc="the arm has a jaw: the master's grasp out on jaw/servo_jp, its angle in from "
                                   "jaw/measured_js (sensor_msgs/JointState)")
    jaw_min: float = setting(_default(CrtkRobot, "jaw_min"), doc="the jaw's smallest commanded angle (rad)")
    jaw_max: float = setting(_default(CrtkRobot, "jaw_max"), doc="the jaw's largest commanded angle (rad)")


@dataclass(frozen=True)
class RavenItpOptions:
    """``[robot]`` options of model "raven2-itp" (robot/raven_itp.RavenItpRobot): a real Raven II,
    pointfence as its master console over the Raven's own ITP packets (UDP; clients/PROTOCOL.md)."""

    TABLE = "robot"
    address: str = setting("", doc='the Raven\'s network layer, "host:port" (UDP; it listens on 36000)',
                           default_doc="required")
    arm: Literal["right", "left"] = setting(_default(RavenItpRobot, "arm"),
                                           doc='"right" (green, u_struct slot 1) or "left" (gold, slot 0)')
    T_world_base: Optional[Vec] = setting(None, doc="the arm's base frame (Raven robot 0 frame) in the world, 16 "
                                          "numbers row-major", default_doc="identity")
    x0: Optional[Vec3] = setting(None, doc="start of the integrated (commanded) pose (world, m)",
                                 default_doc="the base origin")
    workspace_min: Optional[Vec] = setting(None, doc="world box the tip must stay in: lower corner (m)",
                                           default_doc="none")
    workspace_max: Optional[Vec] = setting(None, doc="world box the tip must stay in: upper corner (m)",
                                           default_doc="none")
    max_speed: float = setting(_default(RavenItpRobot, "max_speed"), positive=True,
                               doc="fastest the position increments stream (m/s)")
    max_angular_speed: float = setting(_default(RavenItpRobot, "max_angular_speed"), positive=True,
                                       doc="fastest the rotation increments stream (rad/s)")
    feedback_port: int = setting(_default(RavenItpRobot, "feedback_port"),
                                 doc="UDP port the Raven's v_struct arrives on (0: no feedback)")
    feedback_timeout_s: float = setting(_default(RavenItpRobot, "feedback_timeout_s"), positive=True,
                                        doc="watchdog: FAULT without valid feedback for this long (s)")
    sync_packets: int = setting(_default(RavenItpRobot, "sync_packets"),
                                doc="surgeon-off packets sent at start (the Raven's sequence rules)")
    connect_timeout_s: float = setting(_default(RavenItpRobot, "connect_timeout_s"), positive=True,
                                       doc="wait for the first feedback at start (s; then FAULT)")
    control_rate_hz: float = setting(_default(RavenItpRobot, "control_rate_hz"),
                                     doc="the packet rate (Hz): one u_struct per step")


#: the options dataclass of each robot model
OPTIONS = {"raven2": Raven2Options, "point-mass": PointMassOptions, "crtk": CrtkOptions,
           "raven2-itp": RavenItpOptions}
Model = Literal["raven2", "point-mass", "crtk", "raven2-itp", "none"]


@dataclass(frozen=True)
class RobotConfig:
    """``[robot]``: the simulated robot model, its options and its tool (``[robot.tool]``)."""

    TABLE = "robot"
    model: Model = setting("raven2", doc='"raven2" | "point-mass" | "crtk" (ROS 2) | "raven2-itp" (a real Raven II) | '
                           '"none" (ideal robot: X_r = X_r*)')
    options: Union[Raven2Options, PointMassOptions, CrtkOptions, RavenItpOptions, None] = setting(
        None, doc="the model's options, beside model in [robot]", default_doc="the model's defaults")
    tool: Optional[ToolModel] = setting(None, doc="[robot.tool]: the tool the self-filter removes (robot/tool.py)",
                                        default_doc="a Raven II's instrument; none for other robots")

    def __post_init__(self):
        if self.options is None and self.model in OPTIONS:
            object.__setattr__(self, "options", OPTIONS[self.model]())

    def kwargs(self) -> dict:
        """The model's keyword options (factory.make_robot)."""
        return {} if self.options is None else {k: getattr(self.options, k) for k in OPTIONS[self.model].__dataclass_fields__}

    def table(self) -> dict:
        """This configuration as a plain ``[robot]`` table (JSON-able: the hosted robot process)."""
        out: dict = {"model": self.model}
        out.update({k: list(v) if isinstance(v, tuple) else v for k, v in self.kwargs().items() if v is not None})
        if self.tool is not None:
            out["tool"] = self.tool.table()
        return out


def option_error(key: str, model: str, where: str) -> InputError:
    """Unknown option ``key`` of ``model``: the closest known key, and the model it belongs to."""
    known = set(OPTIONS[model].__dataclass_fields__)
    others = [m for m, c in OPTIONS.items() if key in c.__dataclass_fields__]
    other = f" ({key!r} is an option of model {others[0]!r})" if others else ""
    return unknown_key(key, known, where, other)


def parse_robot(table) -> RobotConfig:
    """``[robot]`` (a TOML table) -> RobotConfig; InputError naming the bad key or value."""
    if table is None:
        table = {}
    if isinstance(table, RobotConfig):
        return table
    if not isinstance(table, dict):
        raise InputError(f"[robot]: expected a table, got {type(table).__name__}")
    opts = dict(table)
    model = check_value(Model, opts.pop("model", "raven2"), "[robot] model")
    tool = opts.pop("tool", None)
    if tool is not None and model in ("crtk", "raven2-itp"):
        raise InputError(f"[robot.tool] with model = {model!r}: the self-filter places the tool by the arm's kinematics "
                         "at each frame's capture time, and this arm's kinematics are its controller's; remove "
                         "[robot.tool] (the self-filter stays off for this arm)")
    tool = None if tool is None else parse_tool(tool)
    if model == "none":
        if opts:
            raise InputError(f"[robot] model = 'none' (the ideal robot) takes no options; got {', '.join(sorted(opts))}")
        return RobotConfig(model, None, tool)
    cls = OPTIONS[model]
    for key in opts:
        if key not in cls.__dataclass_fields__:
            raise option_error(key, model, "[robot]")
    return RobotConfig(model, parse_table(cls, opts, "[robot]"), tool)


def robot_rows() -> list:
    """The README rows of ``[robot]``: model, each model's options, then ``[robot.tool]``."""
    out = [("[robot]", k, t, d, doc) for k, t, d, doc in rows(RobotConfig) if k == "model"]
    for model, cls in OPTIONS.items():
        out += [(f"[robot] {model}", k, t, d, doc) for k, t, d, doc in rows(cls)]
    return out + [("[robot.tool]", k, t, d, doc) for k, t, d, doc in rows(ToolModel)]


