"""Messages in their serialized form: CDR encode and decode of the 1 kHz ``geometry_msgs/PoseStamped``,
``geometry_msgs/WrenchStamped`` and ``sensor_msgs/JointState``, and decode of the camera's
``sensor_msgs/Image``, ``CompressedImage`` and ``CameraInfo``, with ``struct``, for rclpy's raw
subscriptions (``create_subscription(..., raw=True)``: the callback gets the message's bytes) and
raw publishing (``Publisher.publish(bytes)``).

Why: rclpy turns every typed message into Python objects (a ``PoseStamped`` is seven of them, each
field set through a checking property) and back; at 1 kHz per stream that conversion was most of
the CPU time of the bridges (the CRTK arm's in the robot process, the master bridge) on a 2-core
machine. Reading the 100-odd bytes of a pose with one ``struct`` call does the same work in a
few microseconds.

The format is ROS 2's (rmw_fastrtps, rmw_cyclonedds): a 4-byte encapsulation header (``00 01 00
00``: plain CDR, little-endian; ``00 00``: big-endian), then the fields in order, each primitive
aligned to its size from the end of the header; strings are a uint32 length counting a closing
NUL, then the bytes and the NUL; sequences a uint32 count, then the elements (aligned once, where
there is one). ``tests/test_ros2_cdr.py`` checks every codec against rclpy's own
``serialize_message`` / ``deserialize_message``, big-endian input and damaged bytes included.

Decoders raise ``CdrError`` (a ``ValueError``) naming what was wrong; a message that cannot be
read is the caller's to count and refuse, as a bad value would be.
"""
from __future__ import annotations

import struct
from typing import NamedTuple

#: the encapsulation headers: plain CDR little- and big-endian
CDR_LE, CDR_BE = b"\x00\x01\x00\x00", b"\x00\x00\x00\x00"
#: the longest string a decoder accepts (frame ids, joint names), bytes
MAX_STRING = 1024
#: the most elements of a JointState sequence a decoder accepts
MAX_JOINTS = 256

_U32 = {"<": struct.Struct("<I"), ">": struct.Struct(">I")}
_HDR = {"<": struct.Struct("<iII"), ">": struct.Struct(">iII")}     # sec, nanosec, len(frame_id) + 1
_D7 = {"<": struct.Struct("<7d"), ">": struct.Struct(">7d")}
_D6 = {"<": struct.Struct("<6d"), ">": struct.Struct(">6d")}
_STAMP = struct.Struct("<iI")
_NS = 1_000_000_000


class CdrError(ValueError):
    """Bytes that are no message of the expected type."""


def _order(buf, what: str) -> str:
    head = bytes(buf[:4])
    if len(head) < 4 or head[0] != 0 or head[1] not in (0, 1):
        raise CdrError(f"{what}: {len(buf)} bytes starting {head.hex()}; expected a CDR encapsulation "
                       "header (00 01 00 00 or 00 00 00 00)")
    return "<" if head[1] == 1 else ">"


def _pad(off: int, n: int) -> int:
    """``off`` (from the start of the buffer) moved up to a multiple of ``n`` from the data's start."""
    return 4 + ((off - 4 + n - 1) & ~(n - 1))


def _header(buf, e: str, what: str) -> tuple:
    """(sec, nanosec, frame_id, offset after the header) of a ``std_msgs/Header`` at offset 4."""
    try:
        sec, nsec, n = _HDR[e].unpack_from(buf, 4)
    except struct.error:
        raise CdrError(f"{what}: {len(buf)} bytes end inside the header") from None
    return sec, nsec, _string(buf, 16, n, what + " frame_id"), 16 + n


def _string(buf, off: int, n: int, what: str) -> str:
    if not 1 <= n <= MAX_STRING or off + n > len(buf) or buf[off + n - 1] != 0:
        raise CdrError(f"{what}: length {n} at byte {off} of {len(buf)}; expected 1 to {MAX_STRING} bytes "
                       "ending in NUL within the message")
    try:
        return bytes(buf[off:off + n - 1]).decode()
    except UnicodeDecodeError as e:
        raise CdrError(f"{what}: not UTF-8 ({e.reason} at byte {off + e.start})") from None


