"""The CRTK conventions on the wire, shared by the CRTK arm (crtk_robot.py) and the simulated CRTK
arm (sim_arm.py): topic names, quality of service, the operating-state message, and poses
between ``geometry_msgs/Pose`` (position, unit quaternion x y z w) and 4x4 transforms.

Topics of an arm in namespace ``PSM1`` (as the dVRK publishes them): ``/PSM1/servo_cp``
(``geometry_msgs/PoseStamped``, the command), ``/PSM1/measured_cp`` (``PoseStamped``),
``/PSM1/measured_js`` (``sensor_msgs/JointState``), ``/PSM1/operating_state``
(``crtk_msgs/OperatingState``; or, as a stand-in where crtk_msgs cannot be had, a
``std_msgs/String`` holding the state name). Every pose is in the arm's base frame, named by
``header.frame_id``.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

#: operating-state message kinds: "crtk" (crtk_msgs/OperatingState, built by crtk_msgs_build),
#: "string" (std_msgs/String: the state name in ``data``), "none" (no state topic: the arm's
#: health is the freshness and validity of measured_cp and measured_js alone)
STATE_KINDS = ("crtk", "string", "none")
#: CRTK's operating states; only ENABLED follows servo commands
ENABLED = "ENABLED"
#: how far a quaternion's norm may stray from 1 before the pose is not rigid (|q|^2 - 1)
QUAT_TOL = 1e-3


def topic(namespace: str, name: str, override: str = "") -> str:
    """The topic of ``name`` in ``namespace`` ('PSM1' + 'servo_cp' -> '/PSM1/servo_cp');
    ``override``: a topic name of its own (absolute: as given; relative: under the namespace)."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    leaf = override or name
    return leaf if leaf.startswith("/") else f"{ns}/{leaf}"


def check_namespace(namespace) -> str:
    """A ROS namespace (letters, digits, underscores, slashes), or InputError naming it."""
    s = str(namespace).strip("/")
    ok = isinstance(namespace, str) and all(p and (p[0].isalpha() or p[0] == "_") and
                                            all(c.isalnum() or c == "_" for c in p) for p in s.split("/")) if s else True
    if not ok:
        raise InputError(f"CRTK namespace {namespace!r} is not a ROS name (letters, digits and underscores, "
                         "each part starting with a letter; e.g. \"PSM1\")")
    return s


def qos_stream(depth: int = 1):
    """Streams (measured_cp, measured_js, servo_cp subscriptions): keep the newest ``depth``, best
    effort (it matches both reliable and best-effort publishers; a lost sample is replaced 1 ms on)."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT)


def qos_reliable(depth: int = 1):
    """Publishers (matched by reliable and best-effort subscribers alike, as the dVRK's
    subscriptions are reliable) and the operating-state subscription (published on change: a
    lost ENABLED or DISABLED would stay wrong)."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)


def state_type(kind: str):
    """The message class of operating-state kind ``kind`` (None for "none")."""
    if kind == "crtk":
        from .crtk_msgs_build import operating_state_type

        return operating_state_type()
    if kind == "string":
        from std_msgs.msg import String

        return String
    if kind == "none":
        return None
    raise InputError(f"operating_state_type = {kind!r}; expected one of {', '.join(STATE_KINDS)}")


def state_name(msg) -> str:
    """The state name of an operating-state message of either kind."""
    s = getattr(msg, "state", None)
    return s if s is not None else msg.data


def quat_to_matrix(x: float, y: float, z: float, w: float, out: np.ndarray) -> None:
    """Rotation of unit quaternion (x, y, z, w) into ``out[:3, :3]``."""
    out[0, 0], out[0, 1], out[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)
    out[1, 0], out[1, 1], out[1, 2] = 2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)
    out[2, 0], out[2, 1], out[2, 2] = 2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)


def matrix_to_quat(T: np.ndarray) -> tuple:
    """The unit quaternion (x, y, z, w) of the rotation ``T[:3, :3]`` (Shepperd's method)."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = T[0, :3].tolist(), T[1, :3].tolist(), T[2, :3].tolist()
    tr = m00 + m11 + m22
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        return (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s
    if m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        return 0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s
    if m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        return (m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s
    s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
    return (m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s


def pose_problem(p: tuple) -> Optional[str]:
    """Why pose ``p`` = (x, y, z, qx, qy, qz, qw) is no rigid pose (None: it is one)."""
    if not math.isfinite(sum(p)):
        return "is not finite: position " + ", ".join(f"{v:.6g}" for v in p[:3]) + \
               "; orientation " + ", ".join(f"{v:.6g}" for v in p[3:])
    n2 = p[3] * p[3] + p[4] * p[4] + p[5] * p[5] + p[6] * p[6]
    if abs(n2 - 1.0) > QUAT_TOL:
        return f"is not rigid: its orientation quaternion has norm {math.sqrt(n2):.6g}, not 1"
    return None


def pose_to_matrix(p: tuple, out: np.ndarray) -> np.ndarray:
    """Pose ``p`` = (x, y, z, qx, qy, qz, qw) as a 4x4 transform in ``out`` (the quaternion is
    normalised: ``pose_problem`` has accepted it)."""
    n = math.sqrt(p[3] * p[3] + p[4] * p[4] + p[5] * p[5] + p[6] * p[6])
    quat_to_matrix(p[3] / n, p[4] / n, p[5] / n, p[6] / n, out)
    out[0, 3], out[1, 3], out[2, 3] = p[0], p[1], p[2]
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def pose_of(T: np.ndarray) -> tuple:
    """Transform ``T`` (4x4) as a pose (x, y, z, qx, qy, qz, qw): ``pose_to_matrix``'s inverse."""
    return (T[0, 3].item(), T[1, 3].item(), T[2, 3].item()) + matrix_to_quat(T)


def set_stamp(header, ns: int) -> None:
    header.stamp.sec, header.stamp.nanosec = divmod(int(ns), 1_000_000_000)
