"""The rclpy side of a CRTK arm (robot/crtk.py ``CrtkRobot``): one node with the arm's three
subscriptions and its ``servo_cp`` publisher (and, for an arm with a jaw, ``jaw/measured_js``
and ``jaw/servo_jp``: ``sensor_msgs/JointState`` of one position, rad).

measured_cp and measured_js arrive at 1 kHz: the arm's own periodic thread takes them
(``poll``, ``RosNode.polled``: no executor thread wakes for them) at the start of each step,
every message that arrived since the last (up to ``DEPTH``), each with its reception time as its
arrival. The other topics (operating_state, the jaw) are served by the node's thread (rclpy's
``EventsExecutor``). Every 1 kHz topic travels serialized (raw, ros2/cdr.py: rclpy's conversion
to and from message objects was most of their cost). Each message becomes a tuple of plain
floats, the newest of its topic (one reference assignment: no lock); a message that is no valid
pose, or cannot be read, is kept as the newest bad one (``bad_cp``, ``bad_js``) even where a
good one follows, and faults the arm. The arm's ``step`` publishes its setpoint on ``servo_cp``
itself (an rclpy publisher may be used from any thread; the event executor serves no guard
condition to hand it over with).

Round trip (``pointfence bench ros2``): each ``servo_cp`` carries ``header.stamp`` = the
wall-clock time it was sent (ns, unique per send); an arm that echoes the stamp of the last
``servo_cp`` it applied in its ``measured_cp`` (``pointfence ros2 sim-arm`` does) gives
``round_trip_us()``: from each send to the arrival (reception) of the measured_cp that echoes
it, and ``round_trip_us(taken=True)``: to the step that took it.
"""
from __future__ import annotations

import collections
import time
from typing import Optional

from . import cdr
from . import crtk_wire as wire
from .node import RosNode

#: messages of a 1 kHz topic kept for the arm's next step (a step that comes late still sees a bad
#: one among them)
DEPTH = 16