def _fixed(buf, e: str, table: dict, off: int, what: str) -> tuple:
    try:
        return table[e].unpack_from(buf, _pad(off, 8))
    except struct.error:
        raise CdrError(f"{what}: {len(buf)} bytes end inside the message's numbers") from None


def decode_pose_stamped(buf) -> tuple:
    """(stamp ns, frame_id, (x, y, z, qx, qy, qz, qw)) of a serialized ``geometry_msgs/PoseStamped``
    (m, unit quaternion)."""
    e = _order(buf, "PoseStamped")
    sec, nsec, frame, off = _header(buf, e, "PoseStamped")
    return sec * _NS + nsec, frame, _fixed(buf, e, _D7, off, "PoseStamped")


def decode_wrench_stamped(buf) -> tuple:
    """(stamp ns, frame_id, (fx, fy, fz, tx, ty, tz)) of a serialized ``geometry_msgs/WrenchStamped``
    (N, Nm)."""
    e = _order(buf, "WrenchStamped")
    sec, nsec, frame, off = _header(buf, e, "WrenchStamped")
    return sec * _NS + nsec, frame, _fixed(buf, e, _D6, off, "WrenchStamped")


def decode_joint_state(buf) -> tuple:
    """(stamp ns, names, positions, velocities, efforts) of a serialized ``sensor_msgs/JointState``
    (tuples; rad or m, rad/s or m/s, Nm or N)."""
    e = _order(buf, "JointState")
    sec, nsec, _, off = _header(buf, e, "JointState")
    u32 = _U32[e]
    try:
        off = _pad(off, 4)
        (count,) = u32.unpack_from(buf, off)
        _count_ok(count, "JointState name")
        off += 4
        names = []
        for k in range(count):
            off = _pad(off, 4)
            (n,) = u32.unpack_from(buf, off)
            names.append(_string(buf, off + 4, n, f"JointState name[{k}]"))
            off += 4 + n
        arrays = []
        for field in ("position", "velocity", "effort"):
            off = _pad(off, 4)
            (count,) = u32.unpack_from(buf, off)
            _count_ok(count, "JointState " + field)
            off += 4
            if count:
                off = _pad(off, 8)
                arrays.append(struct.unpack_from(f"{e}{count}d", buf, off))
                off += 8 * count
            else:
                arrays.append(())
    except struct.error:
        raise CdrError(f"JointState: {len(buf)} bytes end inside the message") from None
    return (sec * _NS + nsec, tuple(names)) + tuple(arrays)


def _count_ok(count: int, what: str) -> None:
    if count > MAX_JOINTS:
        raise CdrError(f"{what}: {count} elements; at most {MAX_JOINTS} accepted")


class StampedWriter:
    """Serializes one stamped message type with a fixed ``frame_id`` into a buffer allocated once:
    ``encode(stamp_ns, values)`` gives the bytes to publish. ``kind``: "pose" (``PoseStamped``:
    x, y, z, qx, qy, qz, qw) or "wrench" (``WrenchStamped``: fx, fy, fz, tx, ty, tz)."""

    def __init__(self, kind: str, frame_id: str):
        n = {"pose": 7, "wrench": 6}.get(kind)
        if n is None:
            raise ValueError(f"StampedWriter kind {kind!r}; expected 'pose' or 'wrench'")
        self.frame_id = frame_id
        name = frame_id.encode() + b"\x00"
        self._body = _pad(16 + len(name), 8)
        self._buf = bytearray(self._body + 8 * n)
        self._buf[:4] = CDR_LE
        struct.pack_into("<I", self._buf, 12, len(name))
        self._buf[16:16 + len(name)] = name
        self._vals = struct.Struct(f"<{n}d")

    def encode(self, stamp_ns: int, values) -> bytes:
        sec, nsec = divmod(int(stamp_ns), _NS)
        _STAMP.pack_into(self._buf, 4, sec, nsec)
        self._vals.pack_into(self._buf, self._body, *values)
        return bytes(self._buf)


