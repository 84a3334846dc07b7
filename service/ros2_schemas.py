"""ROS 2 message definitions (``ros2msg`` text, as ``ros2 interface show`` prints them with their
dependencies) of everything a pointfence MCAP recording holds, and the topic names.

The standard types are written out here, with every type they depend on, so a recording opens
in ``ros2 bag``, Foxglove and Rerun without a ROS installation: ``std_msgs/Header``,
``builtin_interfaces/Time``, ``geometry_msgs/PoseStamped`` / ``WrenchStamped`` (``Pose``,
``Point``, ``Quaternion``, ``Wrench``, ``Vector3``), ``sensor_msgs/Image``, ``CompressedImage``,
``CameraInfo`` (``RegionOfInterest``), ``JointState``, ``PointCloud2`` (``PointField``),
``diagnostic_msgs/DiagnosticArray`` (``DiagnosticStatus``, ``KeyValue``; the grasper's health).
pointfence's own: ``pointfence_msgs/Event`` (a fault, a hold and its reason, a change of
control), ``pointfence_msgs/Snapshot`` (which camera frames built snapshot ``seq``) and
``pointfence_msgs/TickInput`` / ``TickOutput`` (every field of ``tick_io.TickInput`` /
``TickOutput``, lossless: replay reads them back bit for bit).

Units: SI (m, s, N); poses of the robot side are in the world frame (the robot base),
masters' in their own frame; stamps are wall-clock times (the loop clock mapped to the epoch
recorded in the file's ``pointfence`` metadata).
"""
from __future__ import annotations

import numpy as np

from .tick_io import TickInput, TickOutput

SEP = "=" * 80 + "\n"

_DEPS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Wrench": "Vector3 force\nVector3 torque\n",
    "sensor_msgs/RegionOfInterest": "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n",
    "diagnostic_msgs/KeyValue": "string key\nstring value\n",
    "diagnostic_msgs/DiagnosticStatus": ("byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\n"
                                         "string message\nstring hardware_id\nKeyValue[] values\n"),
    "sensor_msgs/PointField": ("uint8 INT8    = 1\nuint8 UINT8   = 2\nuint8 INT16   = 3\nuint8 UINT16  = 4\n"
                               "uint8 INT32   = 5\nuint8 UINT32  = 6\nuint8 FLOAT32 = 7\nuint8 FLOAT64 = 8\n"
                               "string name\nuint32 offset\nuint8 datatype\nuint32 count\n"),
}

_MAIN = {
    "geometry_msgs/PoseStamped": ("std_msgs/Header header\ngeometry_msgs/Pose pose\n",
                                  ["std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Pose",
                                   "geometry_msgs/Point", "geometry_msgs/Quaternion"]),
    "geometry_msgs/WrenchStamped": ("std_msgs/Header header\ngeometry_msgs/Wrench wrench\n",
                                    ["std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Wrench",
                                     "geometry_msgs/Vector3"]),
    "sensor_msgs/CompressedImage": ("std_msgs/Header header\nstring format\nuint8[] data\n",
                                    ["std_msgs/Header", "builtin_interfaces/Time"]),
    "sensor_msgs/Image": ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
                          "uint32 step\nuint8[] data\n", ["std_msgs/Header", "builtin_interfaces/Time"]),
    "sensor_msgs/CameraInfo": ("std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
                               "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
                               "uint32 binning_y\nsensor_msgs/RegionOfInterest roi\n",
                               ["std_msgs/Header", "builtin_interfaces/Time", "sensor_msgs/RegionOfInterest"]),
    "sensor_msgs/JointState": ("std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
                               "float64[] effort\n", ["std_msgs/Header", "builtin_interfaces/Time"]),
    "sensor_msgs/PointCloud2": ("std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\n"
                                "bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n",
                                ["std_msgs/Header", "builtin_interfaces/Time", "sensor_msgs/PointField"]),
    "diagnostic_msgs/DiagnosticArray": ("std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n",
                                        ["std_msgs/Header", "builtin_interfaces/Time", "diagnostic_msgs/DiagnosticStatus",
                                         "diagnostic_msgs/KeyValue"]),
    # pointfence's own
    "pointfence_msgs/Event": (
        "# something that changed the run: kind is one of fault, hold, release, control, architecture\n"
        "std_msgs/Header header\nint64 tick\nint32 arm\nstring kind\n"
        "# hold reasons (holds.HoldReason names) and their SAFETY.md invariants, comma-separated\n"
        "string reason\nstring invariant\nint64 hold_mask\nstring detail\n",
        ["std_msgs/Header", "builtin_interfaces/Time"]),
    "pointfence_msgs/Snapshot": (
        "# the camera frames (one per camera, configuration order) snapshot seq was built from\n"
        "std_msgs/Header header\nint64 seq\nint64[] frame_seq\n"
        "# each frame's running number on its camera's image topics (their MCAP message sequence)\n"
        "int64[] frame_index\n"
        "# each frame's capture timestamp (s, the source's clock, exact) and its pose T_world_cam\n"
        "# (16 row-major numbers per camera, NaN: the camera's fixed pose)\n"
        "float64[] frame_stamp\nfloat64[] t_world_cam\n",
        ["std_msgs/Header", "builtin_interfaces/Time"]),
}