class CrtkBridge:
    """The rclpy side of one CRTK arm: a node (``RosNode``) with the three subscriptions and the
    ``servo_cp`` publisher. ``cp``, ``js``, ``state``: the newest message of each, as a tuple
    whose first item is its arrival (``time.monotonic()``, s), None before the first (``cp`` and
    ``js`` as of the last ``poll``). ``send`` publishes a setpoint from the caller's thread."""

    def __init__(self, namespace: str, topics: dict, frame_id: str, state_kind: str):
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import JointState

        self.topics, self.frame_id = topics, frame_id
        state_cls = wire.state_type(state_kind)     # (builds crtk_msgs first, where needed)
        self.ros = RosNode("pointfence_crtk_" + (namespace.replace("/", "_") or "arm"), executor="events")
        node = self.ros.node
        self.cp: Optional[tuple] = None     # (arrival, stamp ns, frame_id, x, y, z, qx, qy, qz, qw)
        self.js: Optional[tuple] = None     # (arrival, positions, velocities, efforts)
        self.state: Optional[tuple] = None  # (arrival, state name)
        self.jaw: Optional[tuple] = None    # (arrival, positions) of jaw/measured_js
        self.jaw_sent = 0                   # jaw/servo_jp messages published
        #: the newest measured_cp that was no valid pose in ``frame_id`` (arrival, why), kept even
        #: when a good one follows before the arm's next step: one bad sample must fault the arm
        self.bad_cp: Optional[tuple] = None
        self.bad_js: Optional[tuple] = None  # (arrival, why) of the newest measured_js that could not be read
        self.received = 0                   # measured_cp messages
        self.sent = 0                       # servo_cp messages published
        self._rtt = collections.deque(maxlen=100_000)
        self._rtt_taken = collections.deque(maxlen=100_000)
        self._stamps: dict = {}             # stamp (ns) -> monotonic send time, of recent sends
        self._order: collections.deque = collections.deque()
        self._writer = cdr.StampedWriter("pose", frame_id)
        self._pub = node.create_publisher(PoseStamped, topics["servo_cp"], wire.qos_reliable())
        self._cp_sub = self.ros.polled(PoseStamped, topics["measured_cp"], wire.qos_stream(DEPTH))
        self._js_sub = self.ros.polled(JointState, topics["measured_js"], wire.qos_stream(DEPTH))
        if state_cls is not None:
            node.create_subscription(state_cls, topics["operating_state"], self._on_state, wire.qos_reliable(10))
        self._jaw_pub = None
        if "jaw_servo_jp" in topics:
            self._jaw_writer = cdr.JointStateWriter(("jaw",))
            self._jaw_pub = node.create_publisher(JointState, topics["jaw_servo_jp"], wire.qos_reliable())
            node.create_subscription(JointState, topics["jaw_measured_js"], self._on_jaw, wire.qos_stream(), raw=True)
        self.ros.start()

    # --- the arm's thread: measured_cp and measured_js -----------------------------------------
    def poll(self) -> None:
        """Take every measured_cp and measured_js that arrived since the last call."""
        for raw, arrival in self._cp_sub.take_all():
            self._on_cp(raw, arrival)
        for raw, arrival in self._js_sub.take_all():
            self._on_js(raw, arrival)

    def _on_cp(self, raw: bytes, now: float) -> None:
        self.received += 1
        try:
            stamp, frame, pose = cdr.decode_pose_stamped(raw)
        except cdr.CdrError as e:
            self.bad_cp = (now, f"could not be read: {e}")
            return
        why = f"has frame_id {frame!r}; expected {self.frame_id!r}" if frame != self.frame_id else wire.pose_problem(pose)
        if why is not None:
            self.bad_cp = (now, why)
        self.cp = (now, stamp, frame) + pose
        t0 = self._stamps.pop(stamp, None)
        if t0 is not None:
            self._rtt.append(1e6 * (now - t0))
            self._rtt_taken.append(1e6 * (time.monotonic() - t0))

    def _on_js(self, raw: bytes, now: float) -> None:
        try:
            _, _, q, dq, tau = cdr.decode_joint_state(raw)
        except cdr.CdrError as e:
            self.bad_js = (now, f"could not be read: {e}")
            return
        self.js = (now, q, dq, tau)

    # --- the node's thread ----------------------------------------------------------------------
    def _on_jaw(self, raw: bytes) -> None:
        try:
            q = cdr.decode_joint_state(raw)[2]
        except cdr.CdrError:
            q = ()              # (no angle: the arm reads it as a bad jaw state)
        self.jaw = (time.monotonic(), q)

    def _on_state(self, m) -> None:
        self.state = (time.monotonic(), wire.state_name(m))

    # --- the arm's thread -----------------------------------------------------------------------
    def send(self, pose: tuple) -> None:
        """Publish ``pose`` (x, y, z, qx, qy, qz, qw; base frame) on servo_cp, stamped now (wall
        clock, ns: unique per send, the round trip's key)."""
        stamp = time.time_ns()
        data = self._writer.encode(stamp, pose)
        self._stamps[stamp] = time.monotonic()      # (before the echo can arrive on the node's thread)
        self._order.append(stamp)
        self._pub.publish(data)
        self.sent += 1
        while len(self._order) > 256:      # forget sends never echoed
            self._stamps.pop(self._order.popleft(), None)

    def send_jaw(self, angle: float) -> None:
        """Publish the jaw setpoint ``angle`` (rad) on jaw/servo_jp, stamped now."""
        self._jaw_pub.publish(self._jaw_writer.encode(time.time_ns(), (angle,)))
        self.jaw_sent += 1

    def round_trip_us(self, taken: bool = False) -> list:
        return list(self._rtt_taken if taken else self._rtt)

    @property
    def error(self) -> Optional[str]:
        """Why the node stopped spinning (None: it spins)."""
        return self.ros.error

    def close(self) -> None:
        self.ros.close()
