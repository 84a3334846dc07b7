"""Building a robot by model name, and the ``[robot]`` table of the scene configuration.

TOML shape (every key but ``model`` is an option of that model; unknown keys are errors that
name the key and suggest the closest known one)::

    [robot]
    model = "raven2"              # "raven2" (default) | "point-mass" | "crtk" | "raven2-itp"
    # raven2 options (SI units; per-joint lists have 6 values: shoulder, elbow, insertion,
    # tool roll, wrist, grasper yaw):
    arm = "right"                 # "right" (green) | "left" (gold)
    q0 = [0.5236, 1.5708, 0.40, 0.0, 0.0, 0.0]   # start joints (rad, rad, m, rad, rad, rad)
    T_world_base = [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]   # mount, 16 numbers row-major
    mount_tool_down = [0.0, 0.0, 0.15]   # or: RCM at this world point, tool shaft pointing down at q0
    workspace_min = [-0.1, -0.1, 0.0]    # optional world box the tip must stay in
    workspace_max = [0.1, 0.1, 0.2]
    joint_lower = [...]            # optional, narrower than the Raven's limits
    joint_upper = [...]
    inertia = [0.06, 0.04, 0.40, 2e-5, 2e-5, 2e-5]
    damping = [0.05, 0.04, 2.0, 1e-5, 1e-5, 1e-5]
    bandwidth = [120, 120, 150, 200, 200, 200]     # rad/s; or kp / kd / ki explicitly
    damping_ratio = [0.8, 0.8, 0.8, 0.8, 0.8, 0.8]
    integral_rate = [2, 2, 2, 2, 2, 2]
    integral_band = [1e-3, 1e-3, 1e-4, 5e-3, 5e-3, 5e-3]
    max_torque = [8, 8, 40, 0.05, 0.05, 0.05]
    max_velocity = [3, 3, 0.3, 10, 10, 10]
    fault_error = [0.3, 0.3, 0.05, 1, 1, 1]
    gravity = true
    gravity_vector = [0, 0, -9.81]
    tool_mass = 0.3
    gravity_compensation = 0.9
    [robot.tool]                   # the tool the self-filter removes (robot/tool.py): a Raven II
    shaft_radius = 0.0042          # has its instrument; any other robot has none until ``parts``
    parts = [[0, 0, 0, 0, 0, 0.02, 0.004]]   # capsules [a, b, radius] in the tip frame
    control_rate_hz = 1000

    [robot]
    model = "point-mass"
    mass = 0.5
    damping = 2.0
    bandwidth = 100.0              # or kp / kd
    damping_ratio = 0.9
    max_force = 10.0
    max_velocity = 0.5
    workspace_min = [-0.5, -0.5, -0.5]
    workspace_max = [0.5, 0.5, 0.5]
    x0 = [0.0, 0.0, 0.1]
    T_world_base = [...]
    fault_error = 0.05
    control_rate_hz = 1000

    [robot]
    model = "crtk"                 # an arm behind CRTK over ROS 2 (robot/crtk.py)
    namespace = "PSM1"
    frame_id = "PSM1_base"         # header.frame_id of its poses (default "<namespace>_base")
    dof = 6                        # joints in its measured_js
    T_world_base = [...]           # its base frame in the world
    workspace_min = [-0.1, -0.1, -0.2]
    workspace_max = [0.1, 0.1, 0.0]
    measured_timeout_s = 0.02      # watchdog (s, at most 0.25)
    operating_state_type = "crtk"  # "crtk" | "string" | "none"
    # servo_cp_topic, measured_cp_topic, measured_js_topic, operating_state_topic: overrides
    connect_timeout_s = 5.0

    [robot]
    model = "raven2-itp"           # a real Raven II, pointfence as its ITP master console (robot/raven_itp.py)
    address = "192.168.0.10:36000" # the Raven's network layer (UDP)
    arm = "right"                  # "right" (green, u_struct slot 1) | "left" (gold, slot 0)
    T_world_base = [...]           # the arm's base frame (the Raven's "robot 0 frame") in the world
    x0 = [0.0, 0.0, 0.1]           # start of the integrated pose (world, m; default the base origin)
    workspace_min = [-0.1, -0.1, -0.2]
    workspace_max = [0.1, 0.1, 0.0]
    max_speed = 0.2                # m/s and rad/s the increments are streamed at, at most
    max_angular_speed = 6.0
    feedback_port = 36001          # where the Raven (built with NET_SEND) sends its v_struct; 0: none
    feedback_timeout_s = 0.05      # watchdog on that feedback (s, at most 0.25)
    sync_packets = 1001            # surgeon-off packets at start (the Raven's sequence rules)
    connect_timeout_s = 5.0
"""
from __future__ import annotations

