"""The ROS 2 side of the service's CRTK masters, in a process of its own (started by
ros2/crtk_master.py as ``python -m pointfence.service.ros2.master_bridge SHM DEVICES PARENT``).

One rclpy node (``pointfence_crtk_masters``) serves every device (ros2/crtk_device.py). The main
thread, once a millisecond, beats the heartbeat, takes each device's ``measured_cp`` and gripper
(``gripper/measured_js``) messages that arrived since the last period (``RosNode.polled``: no
executor thread wakes for them; each with its reception time), checks them and writes the
device's state row into shared memory (ros2/master_block.py), and the pedal's the same way
(one thread writes the rows); then it reads each device's force from shared memory and
publishes a new one on ``body/servo_cf`` (``geometry_msgs/WrenchStamped``, N, the device's
frame). The 1 kHz topics (poses, gripper, forces) travel serialized (ros2/cdr.py): a pose that
cannot be read is refused like a bad one.
Its own watchdog: when the service has written no new force for the device's timeout (its tick
stalled, or it died) while the last force published was not zero, it publishes a zero wrench once.
It ends when told to (``ctl["stop"]``), when its parent is gone, or when its node fails, and then
publishes a zero wrench to every device before it closes: a haptic device is never left pushing.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
from typing import Optional

import numpy as np

from . import cdr
from .crtk_device import CrtkDevice
from ..robot.hosted_block import attach_child, put_text
from .master_block import (COMMAND_LAYOUT, ERROR_TEXT, FRAME_TEXT, REJECT_PEDAL, REJECT_UNREADABLE, STATE_LAYOUT,
                           MasterBlock)

#: the main thread's period: force forwarding and the heartbeat, s
PERIOD_S = 0.001


class DeviceSide:
    """One device in the bridge: subscriptions that fill its state row, the force publisher."""

    def __init__(self, blk: MasterBlock, i: int, dev: CrtkDevice, ros):
        from geometry_msgs.msg import PoseStamped, WrenchStamped
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import JointState, Joy
        from std_msgs.msg import Bool

        node = ros.node
        self.dev, self.node, self.i = dev, node, i
        self.state = blk.state[i]
        self.cmd = blk.cmd[i]
        self.stats = blk.forces[i:i + 1].reshape(())   # (0-d view: this device's counters)
        self.text = blk.text[i]
        L = STATE_LAYOUT
        self.row = np.zeros(L.size)
        self.row[L.pressed] = -1.0
        self.row[L.q] = (1.0, 0.0, 0.0, 0.0)
        self.state.write(self.row)
        self.locked = dev.frame_id             # the frame poses must be in (None: the first valid pose's)
        if self.locked:
            put_text(self.text[FRAME_TEXT], self.locked)
        self._Bool = Bool
        self._wrench = None                    # (a StampedWriter for the force's frame, made at the first force)
        self.cmd_row = np.zeros(COMMAND_LAYOUT.size)
        self.seq = 0.0                         # the last force sequence forwarded
        self.new_at = time.monotonic()         # when it arrived (monotonic s)
        self.nonzero = False                   # whether the last force published was not zero
        self.told_orientation = False
        # (the 1 kHz streams keep what arrives within a few periods: a bad pose among them is seen)
        latest = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=16, reliability=ReliabilityPolicy.BEST_EFFORT)
        events = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = node.create_publisher(WrenchStamped, dev.force_topic, events)
        self.orient_pub = node.create_publisher(Bool, dev.cf_orientation_topic, events) if dev.orientation_absolute else None
        self.pose_sub = ros.polled(PoseStamped, dev.pose_topic, latest)
        self.pedal_sub = ros.polled(Joy, dev.clutch_topic, events)
        self._Joy, self._deserialize = Joy, deserialize_message
        self.grip_sub = ros.polled(JointState, dev.gripper_topic, latest) if dev.gripper != "none" else None

    # --- the main thread: messages in -> the state row --------------------------------------------------
    def take(self) -> None:
        """Take every pose, gripper and pedal message that arrived since the last call."""
        for raw, arrival in self.pose_sub.take_all():
            self.on_pose(raw, arrival)
        if self.grip_sub is not None:
            for raw, arrival in self.grip_sub.take_all():
                self.on_gripper(raw, arrival)
        for raw, _ in self.pedal_sub.take_all():
            try:
                buttons = list(self._deserialize(raw, self._Joy).buttons)
            except Exception as e:   # noqa: BLE001 -- bytes that are no Joy: decoupled, as a malformed pedal
                self.on_pedal(None, f"{self.dev.clutch_topic}: the message could not be read ({e})")
            else:
                self.on_pedal(buttons)

    def _reject(self, code: int, message: str) -> None:
        L, row = STATE_LAYOUT, self.row
        row[L.reject] = code
        row[L.rejected.start + code - 1] += 1
        put_text(self.text[ERROR_TEXT], message)

    def on_pose(self, raw: bytes, arrival: float) -> None:
        L, row = STATE_LAYOUT, self.row
        row[L.pose_rx] = arrival
        try:
            _, frame, (x, y, z, qx, qy, qz, qw) = cdr.decode_pose_stamped(raw)
        except cdr.CdrError as e:
            frame, x, y, z, qx, qy, qz, qw = "", *(math.nan,) * 7
            why = f"{self.dev.pose_topic}: {e}"
        else:
            why = None
        p, q = (x, y, z), (qw, qx, qy, qz)
        bad = self.dev.check_pose(frame, self.locked, p, q) if why is None else (REJECT_UNREADABLE, why)
        if bad is None:
            if self.locked is None:
                self.locked = frame
                put_text(self.text[FRAME_TEXT], frame)
            row[L.p] = p
            row[L.q] = q
            row[L.poses] += 1
            row[L.pose_valid] = 1.0
        else:
            row[L.pose_valid] = 0.0
            self._reject(*bad)
        self.state.write(row)

    def on_gripper(self, raw: bytes, arrival: float) -> None:
        L, row = STATE_LAYOUT, self.row
        row[L.grip_rx] = arrival
        try:
            position = cdr.decode_joint_state(raw)[2]
        except cdr.CdrError as e:
            position, bad = (), (REJECT_UNREADABLE, f"{self.dev.gripper_topic}: {e}")
        else:
            bad = self.dev.check_grip(position)
        if bad is None:
            row[L.grasp] = float(position[0])
            row[L.grips] += 1
            row[L.grip_valid] = 1.0
        else:
            row[L.grip_valid] = 0.0
            self._reject(*bad)
        self.state.write(row)

    def on_pedal(self, buttons: Optional[list], unreadable: str = "") -> None:
        """A pedal message's ``buttons`` (None: it could not be read, ``unreadable`` says why)."""
        L, row = STATE_LAYOUT, self.row
        row[L.pedals] += 1
        if buttons is None:
            row[L.pressed] = -1.0
            self._reject(REJECT_UNREADABLE, unreadable)
            self.state.write(row)
            return
        state = self.dev.pedal_state(buttons)
        if state is None:   # malformed: decoupled until a valid pedal message
            row[L.pressed] = -1.0
            self._reject(REJECT_PEDAL, f"{self.dev.clutch_topic}: buttons {buttons[:16]}; expected button "
                                       f"{self.dev.clutch_button} to be 0 (released), 1 (pressed) or 2 (quick tap)")
        else:
            row[L.pressed] = float(state)
        row[L.buttons] = float(sum(1 << k for k, v in enumerate(buttons[:52]) if v == 1))
        self.state.write(row)

    # --- the main thread: forces out ------------------------------------------------------------------
    def _publish(self, f) -> None:
        frame = self.dev.force_frame_id or self.locked
        if frame is None:    # the device has not been heard from: its frame, and whether it listens, are unknown
            return
        if self._wrench is None or self._wrench.frame_id != frame:
            self._wrench = cdr.StampedWriter("wrench", frame)
        try:
            self.pub.publish(self._wrench.encode(time.time_ns(), (*f, 0.0, 0.0, 0.0)))
            self.stats["published"] += 1
        except Exception as e:   # noqa: BLE001 -- counted and named; the service sees the device go on
            self.stats["errors"] += 1
            put_text(self.text[ERROR_TEXT], f"{self.dev.force_topic}: publishing failed: {e}")
        self.nonzero = any(v != 0.0 for v in f)

    def forward(self, now: float) -> None:
        """Publish the service's newest force if there is one; the watchdog zeroes a force the
        service stopped renewing."""
        if self.orient_pub is not None and not self.told_orientation and self.locked is not None:
            self.orient_pub.publish(self._Bool(data=True))
            self.told_orientation = True
        c = self.cmd_row
        if self.cmd.read(c) and c[COMMAND_LAYOUT.seq] != self.seq:
            self.seq = c[COMMAND_LAYOUT.seq]
            self.new_at = now
            f = tuple(float(v) for v in c[COMMAND_LAYOUT.f])
            if all(math.isfinite(v) for v in f):
                self._publish(f)
                return
            self.stats["nonfinite"] += 1
            put_text(self.text[ERROR_TEXT], f"non-finite force {f} from the service; published zero instead")
            self._publish((0.0, 0.0, 0.0))
        elif self.nonzero and now - self.new_at > self.dev.timeout_s:
            self.stats["zeroed"] += 1
            self._publish((0.0, 0.0, 0.0))

    def zero(self) -> None:
        try:
            self._publish((0.0, 0.0, 0.0))
        except Exception:   # noqa: BLE001 -- the context may be gone already
            pass


