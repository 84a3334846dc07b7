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

Processes and threads. rclpy runs in a bridge process of the source's own
(ros2/camera_bridge.py): its callbacks write each image message's bytes, as the middleware
delivered them, into shared memory (ros2/camera_block.py) and wake the source through a pipe;
nothing of ROS runs in the service's process. ``read`` (the camera reader's thread,
``sources/threaded.py``) waits on that pipe without the interpreter lock, then decodes the newest
message in place (``cdr.decode_image``: the pixels a view into the block), converts and checks it
into a new array. A bad message (encoding, size, step, a CameraInfo that disagrees, a damaged
compressedDepth payload, a foreign frame_id) is counted and reported (``last_error``,
``status()``) and skipped: the reader never stops on it, and while only bad messages come the
camera goes stale and the service holds (S2). So does a bridge that dies (``problem`` says so).

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
ROS camera is always live), ``domain_id``, ``max_bytes`` (the largest image message taken;
default: 4 bytes a pixel and 64 kB for the camera given, else 1920 x 1080 x 4; larger ones are
counted and refused), and the camera keys of ``images.CAMERA_KEYS``.
"""
from __future__ import annotations

import importlib.util
import json
import math
import os
import select
import subprocess
import sys
import threading
import time
from collections import OrderedDict
from multiprocessing import shared_memory
from typing import Optional

from pointfence.kernels.camera import Camera
from pointfence.kernels.errors import BackendUnavailable, InputError
from pointfence.kernels.frame import DepthFrame
from pointfence.kernels.yielding import checkpoint

from ..sources.base import LiveSource
from . import cdr, dds, images
from .camera_block import CameraBlock

TRANSPORTS = ("raw", "compressedDepth")
QOS = ("sensor_data", "reliable")
#: delivered frames whose stamp and arrival are kept for ``frame_times``
FRAME_LOG = 256
#: how long the bridge process may take to create its node (rclpy's import included), s
START_TIMEOUT_S = 30.0
#: the largest image message taken when no camera is given: 1920 x 1080, 4 bytes a pixel
DEFAULT_MAX_BYTES = 1920 * 1080 * 4 + 65536


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


class RosDepthSource(LiveSource):
    """Depth frames from ROS 2 topics (see the module docstring)."""

    def __init__(self, target: str, camera: Optional[Camera] = None, *, name: Optional[str] = None,
                 transport: Optional[str] = None, image_topic: Optional[str] = None, info_topic: Optional[str] = None,
                 qos: str = "sensor_data", wait: float = 5.0, timeout: float = 1.0, frame_id: Optional[str] = None,
                 rate_hz: float = 30.0, realtime: bool = True, domain_id: Optional[int] = None,
                 max_bytes: Optional[int] = None, **camera_options):
        del realtime   # always live
        self.target = str(target)
        for key, v in (("wait", wait), ("timeout", timeout)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"ros2 source {target!r}: {key} = {v!r}; expected seconds > 0")
        if qos not in QOS:
            raise InputError(f"ros2 source {target!r}: qos = {qos!r}; expected one of {', '.join(QOS)}")
        if max_bytes is None:
            max_bytes = camera.width * camera.height * 4 + 65536 if camera is not None else DEFAULT_MAX_BYTES
        if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or not 1024 <= max_bytes <= 1 << 30:
            raise InputError(f"ros2 source {target!r}: max_bytes = {max_bytes!r}; expected an integer from 1024 to 2^30 "
                             "(the largest image message, bytes)")
        if importlib.util.find_spec("rclpy") is None:   # (the bridge imports it; this process need not)
            raise BackendUnavailable(f"ros2 source {target!r}: ROS 2 is not available here (no rclpy); {dds.INSTALL_HINT}")
        if domain_id is not None:
            domain_id = dds.check_domain_id(domain_id)
        self.image_topic, self.info_topic, self.transport = resolve_topics(target, transport, image_topic, info_topic)
        self.timeout = float(timeout)
        self.frame_id = frame_id or None
        cam_name = name or (camera.name if camera is not None else "cam0")
        if camera is not None and camera_options:
            raise InputError(f"ros2 source {target!r}: camera option(s) {', '.join(sorted(camera_options))} given with a "
                             f"camera {camera.name!r} from the scene; set them in its [[camera]] entry")
        self._lock = threading.Lock()
        self._taken = 0            # the last image number read
        self._info = None          # the newest CameraInfo (cdr.CameraInfo) and its number
        self._info_seq = 0
        self.delivered = self.overwritten = self.rejected = 0
        self.last_error: Optional[str] = None
        self._newest_bad = False
        self._times: "OrderedDict[int, tuple]" = OrderedDict()
        node_name = "pointfence_camera_" + "".join(c if c.isalnum() else "_" for c in cam_name)
        spec = {"node": node_name, "image_topic": self.image_topic, "info_topic": self.info_topic,
                "transport": self.transport, "qos": qos, "domain_id": domain_id, "capacity": int(max_bytes)}
        self._shm = shared_memory.SharedMemory(create=True, size=CameraBlock.nbytes(int(max_bytes)))
        self.block = CameraBlock(self._shm.buf, int(max_bytes))
        self._rfd, wfd = os.pipe()
        self._proc = None
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "pointfence.service.ros2.camera_bridge", self._shm.name, json.dumps(spec),
                 str(os.getpid()), str(wfd)], stdin=subprocess.DEVNULL, pass_fds=(wfd,))
            os.close(wfd)
            wfd = -1
            self._wait_ready(START_TIMEOUT_S)
            self.from_info = camera is None
            if camera is None:
                info = self._wait_info(float(wait))
                camera = images.camera_from_info(info, cam_name, self._where(self.info_topic), **camera_options)
            super().__init__(camera, rate_hz, realtime=False)
        except BaseException:
            if wfd >= 0:
                os.close(wfd)
            self._stop_bridge()
            raise

    # -- the bridge process ------------------------------------------------------------------
    def _bridge_problem(self) -> Optional[str]:
        """Why the bridge is not serving (failed, ended), or None while it runs."""
        why = self.block.error() if int(self.block.ctl["failed"]) else None
        code = self._proc.poll()
        if code is not None:
            return why or f"the ROS 2 camera bridge process ended (exit code {code})"
        return why

    def _wait_ready(self, timeout: float) -> None:
        end = time.monotonic() + timeout
        while int(self.block.ctl["ready"]) == 0:
            why = self._bridge_problem()
            if why is not None or time.monotonic() > end:
                raise InputError(f"ros2 source {self.target!r}: its ROS 2 bridge process did not start "
                                 f"({why or f'not ready within {timeout:g} s'}); check that ROS 2 is installed "
                                 "(pip install 'pointfence[ros2]') and the DDS environment (ROS_DOMAIN_ID)")
            time.sleep(0.01)

    def _wait_info(self, wait: float):
        end = time.monotonic() + wait
        while time.monotonic() < end:
            info = self._newest_info()
            if info is not None:
                return info
            if self._bridge_problem():
                break
            time.sleep(0.01)
        why = self._bridge_problem()
        why = f" ({why})" if why else ""
        raise InputError(f"ros2 source {self.target!r}: no CameraInfo on {self.info_topic} within {wait:g} s{why}; start the "
                         "camera driver (or `pointfence ros2 camera-node`), check ROS_DOMAIN_ID and the topic names "
                         "(`ros2 topic list`), or give fx, fy, cx, cy, width, height in [[camera]]")

    def _newest_info(self):
        """The newest CameraInfo (``cdr.CameraInfo``), decoded when it changed; None before the
        first. One that cannot be read is an InputError."""
        if int(self.block.ctl["info_seq"]) != self._info_seq:
            got = self.block.read_info()
            if got is not None:
                self._info_seq = got[0]
                try:
                    self._info = cdr.decode_camera_info(got[1])
                except cdr.CdrError as e:
                    self._info = None
                    raise InputError(f"{self._where(self.info_topic)}: {e}") from None
        return self._info

    def _where(self, topic: str) -> str:
        return f"ros2 camera {self.target!r} ({topic})"

    # -- the reader's side -----------------------------------------------------------------
    @property
    def realtime(self) -> bool:
        return True

    def read(self, timeout: Optional[float] = None) -> Optional[DepthFrame]:
        """The newest image as a frame; None when none came within ``timeout`` s (default the
        ``timeout`` option) or the newest was malformed (then ``last_error`` says why)."""
        if self._closed:
            raise InputError(f"RosDepthSource for camera {self._camera.name!r} is closed; open a new source to read again")
        end = time.monotonic() + (self.timeout if timeout is None else max(0.0, float(timeout)))
        while True:
            got = self.block.newest()
            if got is not None and got[0] != self._taken:
                checkpoint()     # decoding is Python: not while a haptic tick is due (kernels/yielding.py)
                return self._take(*got)
            left = end - time.monotonic()
            if left <= 0:
                why = self._bridge_problem()
                if why is not None:
                    self.last_error = f"{self._where(self.image_topic)}: {why}"
                return None
            try:   # (waits without the interpreter lock; the bridge writes a byte per image)
                if select.select([self._rfd], [], [], min(left, 0.1))[0]:
                    os.read(self._rfd, 4096)
            except (OSError, ValueError):   # closed under the reader
                return None

    def _take(self, c: int, raw, arrival: float) -> Optional[DepthFrame]:
        with self._lock:
            if self._taken and c > self._taken + 1:
                self.overwritten += c - self._taken - 1
            self._taken = c
        try:
            frame = self._frame_of(raw, c)
        except InputError as e:
            with self._lock:
                if not self.block.intact(c):   # read while the bridge rewrote it: not the message's fault
                    self.overwritten += 1
                    return None
                self.rejected += 1
                self.last_error = str(e)
                self._newest_bad = True
            return None
        if frame is None:   # the bridge came round to this slot while it was read
            with self._lock:
                self.overwritten += 1
            return None
        with self._lock:
            self._newest_bad = False
            self.delivered += 1
            self._times[frame.seq] = (frame.timestamp, arrival)
            while len(self._times) > FRAME_LOG:
                self._times.popitem(last=False)
        return frame

    def _frame_of(self, raw, c: int) -> Optional[DepthFrame]:
        """Image ``c`` (``raw``: its bytes in the block) as a frame; None when its slot was
        rewritten while it was read."""
        where = self._where(self.image_topic)
        cam = self._camera
        try:
            msg = cdr.decode_compressed_image(raw) if self.transport == "compressedDepth" else cdr.decode_image(raw)
        except cdr.CdrError as e:
            raise InputError(f"{where}: {e}") from None
        info = self._newest_info()
        if info is None:
            raise InputError(f"{where}: an image came but no CameraInfo on {self.info_topic} yet; the driver must publish both")
        images.check_info_matches(info, cam, self.from_info, self._where(self.info_topic))
        images.frame_id_check(str(msg.header.frame_id), str(info.header.frame_id), self.frame_id, where)
        if self.transport == "compressedDepth":
            depth = images.depth_from_compressed(msg, cam, where)
        else:
            depth = images.depth_from_image(msg, cam, where)
        stamp = images.stamp_seconds(msg.header.stamp)
        if not self.block.intact(c):
            return None
        seq = self._seq
        self._seq += 1
        return DepthFrame(cam.name, depth, stamp, seq)

    def frame_times(self, seq: int) -> Optional[tuple]:
        """(header.stamp, arrival on ``time.time()``) in s of delivered frame ``seq`` (the last
        ``FRAME_LOG`` frames), or None."""
        with self._lock:
            return self._times.get(int(seq))

    def status(self) -> dict:
        """Counters and the last error: received (image messages in), delivered (frames out),
        overwritten (replaced by a newer message before read took them), rejected (malformed, or
        larger than ``max_bytes``); the bridge process's pid and problem (None while it runs)."""
        ctl = self.block.ctl
        with self._lock:
            return {"image_topic": self.image_topic, "info_topic": self.info_topic, "transport": self.transport,
                    "received": int(ctl["received"]), "delivered": self.delivered, "overwritten": self.overwritten,
                    "rejected": self.rejected + int(ctl["oversize"]), "camera_info": int(ctl["info_seq"]) > 0,
                    "last_error": self.last_error or (self.block.error() if int(ctl["oversize"]) else None),
                    "bridge_pid": self._proc.pid,
                    "node_error": self._bridge_problem()}

    @property
    def problem(self) -> Optional[str]:
        """Why frames are not coming, as far as the source knows (the last rejected message or
        the bridge's failure); None while the newest message was good."""
        return self.last_error if self._newest_bad else self._bridge_problem()

    def describe(self) -> str:
        return f"ros2 camera {self._camera.name!r} ({self.image_topic})"

    def _stop_bridge(self) -> None:
        if self._shm is None:
            return
        proc = self._proc
        if proc is not None and proc.poll() is None:
            self.block.ctl["stop"] = 1
            try:
                proc.wait(timeout=3.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if self._rfd >= 0:
            os.close(self._rfd)
            self._rfd = -1
        self.block.detach()
        shm, self._shm = self._shm, None
        try:
            shm.close()
        except BufferError:   # a view still alive (a reader mid-read): the mapping goes when it does
            pass
        shm.unlink()

    def _close(self) -> None:
        self._stop_bridge()

    def __repr__(self) -> str:
        return (f"RosDepthSource({self.image_topic!r}, {self.transport}, camera={self._camera.name!r}, "
                f"{self._camera.width}x{self._camera.height})")