import difflib

import numpy as np

from pointfence.kernels.errors import InputError

from .crtk import CrtkRobot
from .base import Robot, as_vector
from .point_mass import PointMass
from .raven2 import Raven2
from .raven_itp import RavenItpRobot
from .settings import OPTIONS, RobotConfig, option_error, parse_robot

MODELS = {"raven2": Raven2, "point-mass": PointMass, "crtk": CrtkRobot, "raven2-itp": RavenItpRobot}


def model_options(model: str) -> set:
    """The option names a model accepts (the fields of its options dataclass, robot/settings.py)."""
    _model(model)
    return set(OPTIONS[model].__dataclass_fields__)


def _model(model) -> type:
    if model not in MODELS:
        near = difflib.get_close_matches(str(model), MODELS, n=1)
        hint = f"; did you mean {near[0]!r}?" if near else ""
        raise InputError(f"robot model {model!r} is not known{hint} Known models: {', '.join(MODELS)}")
    return MODELS[model]


def make_robot(model: str = "raven2", *, connect: bool = True, **options) -> Robot:
    """A robot: ``model`` is 'raven2' (the default robot), 'point-mass', 'crtk' (an arm over
    ROS 2) or 'raven2-itp' (a real Raven II over ITP); ``options`` are that model's keyword options (see the module docstring).
    ``connect=False``: a model that talks to an arm ('crtk', 'raven2-itp') opens no connection (a copy for
    geometry and checks: the service's side of an arm in the robot process); simulated models
    ignore it. Raises InputError on an unknown model or option (naming it and suggesting the
    closest) or a bad value."""
    cls = _model(model)
    for key in options:
        if key not in OPTIONS[model].__dataclass_fields__:
            raise option_error(key, model, f"robot model {model!r}")
    if options.get("mount_tool_down") is not None:
        rcm = options.pop("mount_tool_down")
        if options.get("T_world_base") is not None:
            raise InputError("robot: give T_world_base or mount_tool_down, not both")
        options["T_world_base"] = Raven2.mount_tool_down(as_vector(rcm, 3, "mount_tool_down"),
                                                         arm=options.get("arm", "right"), q=options.get("q0"))
    options.pop("mount_tool_down", None)
    if options.get("T_world_base") is not None:
        T = np.asarray(options["T_world_base"], dtype=object)
        if T.size != 16:
            raise InputError(f"T_world_base has {T.size} numbers; expected 16 (a 4x4, row-major)")
        options["T_world_base"] = as_vector(np.asarray(T, dtype=float).ravel(), 16, "T_world_base").reshape(4, 4)
    if cls is CrtkRobot or cls is RavenItpRobot:
        options["connect"] = connect
    return cls(**options)


def robot_from_config(table, connect: bool = True) -> Robot:
    """Build the robot of a ``[robot]`` configuration: a ``RobotConfig`` (robot/settings.py) or
    a plain TOML table (see the module docstring; checked by ``parse_robot``). The model
    defaults to 'raven2'; "none" (the ideal robot) has no robot to build. ``connect``: see
    ``make_robot``."""
    cfg = parse_robot(table) if not isinstance(table, RobotConfig) else table
    if cfg.model not in MODELS:
        raise InputError(f"[robot] model = {cfg.model!r} has no robot to build (the ideal robot); "
                         f"expected one of {', '.join(repr(m) for m in MODELS)}")
    try:
        return make_robot(cfg.model, connect=connect, **cfg.kwargs())
    except InputError as e:
        raise InputError(f"[robot] {e}") from None
