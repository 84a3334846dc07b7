"""``ros2:<namespace or image topic>``: depth frames from a ROS 2 camera driver.

Topics. A namespace ``ros2:/cam0`` means the usual driver layout: ``/cam0/depth/image_raw``
(raw transport) or ``/cam0/depth/image_raw/compressedDepth`` (``transport=compressedDepth``),
with ``/cam0/depth/camera_info``. A target whose last name starts with ``image``
(``image_raw``, ``image_rect_raw``, ...) is an image topic used as given; one ending in
``/compressedDepth`` is that transport's topic. Either way the CameraInfo is the image's sibling
``camera_info`` (``/a/b/image_rect_raw`` -> ``/a/b/camera_info``). The options ``image_topic``
and ``info_topic`` name them outright.

Messages (``images.py``): ``sensor_msgs/Image`` 16UC1 (mm) or 32FC1 (m), or
``sensor_msgs/CompressedImage`` in the ``compressedDepth`` PNG form, with
``sensor_msgs/CameraInfo`` (K, D plumb_bob, width, height). Without a camera from the scene the
source waits up to ``wait`` s (default 5) for a CameraInfo and takes its intrinsics from it
(``depth_scale`` 0.001 unless given); with one, every image must match its size.

Threads. The rclpy callbacks run on the source's own ``RosNode`` thread (rclpy's events executor)
and only keep the newest message and its arrival time (a reference swap under a short lock); the
image comes serialized (a raw subscription) and ``read`` (the camera reader's thread,
``sources/threaded.py``) reads it (``cdr.decode_image``: the pixels a view into its bytes),
decodes and checks it. A bad message (encoding, size,
step, a CameraInfo that disagrees, a damaged compressedDepth payload, a foreign frame_id) is
counted and reported (``last_error``, ``status()``) and skipped: the reader never stops on it,
and while only bad messages come the camera goes stale and the service holds (S2).

Time. ``DepthFrame.timestamp`` is the message's ``header.stamp`` in seconds (ROS time: seconds
since 1970 on the publisher's clock); the service maps it onto its loop clock with this camera's offset and
drift, estimated online (``service/camera_clock.py``). Camera latency: ``frame_times(seq)`` gives a
delivered frame's stamp and its arrival (``time.time()``, the clock ROS time is on when the
publisher runs on this machine); a snapshot built from frame ``seq`` and published at
``time.time() = t`` is ``t - stamp`` seconds behind the camera (the bench sets
``LiveFrames.on_snapshot`` to note ``t``). Messages replaced by a newer one before ``read`` took
them are counted in ``status()['overwritten']`` (frames dropped on the way into the service).

Options (``ros2:/cam0?transport=compressedDepth&qos=reliable``): ``name``, ``transport``
(raw | compressedDepth), ``image_topic``, ``info_topic``, ``qos`` (``sensor_data``: best effort,
the default, which also receives from reliable publishers; or ``reliable``), ``wait`` (s for the
first CameraInfo), ``timeout`` (s one read waits), ``frame_id`` (the only frame_id accepted),
``rate_hz`` (the nominal rate: staleness is counted in its periods), ``realtime`` (ignored: a
ROS camera is always live), ``domain_id``, and the camera keys of ``images.CAMERA_KEYS``.
"""
from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from typing import Optional

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import InputError
from pointfence.kernels.frame import DepthFrame

from ..sources.base import LiveSource
from . import cdr, images

TRANSPORTS = ("raw", "compressedDepth")
QOS = ("sensor_data", "reliable")
#: delivered frames whose stamp and arrival are kept for ``frame_times``
FRAME_LOG = 256


def resolve_topics(target: str, transport: Optional[str] = None, image_topic: Optional[str] = None,
                   info_topic: Optional[str] = None) -> tuple:
    """(image topic, camera_info topic, transport) of a ``ros2:`` target (module docstring)."""
    t = "/" + str(target).strip().strip("/")
    if transport not in (None,) + TRANSPORTS:
        raise InputError(f"ros2 source {target!r}: transport = {transport!r}; expected one of {', '.join(TRANSPORTS)}")
    parts = t.split("/")
    if parts[-1] == "compressedDepth":
        if transport == "raw":
            raise InputError(f"ros2 source {target!r} names a compressedDepth topic but transport = 'raw'")
        base, transport = "/".join(parts[:-1]), "compressedDepth"
    elif parts[-1].startswith("image"):
        base = t
    else:
        base = t.rstrip("/") + "/depth/image_raw"
    transport = transport or "raw"
    image = image_topic or (base + "/compressedDepth" if transport == "compressedDepth" else base)
    info = info_topic or "/".join(base.split("/")[:-1]) + "/camera_info"
    return image, info, transport


