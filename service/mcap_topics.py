"""Writing the topics of a pointfence MCAP recording (``ros2_schemas`` lists them) from the
recorder's ring rows and frames; used only by the recorder's writer process (``mcap_writer``).

``TopicWriter`` wraps an ``mcap.writer.Writer`` (profile ``ros2``): every schema is registered
with its full ros2msg text, every channel on first use (``cdr`` encoding). Fixed-shape
messages are encoded as NumPy records (``cdr``); the few irregular ones (camera info, events,
snapshots, the fixture cloud) with ``mcap_ros2``'s own encoder.

Per arm b (CRTK names, ``ros2_schemas.robot_ns`` / ``master_ns``), at ``pose_hz``:
``/PSM1/measured_cp`` (the robot's measured tool tip, world), ``/PSM1/servo_cp`` (the command
X_r*, world), ``/MTMR/measured_cp`` (the master's sample, master frame), ``/MTMR/servo_cf``
(the force sent to the master, its frame, N), and ``/pointfence/arm0/{xm,hip,proxy}``
(PoseStamped, world) and ``/pointfence/arm0/force`` (WrenchStamped, world, N). The robot's
poses and the master's carry their orientations (the measured tool orientation, the commanded
one, the master's sample); the proxy points' are identity. The jaw and the grasp
(``sensor_msgs/JointState``, one position, rad): ``/PSM1/jaw/servo_jp`` (the jaw command),
``/PSM1/jaw/measured_js`` (the robot's jaw, where known) and ``/MTMR/gripper/measured_js`` (the
master's grasp). Where the arm's robot has joints (Raven II),
``/PSM1/measured_js`` (``sensor_msgs/JointState``: its joint names, measured positions in rad or
m; no velocity or effort) at the recorder's ``joint_hz``. With a ``[cable]`` grasper, its jaw estimate
(on that arm's ``jaw/measured_js`` instead of the robot's), setpoint and health (``GrasperTopics``).
"""
from __future__ import annotations

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap_ros2._dynamic import serialize_dynamic

from .cdr import FixedLayout, pose_layout, stamp_fields, wrench_layout
from .holds import REASONS, ROBOT
from .ros2_schemas import EVENTS, master_ns, msgdef, robot_ns


