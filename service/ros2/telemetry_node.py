"""The ROS 2 telemetry publisher process (``python -m pointfence.service.ros2.telemetry_node``,
started by ``telemetry.Telemetry``): reads the telemetry ring and the frame ring in shared
memory and publishes, with rclpy, outside the service's interpreter.

Topics (relative names under ``[ros2] namespace``: the default puts them at ``/pointfence/...``,
the recording's names and frame ids, so one Foxglove layout shows a live run and its MCAP file);
every header's frame id is ``[ros2] frame_id`` (default ``world``, the robot base frame) but the
master's own pose's, units SI (m, N, rad), stamps the loop clock mapped to wall-clock time (the
recording's):

* ``pointfence/arm<b>/xm``, ``hip``, ``proxy`` (``geometry_msgs/PoseStamped``): the master's
  point X_m mapped into the world, the haptic interface point, the proxy (points: identity
  orientation), at ``telemetry_rate_hz``;
* ``pointfence/arm<b>/measured_cp`` (``PoseStamped``): the robot's measured tool pose (world:
  ``TickInput.robot_pos`` and ``robot_orientation``), and ``pointfence/arm<b>/servo_cp`` its
  commanded one (``TickOutput.command`` and ``orientation``, the pose the tick sends). Not
  ``/PSM1/measured_cp`` as in the recording: telemetry never publishes on a CRTK device's own
  topics, where a real arm or pointfence's CRTK bridge reads and writes state and commands;
* ``pointfence/arm<b>/master/measured_cp`` (``PoseStamped``): the master's sample in its own
  frame (``TickInput.master_pos`` and ``master_orientation``; frame id ``MTMR_base`` for arm 0,
  ``MTML_base`` for arm 1, as the recording's ``/MTMR/measured_cp``); none while the sample is
  not finite;
* ``pointfence/arm<b>/jaw/servo_jp``, ``jaw/measured_js`` and ``master/gripper/measured_js``
  (``sensor_msgs/JointState``, one joint, ``position`` rad): the jaw command
  (``TickOutput.jaw``), the robot's measured jaw (``TickInput.robot_jaw``) and the master's grasp
  (``TickInput.grasp``); none on a tick where the angle is unknown (NaN);
* ``pointfence/arm<b>/force`` (``geometry_msgs/WrenchStamped``): the force on the master in the
  world frame (N, after the hold ramp: ``TickOutput.force``), torque zero;
* ``pointfence/fixtures`` (``sensor_msgs/PointCloud2``, x y z float32, m): the protected points of
  the newest snapshot's frames (``fixture_cloud.protected_points`` on every 4th pixel, as the
  recording's), at most ``cloud_max_points`` (evenly thinned), at ``cloud_rate_hz``;
* ``pointfence/markers`` (``visualization_msgs/MarkerArray``): per arm a sphere at the proxy of
  the fixture radius (green while coupled, red while the arm holds, grey otherwise; namespace
  ``proxy``), a small sphere at the HIP (``hip``), an arrow from the HIP along the force
  (``force``, ``force_arrow_m_per_n``), and the workspace box (``workspace``, line list);
* ``pointfence/status`` (``std_msgs/String``, JSON, transient local: a late subscriber gets the
  last one): ``{"schema": "pointfence/status/1", "tick", "stamp_ns", "architecture" ("I" | "II" |
  "III"), "haptics", "teleop", "holding", "hold" (reason names), "arms": [{"arm", "hold",
  "invariants", "coupled", "in_contact", "pedal", "master_ok", "robot_fault", "force_gain"}]}``,
  on every change and at least once a second.

Control messages on stdin (``child_pipe.send``): ``("init", dict)`` first,
``("frames", path, shapes, slots, cameras, params)``, ``("close",)``. The end of stdin means the
service is gone: the process exits. An error is one line on stderr and exit status 1.
"""
from __future__ import annotations

import array
import json
import math
import os
import queue
import sys
import time