def main(shm_name: str, devices: list, parent: int) -> int:
    shm = attach_child(shm_name)
    blk = MasterBlock(shm.buf, len(devices))
    ctl = blk.ctl
    node = None
    sides: list = []
    try:
        from .node import RosNode

        node = RosNode("pointfence_crtk_masters", executor="events")   # poses at 1 kHz: see ros2/node.py
        sides = [DeviceSide(blk, i, CrtkDevice(**d), node) for i, d in enumerate(devices)]
        node.start()
        ctl["pid"] = os.getpid()
        ctl["ready"] = 1
        nxt = time.monotonic()
        while int(ctl["stop"]) == 0 and os.getppid() == parent and node.error is None:
            now = time.monotonic()
            ctl["beat"] += 1
            for s in sides:
                s.take()
                s.forward(now)
            nxt += PERIOD_S
            delay = nxt - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                nxt = time.monotonic()
        if node.error is not None:
            raise RuntimeError(f"the bridge's ROS 2 node failed: {node.error}")
        return 0
    except BaseException as e:
        ctl["failed"] = 1
        if blk.n:
            put_text(blk.text[0, ERROR_TEXT], f"CRTK master bridge: {type(e).__name__}: {e}")
        print(f"pointfence CRTK master bridge: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    finally:
        for s in sides:
            s.zero()
        if node is not None:
            time.sleep(0.02)   # (the zero wrenches leave before the participant goes)
            node.close()
        del blk, ctl, sides
        try:
            shm.close()
        except BufferError:   # (a view still alive at exit: the mapping goes with the process)
            pass

if __name__ == "__main__":
    sys.exit(main(sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3])))
