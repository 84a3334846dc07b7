"""`pointfence ros2 sim-master --namespace MTMR [--trajectory CSV | --circle]`: a simulated CRTK
master (a dVRK MTM or a ROS 2 haptic device) as a ROS 2 node in its own process.

It publishes what such a device publishes and listens where it listens:

* ``/<ns>/measured_cp`` (``geometry_msgs/PoseStamped``, ``header.frame_id`` ``--frame-id``,
  default ``<ns>_base``) at ``--rate`` Hz: a trajectory CSV (``t,x,y,z[,clutch]``, master frame,
  m, s; clients/trajectory.py) played by linear interpolation, or ``--circle``: a 2 cm circle of
  4 s period that sinks 9 cm in its first second (the loop benchmark's master: against the
  default scene it presses into the fixture), identity orientation;
* the foot pedal (``sensor_msgs/Joy``) on ``--clutch-topic``, button ``--clutch-button``: the
  trajectory's clutch column (1: coupled) as the pedal a real console would show, by
  ``--pedal`` (``decouples``: a dVRK clutch pedal, released while coupled; ``couples``: a
  dead-man pedal, pressed while coupled; see ros2/crtk_device.py), published at every change
  and every 0.1 s (a subscriber that joins late learns the pedal's state);
* ``/<ns>/body/servo_cf`` (``geometry_msgs/WrenchStamped``): every force received is counted
  and, with ``--forces CSV``, written as ``t,frame_id,fx,fy,fz`` (this process's monotonic
  clock, s; N). A summary line goes to stderr every ``--status-every`` s; on exit (``--duration``,
  SIGTERM or Ctrl-C) the summary is printed as JSON on stdout.

``--start-on-force`` holds the motion's first sample until the first force arrives (the service
hears the device). ``--ready-file`` is written once the node's publishers and subscription exist.
"""
from __future__ import annotations

import json
import math
import signal
import sys
import time
from pathlib import Path

import numpy as np

from pointfence.kernels.errors import InputError

from ..masters import ScriptedMaster
from . import cdr
from . import crtk_wire as wire
from .crtk_device import PEDAL_MEANINGS, CrtkDevice


def add_arguments(p):
    p.add_argument("--namespace", required=True, help="the device's namespace, e.g. MTMR (topics /MTMR/measured_cp, "
                                                      "/MTMR/body/servo_cf)")
    m = p.add_mutually_exclusive_group()
    m.add_argument("--trajectory", default=None, metavar="CSV", help="play this t,x,y,z[,clutch] CSV (master frame, m)")
    m.add_argument("--circle", action="store_true", help="a 2 cm circle that presses 9 cm down (the default motion)")
    p.add_argument("--rate", type=float, default=1000.0, help="measured_cp rate, Hz (default 1000, as the dVRK's MTM)")
    p.add_argument("--frame-id", default=None, help="header.frame_id of measured_cp (default <namespace>_base)")
    p.add_argument("--clutch-topic", default="/footpedals/clutch", help="the pedal's Joy topic (default /footpedals/clutch)")
    p.add_argument("--clutch-button", type=int, default=0, help="the pedal's index in the Joy buttons (default 0)")
    p.add_argument("--pedal", choices=PEDAL_MEANINGS, default="decouples",
                   help="decouples: a clutch pedal, released while coupled (default, the dVRK's); couples: pressed "
                        "while coupled (a dead-man pedal)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: until SIGTERM)")
    p.add_argument("--start-on-force", action="store_true",
                   help="hold the motion's first sample until the first force arrives on body/servo_cf (the service "
                        "hears the device), so that the motion does not run ahead of a slow start")
    p.add_argument("--loop", action="store_true", help="repeat the trajectory (default: hold its last sample)")
    p.add_argument("--forces", default=None, metavar="CSV", help="write every force received here (t,frame_id,fx,fy,fz)")
    p.add_argument("--status-every", type=float, default=1.0, help="summary line period on stderr, s (0: none)")
    p.add_argument("--ready-file", default=None, help="write this file once the node is up")


def circle_motion(duration: float) -> ScriptedMaster:
    """A 2 cm circle of 4 s period (master frame, m) that sinks 9 cm during its first second,
    pedal coupled throughout, for ``duration`` s."""
    t = np.arange(0.0, duration + 0.01, 0.01)
    w = 2 * math.pi / 4.0
    sink = np.minimum(t / 1.0, 1.0) * -0.09
    p = np.stack([0.02 * np.cos(w * t) - 0.02, 0.02 * np.sin(w * t), sink], 1)
    return ScriptedMaster(t, p, name="circle")