import numpy as np

from .. import mcap_shm
from ..holds import REASONS
from ..child_pipe import control_inbox, read_init
from ..ros2_schemas import FIXTURES, master_ns
from . import cdr
from . import telemetry as T

STATUS_SCHEMA = "pointfence/status/1"
#: rows published per cycle after a hiccup (the newest ones)
MAX_ROWS_PER_CYCLE = 8
#: the row's fields the pose and joint topics read (positions, orientations; angles)
POSE_FIELDS = ("xm", "hip", "proxy", "robot_pos", "robot_orientation", "command", "orientation", "master_pos",
               "master_orientation")
ANGLE_FIELDS = ("jaw", "robot_jaw", "grasp")
#: status at least this often (s) when nothing changes
STATUS_EVERY_S = 1.0


class _Frame:
    def __init__(self, depth, color, mask, T_world_cam):
        self.depth, self.color, self.mask, self.T_world_cam = depth, color, mask, T_world_cam


def _names(mask: int) -> list:
    return [r.name for bit, r in REASONS.items() if int(mask) & int(bit)]


def _invariants(mask: int) -> list:
    return list(dict.fromkeys(r.invariant for bit, r in REASONS.items() if int(mask) & int(bit)))


def _status_key(st: dict) -> tuple:
    """What a status change is: everything but the quantities that move all the time (contact,
    the force gain's ramp), which ride along in the next message."""
    arms = tuple(tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in a.items()
                       if k not in ("in_contact", "force_gain")) for a in st["arms"])
    return (st["architecture"], st["haptics"], st["teleop"], tuple(st["hold"]), arms)