class JointStateWriter:
    """Serializes ``sensor_msgs/JointState`` with fixed joint ``names`` (and so a fixed count) into
    a buffer allocated once: ``encode(stamp_ns, positions, velocities=None, efforts=None)`` (an
    omitted array is sent empty, as ROS drivers do for what they do not measure)."""

    def __init__(self, names, frame_id: str = ""):
        self.names = tuple(names)
        self.n = len(self.names)
        fixed = bytearray(CDR_LE)
        fixed += b"\x00" * 8                         # the stamp, written by encode
        frame = frame_id.encode() + b"\x00"
        fixed += struct.pack("<I", len(frame)) + frame
        fixed += b"\x00" * (_pad(len(fixed), 4) - len(fixed))
        fixed += struct.pack("<I", self.n)
        for name in self.names:
            b = name.encode() + b"\x00"
            fixed += b"\x00" * (_pad(len(fixed), 4) - len(fixed))
            fixed += struct.pack("<I", len(b)) + b
        self._prefix = bytes(fixed)
        self._cache: dict = {}
        self._arr = struct.Struct(f"<{self.n}d")

    def _layout(self, present: tuple) -> tuple:
        """(a zeroed buffer, the offset of each present array's doubles) for the arrays present."""
        got = self._cache.get(present)
        if got is None:
            buf = bytearray(self._prefix)
            offsets = []
            for here in present:
                buf += b"\x00" * (_pad(len(buf), 4) - len(buf))
                count = self.n if here else 0
                buf += struct.pack("<I", count)
                if count:
                    buf += b"\x00" * (_pad(len(buf), 8) - len(buf))
                    buf += b"\x00" * (8 * count)
                if here:
                    offsets.append(len(buf) - 8 * count)
            got = self._cache[present] = (buf, tuple(offsets))
        return got

    def encode(self, stamp_ns: int, positions, velocities=None, efforts=None) -> bytes:
        arrays = (positions, velocities, efforts)
        buf, offsets = self._layout(tuple(a is not None for a in arrays))
        sec, nsec = divmod(int(stamp_ns), _NS)
        _STAMP.pack_into(buf, 4, sec, nsec)
        k = 0
        for a in arrays:
            if a is not None:
                if len(a) != self.n:
                    raise ValueError(f"JointStateWriter: {len(a)} values for {self.n} joints {self.names}")
                self._arr.pack_into(buf, offsets[k], *a)
                k += 1
        return bytes(buf)


class Stamp(NamedTuple):
    sec: int
    nanosec: int


class Header(NamedTuple):
    stamp: Stamp
    frame_id: str


class Image(NamedTuple):
    """A ``sensor_msgs/Image`` read from its bytes; ``data`` a view into them (no copy)."""
    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: memoryview


class CompressedImage(NamedTuple):
    """A ``sensor_msgs/CompressedImage`` read from its bytes; ``data`` a view into them."""
    header: Header
    format: str
    data: memoryview


def _stamped_header(buf, e: str, what: str) -> tuple:
    sec, nsec, frame, off = _header(buf, e, what)
    return Header(Stamp(sec, nsec), frame), off


def _bytes_field(buf, e: str, off: int, what: str) -> tuple:
    """(a view of a uint8[] at ``off``, the offset after it)."""
    off = _pad(off, 4)
    (n,) = _U32[e].unpack_from(buf, off)
    if off + 4 + n > len(buf):
        raise CdrError(f"{what}: {n} bytes of data at byte {off + 4}, but the message ends at byte {len(buf)}")
    return memoryview(buf)[off + 4:off + 4 + n], off + 4 + n


