"""`pointfence ros2 sim-arm`: a simulated arm (Raven II or point mass) as a CRTK ROS 2 node.

It does what a dVRK arm's ROS node does, without hardware, so the whole ROS path runs end to
end: it subscribes ``<ns>/servo_cp`` (``geometry_msgs/PoseStamped``, in its base frame, named by
``--frame-id``, default "<ns>_base"), steps the model (service/robot: ``--model`` or a scene's
``[robot]`` table with ``--config``) on absolute deadlines at ``--rate`` (``periodic.PeriodicLoop``),
and publishes ``<ns>/measured_cp``, ``<ns>/measured_js`` every period and ``<ns>/operating_state``
(``crtk_msgs/OperatingState``; ``--state-type string``: a ``std_msgs/String``) on change and
every 0.1 s. The model's world frame is the arm's base frame on the wire.

Each period applies the newest servo_cp (a pose in another frame, non-finite, not rigid or out
of reach is refused and counted; the model keeps its setpoint). ``measured_cp``'s
``header.stamp`` echoes the stamp of the last servo_cp applied (the round-trip hook of
``pointfence bench ros2``: ros2/crtk_bridge.py), or the time of the measurement before the first
(``--no-echo``: always the measurement time). A model that faults (following error) reports
FAULT and stays so (restart the node). Ctrl-C or SIGTERM ends it cleanly.
"""
from __future__ import annotations

import signal
import sys
import time

import numpy as np

from pointfence.kernels.errors import InputError

from . import cdr
from . import crtk_wire as wire

STATE_PERIOD_S = 0.1


def add_arguments(p) -> None:
    p.add_argument("--namespace", default="PSM1", help="the arm's ROS namespace (default PSM1)")
    p.add_argument("--model", choices=("raven2", "point-mass"), default="raven2",
                   help="simulated model (default raven2; --config takes a scene's [robot] table instead)")
    p.add_argument("--config", default=None, help="scene TOML whose [robot] table builds the arm")
    p.add_argument("--rate", type=float, default=1000.0, help="step and publish rate (Hz, default 1000)")
    p.add_argument("--frame-id", default="", help='frame of its poses (default "<namespace>_base")')
    p.add_argument("--state-type", choices=("crtk", "string"), default="crtk",
                   help="operating_state as crtk_msgs/OperatingState (built here) or std_msgs/String")
    p.add_argument("--no-echo", action="store_true", help="measured_cp stamps are measurement times only")
    p.add_argument("--duration", type=float, default=0.0, help="run this many seconds (0: until Ctrl-C)")


def build_model(args):
    """The simulated robot of ``args`` (``--config``'s [robot] table, else ``--model``)."""
    from ..robot import make_robot, robot_from_config

    if args.config:
        from ..config import load

        cfg = load(args.config)
        if cfg.robot.model not in ("raven2", "point-mass"):
            raise InputError(f"sim-arm --config {args.config}: [robot] model = {cfg.robot.model!r}; expected a "
                             "simulated model (\"raven2\" or \"point-mass\")")
        return robot_from_config(cfg.robot)
    if args.model == "raven2":
        from ..robot.raven2 import Raven2

        return make_robot("raven2", T_world_base=Raven2.mount_tool_down(np.array([0.0, 0.0, 0.25])))
    return make_robot(args.model)