def box_edges(lo, hi) -> list:
    """The 12 edges of the box ``lo``-``hi`` as 24 (x, y, z) end points (a LINE_LIST)."""
    c = [(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return [c[i] for p in pairs for i in p]


class Publisher:
    """The node, its publishers and the rings' read side (one instance per process)."""

    def __init__(self, p: dict):
        from geometry_msgs.msg import PoseStamped, WrenchStamped
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState, PointCloud2, PointField
        from std_msgs.msg import String
        from visualization_msgs.msg import MarkerArray

        from .node import RosNode

        self.p = p
        self.n = int(p["n"])
        self.layout = T.TelemetryLayout(self.n)
        if self.layout.cols != p["cols"] or self.layout.width != p["width"]:
            raise RuntimeError("the service's telemetry layout differs from this module's (mixed versions)")
        self.block = mcap_shm.TickBlock(mcap_shm.attach(p["tick_path"]), p["capacity"], self.layout.width)
        self.hdr = self.block.header
        self.consumed = int(self.hdr[T.CONSUMED])
        self.frames = None
        self.cameras, self.params = [], None
        self.snaps_consumed = 0
        self.frame_id = p["frame_id"]
        self.ros = RosNode("pointfence_telemetry", p["namespace"])
        node = self.ros.node
        stream = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.VOLATILE)
        latest = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
        # per arm: [(position field, orientation field or None, publisher, message)], (publisher, message),
        # [(angle field, publisher, message)]
        self.poses, self.wrenches, self.angles = [], [], []
        for b in range(self.n):
            pf = f"pointfence/arm{b}"
            arm = []
            for name, field, qfield, frame in (
                    ("xm", "xm", None, self.frame_id), ("hip", "hip", None, self.frame_id),
                    ("proxy", "proxy", None, self.frame_id),
                    ("measured_cp", "robot_pos", "robot_orientation", self.frame_id),
                    ("servo_cp", "command", "orientation", self.frame_id),
                    ("master/measured_cp", "master_pos", "master_orientation", f"{master_ns(b)}_base")):
                # (the per-tick messages go out serialized: ros2/cdr.py)
                writer = cdr.StampedWriter("pose", frame)
                arm.append((field, qfield, node.create_publisher(PoseStamped, f"{pf}/{name}", stream), writer))
            self.poses.append(arm)
            w = cdr.StampedWriter("wrench", self.frame_id)
            self.wrenches.append((node.create_publisher(WrenchStamped, f"{pf}/force", stream), w))
            joints = []
            for name, field, joint in (("jaw/servo_jp", "jaw", "jaw"), ("jaw/measured_js", "robot_jaw", "jaw"),
                                       ("master/gripper/measured_js", "grasp", "gripper")):
                joints.append((field, node.create_publisher(JointState, f"{pf}/{name}", stream),
                               cdr.JointStateWriter((joint,))))
            self.angles.append(joints)
        self.marker_pub = node.create_publisher(MarkerArray, "pointfence/markers", stream)
        self.cloud_pub = node.create_publisher(PointCloud2, FIXTURES.lstrip("/"), latest)
        self.status_pub = node.create_publisher(String, "pointfence/status", latest)
        self._String, self._PointCloud2 = String, PointCloud2
        self._fields = [PointField(name=c, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                        for i, c in enumerate("xyz")]
        self.markers = self._markers()
        self.next_cloud = 0.0
        self.cloud_period = 1.0 / float(p["cloud_rate_hz"])
        self.last_status = (None, -math.inf)

    # --- control --------------------------------------------------------------------------------
    def control(self, msg: tuple) -> bool:
        """Apply one control message; False for ``close``."""
        op = msg[0]
        if op == "frames":
            _, path, shapes, slots, self.cameras, self.params = msg
            self.frames = mcap_shm.FrameBlock(mcap_shm.attach(path), shapes, slots)
            self.snaps_consumed = int(self.hdr[mcap_shm.SNAPS_CONSUMED])
        elif op == "close":
            return False
        return True

    # --- ticks ----------------------------------------------------------------------------------
    def poll_ticks(self) -> None:
        """Publish the rows the tick left since the last call (the newest ``MAX_ROWS_PER_CYCLE``)."""
        written = int(self.hdr[mcap_shm.WRITTEN])
        if written <= self.consumed:
            return
        first = max(self.consumed, written - MAX_ROWS_PER_CYCLE)
        cap = self.block.capacity
        rows = [self.block.rows[j % cap].copy() for j in range(first, written)]
        self.hdr[T.ROWS_READ] += written - self.consumed
        self.consumed = written
        self.hdr[T.CONSUMED] = written          # (the tick may reuse those rows from here on)
        for row in rows:
            self.publish_row(row)
        self.publish_markers(rows[-1])
        self.publish_status(rows[-1])

    def _stamp_ns(self, row) -> int:
        return int(self.hdr[T.EPOCH]) + int(round(self.layout.get(row, "now") * 1e9))

    def _stamp(self, row) -> tuple:
        return divmod(self._stamp_ns(row), 1_000_000_000)

    def publish_row(self, row: np.ndarray) -> None:
        stamp = self._stamp_ns(row)
        get = self.layout.get
        values = {f: get(row, f) for f in POSE_FIELDS + ANGLE_FIELDS}
        force = get(row, "force")
        count = 0
        for b in range(self.n):
            for field, qfield, pub, writer in self.poses[b]:
                x, y, z = (float(v) for v in values[field][b])
                q = (0.0, 0.0, 0.0, 1.0)
                if qfield is not None:
                    w, qx, qy, qz = (float(v) for v in values[qfield][b])
                    if not math.isfinite(x + y + z + w + qx + qy + qz):    # (a master that gave no sample)
                        continue
                    q = (qx, qy, qz, w)                                   # (ROS's x, y, z, w)
                pub.publish(writer.encode(stamp, (x, y, z) + q))
                count += 1
            for field, pub, writer in self.angles[b]:
                a = float(values[field][b])
                if not math.isfinite(a):                                  # (unknown this tick)
                    continue
                pub.publish(writer.encode(stamp, (a,)))
                count += 1
            pub, writer = self.wrenches[b]
            fx, fy, fz = force[b]
            pub.publish(writer.encode(stamp, (float(fx), float(fy), float(fz), 0.0, 0.0, 0.0)))
            count += 1
        self.hdr[T.PUBLISHED] += count

    # --- markers --------------------------------------------------------------------------------
    def _markers(self):
        from geometry_msgs.msg import Point
        from visualization_msgs.msg import Marker, MarkerArray

        r = float(self.p["radius"])
        out = MarkerArray()

        def marker(ns, mid, kind, scale, rgba):
            m = Marker()
            m.header.frame_id = self.frame_id
            m.ns, m.id, m.type, m.action = ns, mid, kind, Marker.ADD
            m.pose.orientation.w = 1.0
            m.scale.x, m.scale.y, m.scale.z = scale
            m.color.r, m.color.g, m.color.b, m.color.a = rgba
            out.markers.append(m)
            return m

        self._proxy, self._hip, self._arrow = [], [], []
        for b in range(self.n):
            self._proxy.append(marker("proxy", b, Marker.SPHERE, (2 * r, 2 * r, 2 * r), (0.2, 0.8, 0.2, 0.5)))
            self._hip.append(marker("hip", b, Marker.SPHERE, (0.004, 0.004, 0.004), (0.2, 0.4, 1.0, 1.0)))
            a = marker("force", b, Marker.ARROW, (0.002, 0.004, 0.004), (1.0, 0.8, 0.0, 1.0))
            a.points = [Point(), Point()]
            self._arrow.append(a)
        box = marker("workspace", 0, Marker.LINE_LIST, (0.001, 0.0, 0.0), (0.7, 0.7, 0.7, 1.0))
        lo, hi = self.p["workspace"]
        box.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in box_edges(lo, hi)]
        return out

    def publish_markers(self, row: np.ndarray) -> None:
        sec, nsec = self._stamp(row)
        get = self.layout.get
        proxy, hip, force = get(row, "proxy"), get(row, "hip"), get(row, "force")
        hold, coupled = get(row, "arm_hold"), get(row, "coupled")
        k = float(self.p["arrow_m_per_n"])
        for m in self.markers.markers:
            m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
        for b in range(self.n):
            p = self._proxy[b]
            p.pose.position.x, p.pose.position.y, p.pose.position.z = (float(v) for v in proxy[b])
            p.color.r, p.color.g, p.color.b = ((0.9, 0.1, 0.1) if hold[b] else (0.2, 0.8, 0.2) if coupled[b]
                                               else (0.6, 0.6, 0.6))
            h = self._hip[b]
            h.pose.position.x, h.pose.position.y, h.pose.position.z = (float(v) for v in hip[b])
            a0, a1 = self._arrow[b].points
            a0.x, a0.y, a0.z = (float(v) for v in hip[b])
            a1.x, a1.y, a1.z = (float(v) for v in hip[b] + k * force[b])
        self.marker_pub.publish(self.markers)
        self.hdr[T.PUBLISHED] += 1

    # --- status ---------------------------------------------------------------------------------
    def status_of(self, row: np.ndarray) -> dict:
        get = self.layout.get
        arch = int(get(row, "architecture"))
        arms = []
        for b in range(self.n):
            m = int(get(row, "arm_hold")[b])
            arms.append({"arm": b, "hold": _names(m), "invariants": _invariants(m),
                         "coupled": bool(get(row, "coupled")[b]), "in_contact": bool(get(row, "state")[b]),
                         "pedal": bool(get(row, "pedal")[b]), "master_ok": bool(get(row, "master_ok")[b]),
                         "robot_fault": bool(get(row, "robot_fault")[b]),
                         "force_gain": round(float(get(row, "gain")[b]), 3)})
        hold = int(get(row, "hold"))
        return {"schema": STATUS_SCHEMA, "architecture": ("I", "II", "III")[arch - 1] if 1 <= arch <= 3 else str(arch),
                "haptics": bool(get(row, "haptics")), "teleop": bool(get(row, "teleop")),
                "holding": bool(hold) or any(a["hold"] for a in arms), "hold": _names(hold), "arms": arms}

    def publish_status(self, row: np.ndarray) -> None:
        st = self.status_of(row)
        key = _status_key(st)
        now = time.monotonic()
        if key == self.last_status[0] and now - self.last_status[1] < STATUS_EVERY_S:
            return
        self.last_status = (key, now)
        msg = self._String()
        msg.data = json.dumps({**st, "tick": int(self.layout.get(row, "k")), "stamp_ns": self._stamp_ns(row)})
        self.status_pub.publish(msg)
        self.hdr[T.PUBLISHED] += 1

    # --- the fixture cloud ----------------------------------------------------------------------
    def poll_cloud(self) -> None:
        """The newest frame entry's fixture cloud, at most ``cloud_rate_hz`` times a second."""
        from ..fixture_cloud import protected_points

        fb = self.frames
        now = time.monotonic()
        if fb is None or now < self.next_cloud:
            return
        written = int(self.hdr[mcap_shm.SNAPS_WRITTEN])
        if written <= self.snaps_consumed:
            return
        self.next_cloud = now + self.cloud_period
        slot = (written - 1) % fb.slots
        frames = []
        for i in range(len(self.cameras)):
            e = fb.cam_meta(slot, i)
            pose = e[mcap_shm.POSE: mcap_shm.POSE + 16]
            frames.append(_Frame(fb.depth[slot][i], fb.color[slot][i] if e[mcap_shm.COLOR] else None,
                                 fb.mask[slot][i] if e[mcap_shm.MASK] else None,
                                 None if np.isnan(pose[0]) else pose.reshape(4, 4).copy()))
        pts = protected_points(self.cameras, frames, self.params, stride=1)
        self.snaps_consumed = written
        self.hdr[mcap_shm.SNAPS_CONSUMED] = written
        cap = int(self.p["cloud_max_points"])
        if len(pts) > cap:
            pts = pts[:: -(-len(pts) // cap)]
        self.publish_cloud(np.ascontiguousarray(pts, np.float32), time.time_ns())

    def publish_cloud(self, pts: np.ndarray, ns: int) -> None:
        msg = self._PointCloud2()
        msg.header.frame_id = self.frame_id
        msg.header.stamp.sec, msg.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
        msg.height, msg.width = 1, len(pts)
        msg.fields = self._fields
        msg.is_bigendian, msg.point_step, msg.row_step, msg.is_dense = False, 12, 12 * len(pts), True
        data = array.array("B")
        data.frombytes(pts.tobytes())
        msg.data = data
        self.cloud_pub.publish(msg)
        self.hdr[T.CLOUDS] += 1
        self.hdr[T.CLOUD_POINTS] = len(pts)
        self.hdr[T.PUBLISHED] += 1

    def close(self) -> None:
        self.ros.close()


def main() -> int:
    ctl = sys.stdin.buffer
    p = read_init(ctl, "telemetry_node", "Telemetry")
    if p is None:
        return 2
    inbox = control_inbox(ctl, "telemetry-control")
    try:
        pub = Publisher(p)
    except Exception as e:     # (rclpy, DDS, the shared memory): one line for the service's status
        print(f"ROS 2 telemetry could not start: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    period = 0.5 / float(p["rate_hz"])     # twice the rate: a row waits at most half a period
    try:
        running, next_t = True, time.monotonic()
        while running:
            while True:
                try:
                    msg = inbox.get_nowait()
                except queue.Empty:
                    break
                running = msg is not None and pub.control(msg)
                if not running:
                    break
            if running and os.getppid() != p["parent_pid"]:
                running = False          # (the service is gone and stdin somehow still open)
            pub.poll_ticks()
            pub.poll_cloud()
            pub.hdr[T.BEAT] += 1
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.monotonic()
    except Exception as e:
        print(f"ROS 2 telemetry failed: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    finally:
        pub.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
