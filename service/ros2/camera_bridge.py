"""The ROS 2 side of a ``ros2:`` camera source, in a process of its own (started by
ros2/camera_source.py as ``python -m pointfence.service.ros2.camera_bridge SHM SPEC PARENT FD``).

One rclpy node (``pointfence_camera_<name>``) subscribes to the image topic (``sensor_msgs/Image``
or, for the ``compressedDepth`` transport, ``sensor_msgs/CompressedImage``) and the CameraInfo
topic, both raw (the callbacks get the serialized bytes). Its executor thread writes every image
into the shared-memory block (ros2/camera_block.py) with its arrival time and writes one byte into
the pipe ``FD`` so the source's reader thread, blocked on the pipe's other end, wakes; CameraInfo
is written whenever it changes other than in its stamp. Decoding and every check stay in the
source (one place for what a malformed message is).

**Why a process.** In the service's process, the executor's take of each 600 kB depth image (the
middleware's buffer copied into a Python ``bytes`` under the interpreter lock) kept the 1 kHz
loop waiting for the lock once a frame (measured: bench/HISTORY.md, the ros2 section, stop 36);
here that copy runs beside the loop instead of in front of it.

It ends when told to (``ctl["stop"]``), when its parent is gone, or when its node fails.
"""
from __future__ import annotations

import json
import os
import sys
import time

from ..robot.hosted_block import attach_child, put_text
from .camera_block import CameraBlock

#: the main loop's period (heartbeat, parent and stop checks), s
PERIOD_S = 0.05


def qos_profile(name: str):
    """rclpy's quality of service for ``name``: ``sensor_data`` (best effort, which also receives
    from reliable publishers) or ``reliable``."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

    if name == "reliable":
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE)
    return qos_profile_sensor_data


class Forwarder:
    """The node's callbacks: messages into the block, a byte into the pipe per image."""

    def __init__(self, blk: CameraBlock, fd: int):
        self.blk, self.fd = blk, fd
        self._info_body = None   # the last CameraInfo written, less its stamp

    def on_image(self, raw: bytes) -> None:
        if self.blk.write_image(raw, time.time()):
            try:
                os.write(self.fd, b"\x01")
            except BlockingIOError:   # the reader has a wake-up waiting already
                pass

    def on_info(self, raw: bytes) -> None:
        body = raw[:4] + raw[12:]   # (bytes 4-12: the header's stamp, new in every message)
        if body != self._info_body and self.blk.write_info(raw):
            self._info_body = body


def main(shm_name: str, spec: dict, parent: int, fd: int) -> int:
    shm = attach_child(shm_name)
    blk = CameraBlock(shm.buf, spec["capacity"])
    ctl = blk.ctl
    os.set_blocking(fd, False)
    node = None
    try:
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image

        from .node import RosNode

        node = RosNode(spec["node"], domain_id=spec.get("domain_id"), executor="events")
        fwd = Forwarder(blk, fd)
        profile = qos_profile(spec["qos"])
        msg_type = CompressedImage if spec["transport"] == "compressedDepth" else Image
        node.node.create_subscription(msg_type, spec["image_topic"], fwd.on_image, profile, raw=True)
        node.node.create_subscription(CameraInfo, spec["info_topic"], fwd.on_info, profile, raw=True)
        node.start()
        ctl["pid"] = os.getpid()
        ctl["ready"] = 1
        while int(ctl["stop"]) == 0 and os.getppid() == parent and node.error is None:
            ctl["beat"] += 1
            time.sleep(PERIOD_S)
        if node.error is not None:
            raise RuntimeError(f"the camera bridge's ROS 2 node failed: {node.error}")
        return 0
    except BaseException as e:
        ctl["failed"] = 1
        put_text(blk.text, f"ROS 2 camera bridge: {type(e).__name__}: {e}")
        print(f"pointfence ROS 2 camera bridge: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    finally:
        if node is not None:
            node.close()
        del blk, ctl
        try:
            shm.close()
        except BufferError:   # (a view still alive at exit: the mapping goes with the process)
            pass
        os.close(fd)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])))