#: ros2msg element type of a tick struct's field, by its numpy dtype or Python type
_ELEM = {np.dtype(np.float64): "float64", np.dtype(bool): "bool", np.dtype(np.int32): "int32",
         np.dtype(np.int64): "int64", float: "float64", bool: "bool", int: "int64"}


def tick_fields(cls) -> list:
    """(name, ros2msg element type, numpy dtype, values per arm or 0 for a scalar) of every field
    of ``tick_io.TickInput`` or ``TickOutput`` but ``n`` (the arm count is the file's)."""
    probe = cls.zeros(2)
    out = []
    for name, value in vars(probe).items():
        if name == "n":
            continue
        if isinstance(value, np.ndarray):
            per_arm = int(np.prod(value.shape[1:])) if value.ndim > 1 else 1
            out.append((name, _ELEM[value.dtype], value.dtype, per_arm))
        else:
            kind = bool if isinstance(value, bool) else int if isinstance(value, int) else float
            out.append((name, _ELEM[kind], np.dtype(kind), 0))
    return out


#: TickOutput's extra field: the loop's wall-clock compute time of the tick (us; not replayed)
TICK_US = "tick_us"


def _tick_msg(cls, extra: str = "") -> str:
    lines = [f"# every field of pointfence tick_io.{cls.__name__}; arrays are per arm, row-major (B, 3)",
             "std_msgs/Header header"]
    for name, elem, _, per_arm in tick_fields(cls):
        lines.append(f"{elem}{'[]' if per_arm else ''} {name}")
    return "\n".join(lines) + "\n" + extra


_MAIN["pointfence_msgs/TickInput"] = (_tick_msg(TickInput), ["std_msgs/Header", "builtin_interfaces/Time"])
_MAIN["pointfence_msgs/TickOutput"] = (_tick_msg(TickOutput, f"float64 {TICK_US}\n"),
                                       ["std_msgs/Header", "builtin_interfaces/Time"])


def msgdef(name: str) -> str:
    """The full ros2msg text of message ``name``: its fields, then each dependency after a
    separator line, as ``mcap_ros2`` and ROS 2's rosbag2 write them."""
    text, deps = _MAIN[name]
    return text + "".join(f"{SEP}MSG: {d}\n{_DEPS[d]}" for d in deps)


SCHEMAS = tuple(_MAIN)

# --- topics ------------------------------------------------------------------------------------
TICK_INPUT = "/pointfence/tick/input"
TICK_OUTPUT = "/pointfence/tick/output"
EVENTS = "/pointfence/events"
SNAPSHOTS = "/pointfence/snapshots"
FIXTURES = "/pointfence/fixtures"


def robot_ns(arm: int) -> str:
    """CRTK namespace of arm ``arm``'s robot: PSM1, PSM2, ... (dVRK names)."""
    return f"PSM{arm + 1}"


def master_ns(arm: int) -> str:
    """CRTK namespace of arm ``arm``'s master: MTMR drives PSM1 and MTML PSM2 as on a dVRK; then MTM3, ..."""
    return ("MTMR", "MTML")[arm] if arm < 2 else f"MTM{arm + 1}"


def camera_topics(name: str) -> dict:
    """Topics of camera ``name``: depth (``sensor_msgs/Image`` 16UC1, the camera's depth codes),
    camera info, colour (rgb8) and mask (mono8) images, as ROS drivers name raw images."""
    return {"depth": f"/{name}/depth/image_raw", "info": f"/{name}/depth/camera_info",
            "color": f"/{name}/color/image_raw", "mask": f"/{name}/mask/image_raw"}


def legacy_camera_topics(name: str) -> dict:
    """The image topics of recordings made before raw images (``sensor_msgs/CompressedImage``:
    depth in the ``compressedDepth`` PNG form, colour and mask PNGs); still read."""
    return {"depth": f"/{name}/depth/compressed", "color": f"/{name}/color/compressed",
            "mask": f"/{name}/mask/compressed"}


__all__ = ["msgdef", "SCHEMAS", "tick_fields", "robot_ns", "master_ns", "camera_topics", "legacy_camera_topics",
           "TICK_INPUT", "TICK_OUTPUT", "EVENTS", "SNAPSHOTS", "FIXTURES", "TICK_US"]