def _size_and_string(buf, e: str, off: int, what: str) -> tuple:
    """(height, width, the string after them, the offset after it): the fields that open an
    Image (encoding) and a CameraInfo (distortion_model), right after the header."""
    off = _pad(off, 4)
    height, width, n = struct.unpack_from(e + "III", buf, off)
    return height, width, _string(buf, off + 12, n, what), off + 12 + n


def decode_image(buf) -> Image:
    """A serialized ``sensor_msgs/Image`` (its pixels a view into ``buf``)."""
    e = _order(buf, "Image")
    header, off = _stamped_header(buf, e, "Image")
    u32 = _U32[e]
    try:
        height, width, encoding, off = _size_and_string(buf, e, off, "Image encoding")
        is_bigendian = buf[off]
        off = _pad(off + 1, 4)
        (step,) = u32.unpack_from(buf, off)
        data, _ = _bytes_field(buf, e, off + 4, "Image")
    except (struct.error, IndexError):
        raise CdrError(f"Image: {len(buf)} bytes end inside the message") from None
    return Image(header, height, width, encoding, is_bigendian, step, data)


def decode_compressed_image(buf) -> CompressedImage:
    """A serialized ``sensor_msgs/CompressedImage`` (its payload a view into ``buf``)."""
    e = _order(buf, "CompressedImage")
    header, off = _stamped_header(buf, e, "CompressedImage")
    try:
        off = _pad(off, 4)
        (n,) = _U32[e].unpack_from(buf, off)
        fmt = _string(buf, off + 4, n, "CompressedImage format")
        data, _ = _bytes_field(buf, e, off + 4 + n, "CompressedImage")
    except struct.error:
        raise CdrError(f"CompressedImage: {len(buf)} bytes end inside the message") from None
    return CompressedImage(header, fmt, data)


class RegionOfInterest(NamedTuple):
    x_offset: int
    y_offset: int
    height: int
    width: int
    do_rectify: bool


class CameraInfo(NamedTuple):
    """A ``sensor_msgs/CameraInfo`` read from its bytes (the fields ``images.py`` reads by name)."""
    header: Header
    height: int
    width: int
    distortion_model: str
    d: tuple
    k: tuple
    r: tuple
    p: tuple
    binning_x: int
    binning_y: int
    roi: RegionOfInterest


#: the most distortion coefficients a CameraInfo decoder accepts (rational_polynomial has 8)
MAX_DISTORTION = 64


def decode_camera_info(buf) -> CameraInfo:
    """A serialized ``sensor_msgs/CameraInfo`` (K, R, P and D as tuples of floats)."""
    e = _order(buf, "CameraInfo")
    header, off = _stamped_header(buf, e, "CameraInfo")
    u32 = _U32[e]
    try:
        height, width, model, off = _size_and_string(buf, e, off, "CameraInfo distortion_model")
        off = _pad(off, 4)
        (count,) = u32.unpack_from(buf, off)
        if count > MAX_DISTORTION:
            raise CdrError(f"CameraInfo d: {count} coefficients; at most {MAX_DISTORTION} accepted")
        off += 4
        d = ()
        if count:
            off = _pad(off, 8)
            d = struct.unpack_from(f"{e}{count}d", buf, off)
            off += 8 * count
        off = _pad(off, 8)
        k = struct.unpack_from(e + "9d", buf, off)
        r = struct.unpack_from(e + "9d", buf, off + 72)
        p = struct.unpack_from(e + "12d", buf, off + 144)
        off += 240
        bx, by, x0, y0, rh, rw = struct.unpack_from(e + "6I", buf, off)
        rect = buf[off + 24]
    except (struct.error, IndexError):
        raise CdrError(f"CameraInfo: {len(buf)} bytes end inside the message") from None
    return CameraInfo(header, height, width, model, d, k, r, p, bx, by, RegionOfInterest(x0, y0, rh, rw, bool(rect)))
