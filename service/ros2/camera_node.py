"""`pointfence ros2 camera-node`: any pointfence depth source published as a ROS 2 camera.

``pointfence ros2 camera-node --source SPEC --namespace /cam0`` opens ``SPEC`` (recorded,
synthetic, openni2, depthai, ...) and publishes, for every frame, the standard messages a ROS
depth driver publishes (the layout ``ros2:/cam0`` reads, ``camera_source.py``):

* ``/cam0/depth/image_raw``: ``sensor_msgs/Image`` 16UC1 (mm; the source's codes converted when
  its units are not mm, 0 where there is no reading); with ``--compressed``
  ``/cam0/depth/image_raw/compressedDepth`` instead: ``sensor_msgs/CompressedImage`` in the
  ``compressedDepth`` PNG form (lossless);
* ``/cam0/depth/camera_info``: ``sensor_msgs/CameraInfo`` of the source's ``Camera`` (K, D
  plumb_bob, width, height); the camera's pose is not sent (it is the receiving scene's
  ``[[camera]] T_world_cam``).

``header.frame_id`` is ``--frame-id`` (default ``<namespace>_depth_optical_frame``).
``header.stamp`` (``--stamp``): ``mapped`` (default) puts the capture on ROS time
(``time.time()``, the clock other nodes use): a camera's capture time moved by the offset of the
two clocks at its first frame (the stamps keep the camera's own spacing); a file's or a synthetic
scene's frame is captured the moment it is due and read (a schedule that slips, e.g. behind a
slow first read, never leaves the stamps behind the frames); ``source`` is the capture time as the source gives
it (a recording's own timestamps); ``now`` is the moment the frame was published.

Pacing: a live source (a camera) is published as it delivers, at most ``--rate`` Hz; a file or
synthetic source is read at ``--rate`` Hz (default: the source's rate) on absolute deadlines.
``--frames N`` stops after N frames. Ctrl-C or SIGTERM ends it cleanly (node destroyed, source
closed, exit status 0).
"""
from __future__ import annotations

import math
import signal
import sys
import threading
import time
from typing import Optional

from pointfence.kernels.errors import InputError, PointfenceError

from . import images

STAMPS = ("mapped", "source", "now")


def add_arguments(p) -> None:
    p.add_argument("--source", required=True, help="pointfence source spec, e.g. recorded:DIR, synthetic:sphere, openni2:any")
    p.add_argument("--namespace", default="/cam0", help="topic namespace (default /cam0: /cam0/depth/image_raw, ...)")
    p.add_argument("--rate", type=float, default=None, help="frames per second (default: the source's rate; live sources: at most)")
    p.add_argument("--compressed", action="store_true", help="publish compressedDepth (PNG) instead of a raw 16UC1 Image")
    p.add_argument("--frame-id", default=None, help="header.frame_id (default <namespace>_depth_optical_frame)")
    p.add_argument("--stamp", choices=STAMPS, default="mapped", help="header.stamp: mapped (default), source or now")
    p.add_argument("--qos", choices=("reliable", "sensor_data"), default="reliable",
                   help="publisher QoS (reliable, the default, reaches best-effort and reliable subscribers)")
    p.add_argument("--frames", type=int, default=0, help="stop after this many frames (0: run until stopped)")


def topics(namespace: str) -> tuple:
    """(image, compressedDepth image, camera_info) topics under ``namespace``."""
    ns = "/" + str(namespace).strip().strip("/")
    if ns == "/":
        raise InputError("camera-node: --namespace is empty; give one, e.g. /cam0")
    base = ns + "/depth/image_raw"
    return base, base + "/compressedDepth", ns + "/depth/camera_info"