class SimArm:
    """The node: ``robot`` (service/robot interface) behind CRTK topics in ``namespace``."""

    def __init__(self, robot, namespace: str, frame_id: str = "", state_type: str = "crtk", echo: bool = True):
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import JointState

        from .node import RosNode

        ns = wire.check_namespace(namespace)
        self.robot, self.echo = robot, echo
        self.frame_id = frame_id or f"{ns.replace('/', '_') or 'arm'}_base"
        self.state_cls = wire.state_type(state_type)
        self.ros = RosNode("pointfence_sim_arm_" + (ns.replace("/", "_") or "arm"), executor="events")
        node = self.ros.node
        self._cmd = None                    # newest servo_cp: (stamp ns, frame_id, pose 7-tuple)
        self._cmd_seen = None
        self.applied = self.refused = 0
        self.last_refusal = ""
        self._stamp = None                  # the stamp of the last servo_cp applied
        self._T = np.eye(4)
        # (serialized: ros2/cdr.py; 1 kHz messages as rclpy objects cost most of this process's time)
        self._cp = cdr.StampedWriter("pose", self.frame_id)
        self._js = cdr.JointStateWriter(robot.joint_names, self.frame_id)
        self._state_name, self._state_at = None, 0.0
        self._pub_cp = node.create_publisher(PoseStamped, wire.topic(ns, "measured_cp"), wire.qos_reliable())
        self._pub_js = node.create_publisher(JointState, wire.topic(ns, "measured_js"), wire.qos_reliable())
        self._pub_state = node.create_publisher(self.state_cls, wire.topic(ns, "operating_state"), wire.qos_reliable(10))
        self._servo = self.ros.polled(PoseStamped, wire.topic(ns, "servo_cp"), wire.qos_stream())
        self.ros.start()

    def period(self, dt: float) -> None:
        """Apply the newest servo_cp, step the model ``dt`` seconds, publish its state."""
        got = self._servo.take()          # (the newest only: the subscription keeps one)
        if got is not None:
            try:
                self._cmd = cdr.decode_pose_stamped(got[0])
            except cdr.CdrError as e:
                self.refused += 1
                self.last_refusal = f"servo_cp {e}"
        r, cmd = self.robot, self._cmd
        if cmd is not None and cmd is not self._cmd_seen:
            self._cmd_seen = cmd
            stamp, frame, pose = cmd
            why = (f"frame_id {frame!r}; expected {self.frame_id!r}" if frame != self.frame_id
                   else wire.pose_problem(pose))
            try:
                if why is not None:
                    raise InputError(f"servo_cp {why}")
                r.servo_cp(wire.pose_to_matrix(pose, self._T))
                self.applied += 1
                self._stamp = stamp
            except InputError as e:
                self.refused += 1
                self.last_refusal = str(e)
        r.step(dt)
        now = time.time_ns()
        pose = wire.pose_of(r.measured_cp(out=self._T))
        self._pub_cp.publish(self._cp.encode(self._stamp if (self.echo and self._stamp is not None) else now, pose))
        js = r.measured_js()
        self._pub_js.publish(self._js.encode(now, js.position.tolist(), js.velocity.tolist(), js.effort.tolist()))
        name = "FAULT" if r.state.name == "FAULT" else wire.ENABLED
        mono = time.monotonic()
        if name != self._state_name or mono - self._state_at >= STATE_PERIOD_S:
            self._state_name, self._state_at = name, mono
            msg = self.state_cls()
            if hasattr(msg, "state"):
                wire.set_stamp(msg.header, now)
                msg.header.frame_id = self.frame_id
                msg.state, msg.is_homed, msg.is_busy = name, True, False
            else:
                msg.data = name
            self._pub_state.publish(msg)

    def close(self) -> None:
        self.ros.close()


def run(args) -> int:
    from ..clock import RealClock
    from ..periodic import PeriodicLoop

    if not (10.0 <= args.rate <= 10000.0):
        raise InputError(f"sim-arm --rate {args.rate:g}; expected 10-10000 Hz")
    robot = build_model(args)
    arm = SimArm(robot, args.namespace, args.frame_id, args.state_type, echo=not args.no_echo)
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    end = time.monotonic() + args.duration if args.duration > 0 else float("inf")
    sched = PeriodicLoop(1.0 / args.rate, RealClock(spin_s=0.0))
    print(f"sim-arm: {robot.model} on {wire.topic(args.namespace, '')} (frame {arm.frame_id!r}) at {args.rate:g} Hz",
          file=sys.stderr, flush=True)
    try:
        sched.run(lambda k: arm.period(sched.dt), keep_going=lambda: not stop and time.monotonic() < end)
    finally:
        arm.close()
    print(f"sim-arm: stopped; {arm.applied} servo_cp applied, {arm.refused} refused"
          + (f" (last: {arm.last_refusal})" if arm.refused else ""), file=sys.stderr)
    return 0