class TopicWriter:
    def __init__(self, writer):
        self.w = writer
        self._schemas: dict = {}
        self._channels: dict = {}
        self._encoders: dict = {}
        self.messages = 0

    def _channel(self, topic: str, schema: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._schemas.get(schema)
            if sid is None:
                sid = self._schemas[schema] = self.w.register_schema(schema, SchemaEncoding.ROS2, msgdef(schema).encode())
            cid = self._channels[topic] = self.w.register_channel(topic, MessageEncoding.CDR, sid)
        return cid

    def raw(self, topic: str, schema: str, data: bytes, log_ns: int, sequence: int = 0) -> None:
        """A message already CDR-encoded; ``sequence``: the MCAP message's sequence number (a
        camera frame's number on the image topics)."""
        self.w.add_message(self._channel(topic, schema), int(log_ns), data, int(log_ns), int(sequence) & 0xFFFFFFFF)
        self.messages += 1

    def dyn(self, topic: str, schema: str, msg: dict, log_ns: int, sequence: int = 0) -> None:
        """A message given as a dict, encoded by ``mcap_ros2``."""
        enc = self._encoders.get(schema)
        if enc is None:
            enc = self._encoders[schema] = serialize_dynamic(schema, msgdef(schema))[schema]
        self.raw(topic, schema, enc(msg), log_ns, sequence)


def stamp(ns: int, frame_id: str) -> dict:
    return {"stamp": {"sec": int(ns) // 1_000_000_000, "nanosec": int(ns) % 1_000_000_000}, "frame_id": frame_id}


class ArmTopics:
    """The decimated pose and wrench topics of every arm, from ring rows (``TickLayout`` columns)."""

    def __init__(self, layout, n: int):
        self.layout, self.n = layout, n
        self.topics = []   # (topic, schema, layout, (part, field), record field, (part, orientation field))
        for b in range(n):
            r, m, pf = robot_ns(b), master_ns(b), f"/pointfence/arm{b}"
            P, W = "geometry_msgs/PoseStamped", "geometry_msgs/WrenchStamped"
            self.topics += [(f"/{r}/measured_cp", P, pose_layout("world"), ("in", "robot_pos"), "p", ("in", "robot_orientation")),
                            (f"/{r}/servo_cp", P, pose_layout("world"), ("out", "command"), "p", ("out", "orientation")),
                            (f"/{m}/measured_cp", P, pose_layout(f"{m}_base"), ("in", "master_pos"), "p",
                             ("in", "master_orientation")),
                            (f"/{m}/servo_cf", W, wrench_layout(f"{m}_base"), ("out", "force_master"), "f", None),
                            (f"{pf}/xm", P, pose_layout("world"), ("out", "xm"), "p", None),
                            (f"{pf}/hip", P, pose_layout("world"), ("out", "hip"), "p", None),
                            (f"{pf}/proxy", P, pose_layout("world"), ("out", "proxy"), "p", None),
                            (f"{pf}/force", W, wrench_layout("world"), ("out", "force"), "f", None)]
        self.arm_of = [b for b in range(n) for _ in range(8)]
        #: (topic, layout, (part, field), arm) of the jaw and grasp JointStates (one position, rad)
        self.angles = [t for b in range(n) for t in (
            (f"/{robot_ns(b)}/jaw/servo_jp", _angle_layout("jaw"), ("out", "jaw"), b),
            (f"/{robot_ns(b)}/jaw/measured_js", _angle_layout("jaw"), ("in", "robot_jaw"), b),
            (f"/{master_ns(b)}/gripper/measured_js", _angle_layout("gripper"), ("in", "grasp"), b))]

    def hand_over_jaw(self, arm: int) -> None:
        """Leave ``arm``'s ``jaw/measured_js`` to a ``[cable]`` grasper (``GrasperTopics`` writes
        its measured jaw there): one writer per topic."""
        topic = f"/{robot_ns(arm)}/jaw/measured_js"
        self.angles = [a for a in self.angles if a[0] != topic]

    def write(self, tw: TopicWriter, rows: np.ndarray, ns: np.ndarray) -> None:
        cols = self.layout.cols
        for (topic, schema, lay, key, fld, qkey), b in zip(self.topics, self.arm_of):
            c, _ = cols[key]
            rec = lay.blank(len(rows))
            stamp_fields(rec, ns)
            rec[fld] = rows[:, c + 3 * b: c + 3 * b + 3]
            if fld == "p":
                if qkey is None:
                    rec["q"][:, 3] = 1.0
                else:                                  # (w, x, y, z) -> ROS's (x, y, z, w)
                    cq, _ = cols[qkey]
                    q = rows[:, cq + 4 * b: cq + 4 * b + 4]
                    rec["q"][:, :3], rec["q"][:, 3] = q[:, 1:], q[:, 0]
            buf, size = rec.tobytes(), lay.size
            for i in range(len(rows)):
                tw.raw(topic, schema, buf[i * size: (i + 1) * size], ns[i])
        for topic, lay, key, b in self.angles:
            c, _ = cols[key]
            v = rows[:, c + b]
            keep = np.flatnonzero(np.isfinite(v))     # (NaN: no value this tick)
            rec = lay.blank(len(keep))
            stamp_fields(rec, ns[keep])
            rec["position"] = v[keep, None]
            buf, size = rec.tobytes(), lay.size
            for j, i in enumerate(keep.tolist()):
                tw.raw(topic, "sensor_msgs/JointState", buf[j * size: (j + 1) * size], ns[i])


def _angle_layout(name: str):
    """``sensor_msgs/JointState`` of one joint ``name``: its ``position`` (rad), no velocity or effort."""
    return FixedLayout().header("").u32(1).string(name).array("position", "f8", 1).array("velocity", "f8", 0) \
        .array("effort", "f8", 0)


class JointTopics:
    """``/<arm>/measured_js`` (``sensor_msgs/JointState``) of the arms in ``names`` (arm ->
    joint names), from the joint rows the tick filled on every ``every``-th tick."""

    def __init__(self, names: dict, every: int):
        self.names = {int(b): list(v) for b, v in names.items()}
        self.every = max(1, int(every))
        self.topics = {b: f"/{robot_ns(b)}/measured_js" for b in self.names}

    def write(self, tw: TopicWriter, k: np.ndarray, joints: np.ndarray, ns: np.ndarray) -> None:
        """``k`` (N,) tick numbers, ``joints`` (N, arms, dof) their joint rows (NaN: none), ``ns``
        (N,) stamps."""
        for i in np.flatnonzero(k % self.every == 0):
            t = int(ns[i])
            for b, names in self.names.items():
                if np.isnan(joints[i, b, 0]):       # (none taken for this tick)
                    continue
                tw.dyn(self.topics[b], "sensor_msgs/JointState",
                       {"header": stamp(t, ""), "name": names,
                        "position": joints[i, b, : len(names)].tolist(), "velocity": [], "effort": []}, t)


class GrasperTopics:
    """The cable-driven grasper of arm ``arm`` (``[cable]``, ``cable_grasper.GrasperHost``), from
    the rows (``cable_grasper.RECORD_FIELDS``) the tick took on every ``every``-th tick:

    * ``/<arm>/jaw/measured_js`` (``sensor_msgs/JointState``, joint ``jaw``): the estimated jaw
      angle (rad), velocity (rad/s) and, as effort, the estimated external torque on the jaw (N m:
      the contact, section 4.5);
    * ``/<arm>/jaw/setpoint_js``: the controller's setpoint (rad) and, as effort, the motor torque
      it applied (N m; 0 while faulted);
    * ``/pointfence/arm<b>/grasper`` (``diagnostic_msgs/DiagnosticArray``) on every ``diag_every``-th
      row and whenever the fault or the tension alert changes: level OK, WARN (tension out of its
      range) or ERROR (a fault, named by kind), with the tension, stiffness, torques and lateness.
    """

    LEVEL_OK, LEVEL_WARN, LEVEL_ERROR = 0, 1, 2

    def __init__(self, arm: int, every: int, fields: tuple, diag_every: int = 10):
        from .cable_block import FAULT_CODES

        self.arm, self.every, self.diag_every = int(arm), max(1, int(every)), max(1, int(diag_every))
        self.col = {f: i for i, f in enumerate(fields)}
        r = robot_ns(self.arm)
        self.measured, self.setpoint = f"/{r}/jaw/measured_js", f"/{r}/jaw/setpoint_js"
        self.diag = f"/pointfence/arm{self.arm}/grasper"
        self.hardware = f"{r} jaw"
        self.fault_names = FAULT_CODES
        self.rows = 0
        self.prev = (0, 0)

    def write(self, tw: TopicWriter, k: np.ndarray, rows: np.ndarray, ns: np.ndarray) -> None:
        """``k`` (N,) tick numbers, ``rows`` (N, fields) their grasper rows, ``ns`` (N,) stamps."""
        c = self.col
        for i in np.flatnonzero(k % self.every == 0):
            row = rows[i]
            if np.isnan(row[c["jaw"]]):          # (the record did not read on that tick)
                continue
            t = int(ns[i])
            tw.dyn(self.measured, "sensor_msgs/JointState",
                   {"header": stamp(t, ""), "name": ["jaw"], "position": [float(row[c["jaw"]])],
                    "velocity": [float(row[c["jaw_velocity"]])], "effort": [float(row[c["link_torque"]])]}, t)
            tw.dyn(self.setpoint, "sensor_msgs/JointState",
                   {"header": stamp(t, ""), "name": ["jaw"], "position": [float(row[c["setpoint"]])],
                    "velocity": [], "effort": [float(row[c["motor_torque"]])]}, t)
            state = (int(row[c["fault_code"]]), int(row[c["tension_alert"]]))
            if self.rows % self.diag_every == 0 or state != self.prev:
                self._diagnostic(tw, t, row, state)
            self.prev = state
            self.rows += 1

    def _diagnostic(self, tw: TopicWriter, t: int, row: np.ndarray, state: tuple) -> None:
        c = self.col
        fault, alert = state
        if fault:
            level, msg = self.LEVEL_ERROR, f"fault: {self.fault_names.get(fault, fault)}; grasper torque is zero"
        elif alert:
            level, msg = self.LEVEL_WARN, f"cable tension {'below' if alert == 1 else 'above'} its safe range"
        else:
            level, msg = self.LEVEL_OK, "ok"
        tension = row[c["tension_g"]]
        values = [("tension_g", "" if np.isnan(tension) else f"{tension:.1f}"), ("k_e", f"{row[c['k_e']]:.6g}"),
                  ("motor_torque", f"{row[c['motor_torque']]:.6g}"), ("link_torque", f"{row[c['link_torque']]:.6g}"),
                  ("jaw", f"{row[c['jaw']]:.6g}"), ("late_ms", f"{row[c['late']] * 1e3:.3f}"),
                  ("fault", self.fault_names.get(fault, "") if fault else "")]
        tw.dyn(self.diag, "diagnostic_msgs/DiagnosticArray",
               {"header": stamp(t, ""), "status": [{"level": level, "name": "pointfence/grasper", "message": msg,
                                                    "hardware_id": self.hardware,
                                                    "values": [{"key": k, "value": v} for k, v in values]}]}, t)


def _names(mask: int) -> tuple:
    rs = [r for bit, r in REASONS.items() if int(mask) & int(bit)]
    return ",".join(r.name for r in rs), ",".join(dict.fromkeys(r.invariant for r in rs))


class EventDetector:
    """``pointfence_msgs/Event`` messages from consecutive ticks: an arm that starts or stops
    holding (with its reasons and their invariants), a robot that faults, an architecture
    switch, haptics or teleoperation engaged or disengaged."""

    def __init__(self, layout, n: int):
        self.layout, self.n = layout, n
        self.prev = None
        self.count = 0

    def _col(self, row, part, name, b=None):
        c, _ = self.layout.cols[(part, name)]
        return row[c if b is None else c + b]

    def _watched(self) -> np.ndarray:
        cols = self.layout.cols
        idx = [cols[("out", "arm_hold")][0] + b for b in range(self.n)]
        idx += [cols[("in", "robot_fault")][0] + b for b in range(self.n)]
        return np.array(idx + [cols[("in", name)][0] for name in ("architecture", "haptics", "teleop")])

    def write(self, tw: TopicWriter, rows: np.ndarray, ns: np.ndarray) -> None:
        if not len(rows):
            return
        col, idx = self._col, self._watched()
        first = self.prev if self.prev is not None else rows[0].copy()
        if self.prev is None:   # the run starts without holds or faults
            first[idx[: 2 * self.n]] = 0
        before = np.vstack([first[None], rows[:-1]])
        changed = np.flatnonzero(np.any(rows[:, idx] != before[:, idx], axis=1))
        self.prev = rows[-1].copy()
        for i in changed:
            row, prev, t_ns = rows[i], before[i], ns[i]
            k = int(col(row, "in", "k"))
            for b in range(self.n):
                new, old = int(col(row, "out", "arm_hold", b)), int(col(prev, "out", "arm_hold", b))
                if new != old:
                    kind = "hold" if new else "release"
                    names, inv = _names(new if new else old)
                    self._emit(tw, t_ns, k, b, kind, names, inv, new, "" if new else "these reasons cleared")
                if col(row, "in", "robot_fault", b) and not col(prev, "in", "robot_fault", b):
                    self._emit(tw, t_ns, k, b, "fault", *_names(ROBOT), int(col(row, "out", "hold")),
                               "the robot reports a fault")
            for name, kind in (("architecture", "architecture"), ("haptics", "control"), ("teleop", "control")):
                if col(row, "in", name) != col(prev, "in", name):
                    v = int(col(row, "in", name))
                    detail = (f"architecture {('I', 'II', 'III')[v - 1] if 1 <= v <= 3 else v}" if name == "architecture"
                              else f"{name} {'engaged' if v else 'disengaged'}")
                    self._emit(tw, t_ns, k, -1, kind, "", "S1", int(col(row, "out", "hold")), detail)

    def _emit(self, tw, t_ns, k, arm, kind, reason, invariant, mask, detail) -> None:
        self.count += 1
        tw.dyn(EVENTS, "pointfence_msgs/Event", {"header": stamp(t_ns, "world"), "tick": k, "arm": arm, "kind": kind,
                                                  "reason": reason, "invariant": invariant, "hold_mask": mask,
                                                  "detail": detail}, t_ns)


def camera_info(cam, ns: int) -> dict:
    """``sensor_msgs/CameraInfo`` of camera ``cam`` (``kernels.camera.Camera``): K, D (plumb_bob:
    k1 k2 p1 p2 k3), R identity, P = [K | 0]; frame id the camera's name (its optical frame)."""
    fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
    return {"header": stamp(ns, cam.name), "height": cam.height, "width": cam.width, "distortion_model": "plumb_bob",
            "d": [float(x) for x in cam.dist], "k": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
            "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "p": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
            "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}


__all__ = ["TopicWriter", "ArmTopics", "JointTopics", "GrasperTopics", "EventDetector", "camera_info", "stamp"]