class CameraPublisher:
    """Publishes one camera's frames on ``node`` (an rclpy node) under ``namespace``."""

    def __init__(self, node, namespace: str, camera, compressed: bool = False, frame_id: str = "",
                 stamp: str = "mapped", qos: str = "reliable"):
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image

        if stamp not in STAMPS:
            raise InputError(f"camera-node: stamp = {stamp!r}; expected one of {', '.join(STAMPS)}")
        image, cimage, info = topics(namespace)
        profile = (qos_profile_sensor_data if qos == "sensor_data" else
                   QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE))
        self.camera = camera
        self.compressed = bool(compressed)
        self.frame_id = frame_id or (namespace.strip("/").replace("/", "_") + "_depth_optical_frame")
        self.stamp = stamp
        self.image_topic = cimage if compressed else image
        self.info_topic = info
        self._image = node.create_publisher(CompressedImage if compressed else Image, self.image_topic, profile)
        self._info = node.create_publisher(CameraInfo, info, profile)
        self._offset = None
        self.published = 0

    def stamp_of(self, capture: float, read_at: Optional[float] = None) -> float:
        """header.stamp (s) of a frame captured at ``capture`` on the source's clock and read
        from the source at ``read_at`` (``time.time()``; None for a camera, which delivers on its
        own): ``mapped`` stamps a file's frame with ``read_at``, and a camera's with its capture
        time moved by the offset of the two clocks at its first frame, fixed before that frame's
        read, so no later stamp lies ahead of the moment its frame was read."""
        if self.stamp == "source":
            return capture
        now = time.time()
        if self.stamp == "now":
            return now
        if read_at is not None:
            return read_at
        if self._offset is None:
            self._offset = (now if read_at is None else read_at) - capture
        return capture + self._offset

    def publish(self, frame, read_at: Optional[float] = None) -> float:
        """Publish ``frame`` (a ``DepthFrame`` of this camera) and its CameraInfo; returns the stamp."""
        t = self.stamp_of(float(frame.timestamp), read_at)
        make = images.compressed_msg if self.compressed else images.image_msg
        msg = make(frame.depth, self.camera, self.frame_id, t)
        self._info.publish(images.info_msg(self.camera, self.frame_id, t))
        self._image.publish(msg)
        self.published += 1
        return t


def run(args) -> int:
    from pointfence.service.sources import open_source

    from .node import RosNode

    if args.rate is not None and not (math.isfinite(args.rate) and 0 < args.rate <= 1000):
        raise InputError(f"camera-node: --rate {args.rate}; expected frames per second in (0, 1000]")
    if args.frames < 0:
        raise InputError(f"camera-node: --frames {args.frames}; expected 0 (no end) or a positive count")
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    src = open_source(args.source)
    try:
        rate = float(args.rate or src.rate_hz)
        ns = "/" + args.namespace.strip().strip("/")
        with RosNode("pointfence_camera_node", namespace="") as rn:
            pub = CameraPublisher(rn.node, ns, src.camera, args.compressed, args.frame_id or "", args.stamp, args.qos)
            print(f"camera-node: {args.source} -> {pub.image_topic} + {pub.info_topic} "
                  f"({src.camera.width}x{src.camera.height} at {rate:g} Hz)", flush=True)
            _loop(src, pub, rate, args.frames, stop)
            if rn.error:
                print(f"camera-node: the ROS node failed: {rn.error}", file=sys.stderr)
                return 1
    except PointfenceError as e:
        print(f"camera-node: {e}", file=sys.stderr)
        return 1
    finally:
        src.close()
        for s, h in previous.items():
            signal.signal(s, h)
    return 0


def _loop(src, pub: CameraPublisher, rate: float, frames: int, stop: threading.Event) -> None:
    """Read and publish until ``stop``, the end of the stream, or ``frames`` frames."""
    period = 1.0 / rate
    due = time.monotonic()
    last = -math.inf
    read_at = None
    while not stop.is_set() and (frames == 0 or pub.published < frames):
        if src.realtime:   # a camera: publish as it delivers, at most ``rate``
            frame = src.read(timeout=0.2)
            if frame is None:
                if src.ended:
                    return
                continue
            now = time.monotonic()
            if now - last < 0.9 * period:
                continue
            last = now
        else:              # a file or a synthetic scene: read on absolute deadlines
            if stop.wait(max(0.0, due - time.monotonic())):
                return
            due = max(due + period, time.monotonic() - period)
            read_at = time.time()   # a file's frame is "captured" when it is due and read
            frame = src.read()
            if frame is None:
                return
        pub.publish(frame, read_at)