def _qos(name: str, target: str):
    from rclpy.qos import QoSProfile, qos_profile_sensor_data, ReliabilityPolicy, HistoryPolicy

    if name == "sensor_data":
        return qos_profile_sensor_data
    if name == "reliable":
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE)
    raise InputError(f"ros2 source {target!r}: qos = {name!r}; expected one of {', '.join(QOS)}")


class RosDepthSource(LiveSource):
    """Depth frames from ROS 2 topics (see the module docstring)."""

    def __init__(self, target: str, camera: Optional[Camera] = None, *, name: Optional[str] = None,
                 transport: Optional[str] = None, image_topic: Optional[str] = None, info_topic: Optional[str] = None,
                 qos: str = "sensor_data", wait: float = 5.0, timeout: float = 1.0, frame_id: Optional[str] = None,
                 rate_hz: float = 30.0, realtime: bool = True, domain_id: Optional[int] = None, **camera_options):
        del realtime   # always live
        self.target = str(target)
        for key, v in (("wait", wait), ("timeout", timeout)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"ros2 source {target!r}: {key} = {v!r}; expected seconds > 0")
        self.image_topic, self.info_topic, self.transport = resolve_topics(target, transport, image_topic, info_topic)
        self.timeout = float(timeout)
        self.frame_id = frame_id or None
        cam_name = name or (camera.name if camera is not None else "cam0")
        if camera is not None and camera_options:
            raise InputError(f"ros2 source {target!r}: camera option(s) {', '.join(sorted(camera_options))} given with a "
                             f"camera {camera.name!r} from the scene; set them in its [[camera]] entry")
        self._lock = threading.Lock()
        self._new = threading.Event()
        self._msg = None
        self._msg_arrival = 0.0
        self._info = None
        self.received = self.delivered = self.overwritten = self.rejected = 0
        self.last_error: Optional[str] = None
        self._newest_bad = False
        self._times: "OrderedDict[int, tuple]" = OrderedDict()
        from .node import RosNode

        from sensor_msgs.msg import CameraInfo, CompressedImage, Image

        profile = _qos(qos, target)
        node_name = "pointfence_camera_" + "".join(c if c.isalnum() else "_" for c in cam_name)
        self._node = RosNode(node_name, domain_id=domain_id, executor="events")
        try:
            msg_type = CompressedImage if self.transport == "compressedDepth" else Image
            self._node.node.create_subscription(msg_type, self.image_topic, self._on_image, profile, raw=True)
            self._node.node.create_subscription(CameraInfo, self.info_topic, self._on_info, profile)
            self._node.start()
            self.from_info = camera is None
            if camera is None:
                info = self._wait_info(float(wait))
                camera = images.camera_from_info(info, cam_name, self._where(self.info_topic), **camera_options)
            super().__init__(camera, rate_hz, realtime=False)
        except BaseException:
            self._node.close()
            raise

    # -- rclpy callbacks (the node's thread): keep the newest, nothing else ---------------
    def _on_image(self, msg) -> None:
        now = time.time()
        with self._lock:
            if self._msg is not None:
                self.overwritten += 1
            self._msg, self._msg_arrival = msg, now
            self.received += 1
        self._new.set()

    def _on_info(self, msg) -> None:
        with self._lock:
            self._info = msg

    def _wait_info(self, wait: float):
        end = time.monotonic() + wait
        while time.monotonic() < end:
            with self._lock:
                if self._info is not None:
                    return self._info
            if self._node.error:
                break
            time.sleep(0.01)
        why = f" (node error: {self._node.error})" if self._node.error else ""
        raise InputError(f"ros2 source {self.target!r}: no CameraInfo on {self.info_topic} within {wait:g} s{why}; start the "
                         "camera driver (or `pointfence ros2 camera-node`), check ROS_DOMAIN_ID and the topic names "
                         "(`ros2 topic list`), or give fx, fy, cx, cy, width, height in [[camera]]")

    def _where(self, topic: str) -> str:
        return f"ros2 camera {self.target!r} ({topic})"

    # -- the reader's side -----------------------------------------------------------------
    @property
    def realtime(self) -> bool:
        return True

    def read(self, timeout: Optional[float] = None) -> Optional[DepthFrame]:
        """The newest message as a frame; None when none came within ``timeout`` s (default the
        ``timeout`` option) or the newest was malformed (then ``last_error`` says why)."""
        if self._closed:
            raise InputError(f"RosDepthSource for camera {self._camera.name!r} is closed; open a new source to read again")
        if not self._new.wait(self.timeout if timeout is None else max(0.0, float(timeout))):
            if self._node.error:
                self.last_error = f"{self._where(self.image_topic)}: the ROS node stopped: {self._node.error}"
            return None
        with self._lock:
            self._new.clear()
            msg, arrival, info = self._msg, self._msg_arrival, self._info
            self._msg = None
        if msg is None:
            return None
        try:
            frame = self._frame_of(msg, info)
        except InputError as e:
            self.rejected += 1
            self.last_error = str(e)
            self._newest_bad = True
            return None
        with self._lock:
            self._newest_bad = False
            self.delivered += 1
            self._times[frame.seq] = (frame.timestamp, arrival)
            while len(self._times) > FRAME_LOG:
                self._times.popitem(last=False)
        return frame

    def _frame_of(self, raw: bytes, info) -> DepthFrame:
        where = self._where(self.image_topic)
        cam = self._camera
        try:
            msg = cdr.decode_compressed_image(raw) if self.transport == "compressedDepth" else cdr.decode_image(raw)
        except cdr.CdrError as e:
            raise InputError(f"{where}: {e}") from None
        if info is None:
            raise InputError(f"{where}: an image came but no CameraInfo on {self.info_topic} yet; the driver must publish both")
        images.check_info_matches(info, cam, self.from_info, self._where(self.info_topic))
        images.frame_id_check(str(msg.header.frame_id), str(info.header.frame_id), self.frame_id, where)
        if self.transport == "compressedDepth":
            depth = images.depth_from_compressed(msg, cam, where)
        else:
            depth = images.depth_from_image(msg, cam, where)
        stamp = images.stamp_seconds(msg.header.stamp)
        seq = self._seq
        self._seq += 1
        return DepthFrame(cam.name, depth, stamp, seq)

    def threads(self) -> list:
        """The node's thread (its callbacks take the interpreter lock; the feed raises it)."""
        th = self._node.thread
        return [th] if th is not None else []

    def frame_times(self, seq: int) -> Optional[tuple]:
        """(header.stamp, arrival on ``time.time()``) in s of delivered frame ``seq`` (the last
        ``FRAME_LOG`` frames), or None."""
        with self._lock:
            return self._times.get(int(seq))

    def status(self) -> dict:
        """Counters and the last error: received (messages in), delivered (frames out),
        overwritten (replaced by a newer message before read took them), rejected (malformed)."""
        with self._lock:
            return {"image_topic": self.image_topic, "info_topic": self.info_topic, "transport": self.transport,
                    "received": self.received, "delivered": self.delivered, "overwritten": self.overwritten,
                    "rejected": self.rejected, "camera_info": self._info is not None, "last_error": self.last_error,
                    "node_error": self._node.error}

    @property
    def problem(self) -> Optional[str]:
        """Why frames are not coming, as far as the source knows (the last rejected message or
        the node's failure); None while the newest message was good."""
        return self.last_error if self._newest_bad else self._node.error

    def describe(self) -> str:
        return f"ros2 camera {self._camera.name!r} ({self.image_topic})"

    def _close(self) -> None:
        self._node.close()

    def __repr__(self) -> str:
        return (f"RosDepthSource({self.image_topic!r}, {self.transport}, camera={self._camera.name!r}, "
                f"{self._camera.width}x{self._camera.height})")