class SimMaster:
    """The node's state: the motion, the pedal, the forces received."""

    def __init__(self, args):
        if not args.rate > 0 or args.rate > 10000:
            raise InputError(f"--rate {args.rate}; expected 0 < Hz <= 10000")
        self.dev = CrtkDevice(namespace=args.namespace, clutch_topic=args.clutch_topic,
                              clutch_button=args.clutch_button, pedal=args.pedal)
        self.frame = args.frame_id or f"{self.dev.namespace}_base"
        self.motion = (ScriptedMaster.from_csv(args.trajectory) if args.trajectory
                       else circle_motion(3600.0 if args.duration is None else args.duration + 1.0))
        self.loop = bool(args.loop)
        self.forces = 0
        self.frames_seen: dict = {}
        self.max_force = 0.0
        self.last_force = (0.0, 0.0, 0.0)
        self.nonzero = 0
        self._rows: list = []
        self._out = Path(args.forces).open("w") if args.forces else None
        if self._out is not None:
            self._out.write("t,frame_id,fx,fy,fz\n")

    def on_force(self, raw: bytes) -> None:
        _, fr, w = cdr.decode_wrench_stamped(raw)    # (a bad one raises: the sim-master stops, saying why)
        v = w[:3]
        n = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        self.forces += 1
        self.nonzero += n > 0
        self.max_force = max(self.max_force, n)
        self.last_force = v
        self.frames_seen[fr] = self.frames_seen.get(fr, 0) + 1
        if self._out is not None:
            self._rows.append(f"{time.monotonic():.6f},{fr},{v[0]:.6g},{v[1]:.6g},{v[2]:.6g}\n")

    def flush(self) -> None:
        if self._out is not None and self._rows:
            rows, self._rows = self._rows, []
            self._out.write("".join(rows))
            self._out.flush()

    def close(self) -> None:
        self.flush()
        if self._out is not None:
            self._out.close()

    def summary(self) -> dict:
        return {"namespace": self.dev.namespace, "forces_received": self.forces, "forces_nonzero": int(self.nonzero),
                "max_force_n": round(self.max_force, 4), "last_force_n": [round(v, 4) for v in self.last_force],
                "force_frames": self.frames_seen}


def run(args) -> int:
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Joy

    from .node import RosNode

    sim = SimMaster(args)
    dev = sim.dev
    stop = {"now": False}

    def on_signal(sig, frame):
        stop["now"] = True

    signal.signal(signal.SIGTERM, on_signal)
    reliable = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
    node = RosNode(f"pointfence_sim_master_{dev.namespace.replace('/', '_')}", executor="events")
    try:
        n = node.node
        pose_pub = n.create_publisher(PoseStamped, dev.pose_topic, reliable)
        pedal_pub = n.create_publisher(Joy, dev.clutch_topic, reliable)
        forces = node.polled(WrenchStamped, dev.force_topic, reliable)     # (taken once a period, below)
        node.start()
        if args.ready_file:
            Path(args.ready_file).write_text(json.dumps({"namespace": dev.namespace, "pose_topic": dev.pose_topic,
                                                         "force_topic": dev.force_topic}) + "\n")
        print(f"pointfence ros2 sim-master: {dev.pose_topic} at {args.rate:g} Hz (frame {sim.frame!r}), pedal "
              f"{dev.clutch_topic}[{dev.clutch_button}] ({dev.pedal}), forces from {dev.force_topic}", file=sys.stderr)
        pose, pedal = cdr.StampedWriter("pose", sim.frame), Joy()     # (poses at 1 kHz: serialized)
        period = 1.0 / args.rate
        m = sim.motion
        t0 = time.monotonic()
        nxt, last_pedal, pressed, last_status, last_flush = t0, -1.0, None, t0, t0
        waiting = bool(args.start_on_force)
        while not stop["now"]:
            now = time.monotonic()
            if args.duration is not None and now - t0 >= args.duration:
                break
            for raw, _ in forces.take_all():
                sim.on_force(raw)
            if waiting:
                if sim.forces:
                    waiting, t0 = False, now
                else:
                    t0 = now          # the motion's clock starts at the first force
            s = now - t0
            m.poll(m.times[0] + (s % max(m.duration, 1e-9) if sim.loop else s))
            stamp = time.time_ns()
            x, y, z = (float(v) for v in m.position)
            pose_pub.publish(pose.encode(stamp, (x, y, z, 0.0, 0.0, 0.0, 1.0)))
            want = int(m.clutch == (dev.pedal == "couples"))   # coupled -> the pedal's state
            if want != pressed or now - last_pedal >= 0.1:
                pressed, last_pedal = want, now
                wire.set_stamp(pedal.header, stamp)
                pedal.buttons = [0] * dev.clutch_button + [want]
                pedal_pub.publish(pedal)
            if now - last_flush >= 0.1:
                sim.flush()
                last_flush = now
            if args.status_every and now - last_status >= args.status_every:
                print(f"[sim-master {dev.namespace}] t {s:.1f} s, forces received {sim.forces} "
                      f"(last {[round(v, 3) for v in sim.last_force]} N)", file=sys.stderr)
                last_status = now
            nxt += period
            delay = nxt - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                nxt = time.monotonic()
    except KeyboardInterrupt:
        pass
    finally:
        node.close()
        sim.close()
        print(json.dumps(sim.summary()))
        sys.stdout.flush()
    return 0
