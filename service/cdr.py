"""ROS 2 CDR encoding of fixed-shape messages as NumPy records, and of raw images.

A ROS 2 message whose strings and sequence lengths are the same in every message of a channel
(a ``PoseStamped`` with its ``frame_id``, a ``TickInput`` of B arms) has one byte layout: a
4-byte encapsulation header (little-endian CDR), then each field aligned to its own size,
counted from the end of that header. ``FixedLayout`` builds that layout as a NumPy structured
dtype, constants (string lengths and bytes, sequence lengths) filled in once, so a writer
encodes a whole block of messages with one array assignment per field and decodes them with
``np.frombuffer``: no per-message Python encoder (``mcap_ros2``'s takes about 45 us a message,
1 kHz of ticks would cost a tenth of a core). The tests check every layout against
``mcap_ros2``'s own decoder.
"""
from __future__ import annotations

import struct

import numpy as np

from pointfence.kernels.errors import InputError

#: CDR little-endian encapsulation (representation id 0x0001, options 0)
ENCAPSULATION = b"\x00\x01\x00\x00"
_SIZE = {"f8": 8, "i8": 8, "u4": 4, "i4": 4, "u1": 1, "?": 1}


class FixedLayout:
    """One message's byte layout. Add fields in the message's order: ``header(frame_id)``,
    ``scalar(name, code)``, ``array(name, code, n, sequence=True)``, ``string(text)`` (a constant),
    ``u32(value)`` (a constant); then ``dtype`` and ``blank(n)`` (n records, constants filled)."""

    def __init__(self):
        self._names, self._formats, self._offsets, self._consts = [], [], [], []
        self._off = 0            # offset in the CDR body (after the encapsulation)
        self._pad = 0
        self._const("encapsulation", "S4", ENCAPSULATION, absolute=0)

    def _align(self, size: int) -> None:
        self._off = (self._off + size - 1) // size * size

    def _field(self, name: str, fmt, size: int, align: int) -> None:
        self._align(align)
        self._names.append(name)
        self._formats.append(fmt)
        self._offsets.append(4 + self._off)
        self._off += size

    def _const(self, tag: str, fmt, value, absolute: int) -> None:
        """A constant of the layout (a length, a string's bytes) at byte ``absolute``."""
        name = f"_c{len(self._consts)}_{tag}"
        self._names.append(name)
        self._formats.append(fmt)
        self._offsets.append(absolute)
        self._consts.append((name, value))

    def header(self, frame_id: str) -> "FixedLayout":
        """``std_msgs/Header``: ``stamp_sec`` (int32), ``stamp_nanosec`` (uint32), the frame id."""
        self.scalar("stamp_sec", "i4")
        self.scalar("stamp_nanosec", "u4")
        return self.string(frame_id)

    def scalar(self, name: str, code: str) -> "FixedLayout":
        size = _SIZE[code]
        self._field(name, "<" + code if size > 1 else code, size, size)
        return self

    def array(self, name: str, code: str, n: int, sequence: bool = True) -> "FixedLayout":
        """``n`` elements; ``sequence``: an unbounded ``T[]`` (a uint32 length first), else ``T[n]``."""
        if sequence:
            self.u32(n)
        size = _SIZE[code]
        if n:
            self._field(name, ("<" + code if size > 1 else code, (n,)), size * n, size)
        else:
            self._align(size)
        return self

    def u32(self, value: int) -> "FixedLayout":
        self._align(4)
        self._const("u32", "<u4", int(value), absolute=4 + self._off)
        self._off += 4
        return self

    def string(self, text: str) -> "FixedLayout":
        """A constant ``string``: uint32 length (with the NUL), the bytes, the NUL."""
        raw = text.encode() + b"\x00"
        self.u32(len(raw))
        self._const("str", f"S{len(raw)}", raw, absolute=4 + self._off)
        self._off += len(raw)
        return self

    @property
    def size(self) -> int:
        return 4 + self._off

    @property
    def dtype(self) -> np.dtype:
        return np.dtype({"names": self._names, "formats": self._formats, "offsets": self._offsets,
                         "itemsize": self.size})

    def blank(self, n: int) -> np.ndarray:
        """``n`` zeroed records with every constant in place."""
        rec = np.zeros(n, self.dtype)
        for name, value in self._consts:
            rec[name] = value
        return rec

    def check(self, data: bytes) -> bool:
        """Whether ``data`` is one message of this layout (its size and constants)."""
        if len(data) != self.size:
            return False
        rec = np.frombuffer(data, self.dtype)
        return all(rec[name][0] == value for name, value in self._consts)


def pose_layout(frame_id: str) -> FixedLayout:
    """``geometry_msgs/PoseStamped``: fields ``p`` (3, m) and ``q`` (x, y, z, w)."""
    return FixedLayout().header(frame_id).array("p", "f8", 3, sequence=False).array("q", "f8", 4, sequence=False)


def wrench_layout(frame_id: str) -> FixedLayout:
    """``geometry_msgs/WrenchStamped``: fields ``f`` (3, N) and ``tau`` (3, N m)."""
    return FixedLayout().header(frame_id).array("f", "f8", 3, sequence=False).array("tau", "f8", 3, sequence=False)


def stamp_fields(rec: np.ndarray, ns: np.ndarray) -> None:
    """Header stamps of records ``rec`` from times ``ns`` (int64 ns since the epoch)."""
    rec["stamp_sec"] = ns // 1_000_000_000
    rec["stamp_nanosec"] = ns % 1_000_000_000


#: ``sensor_msgs/Image`` encodings of the arrays ``raw_image`` takes: (dtype, channels) -> encoding
IMAGE_ENCODINGS = {(np.dtype(np.uint16), 1): "16UC1", (np.dtype(np.uint8), 3): "rgb8", (np.dtype(np.uint8), 1): "mono8"}


def raw_image(stamp_ns: int, frame_id: str, img: np.ndarray) -> bytes:
    """A ``sensor_msgs/Image`` message, CDR-encoded (little-endian): ``img`` a C-contiguous uint16
    (H, W) depth image ("16UC1"), uint8 (H, W, 3) RGB ("rgb8") or uint8 (H, W) grey ("mono8"),
    its pixels copied once into the message."""
    channels = img.shape[2] if img.ndim == 3 else 1
    enc = IMAGE_ENCODINGS.get((img.dtype, channels)) if img.ndim in (2, 3) else None
    if enc is None or not img.flags.c_contiguous:
        raise InputError(f"image of {img.dtype} {img.shape} ({'' if img.flags.c_contiguous else 'not '}C-contiguous); "
                         "expected a C-contiguous uint16 (H, W), uint8 (H, W, 3) or uint8 (H, W) array")
    h, w = img.shape[:2]
    head = FixedLayout().header(frame_id).u32(h).u32(w).string(enc).scalar("is_bigendian", "u1") \
        .u32(w * channels * img.itemsize)                 # (little-endian: is_bigendian 0)
    rec = head.blank(1)
    stamp_fields(rec, np.array([stamp_ns], np.int64))
    body = rec.tobytes()
    pad = (-(len(body) - 4)) % 4        # the uint8[] length is a uint32: aligned to 4
    return b"".join((body, b"\x00" * pad, struct.pack("<I", img.nbytes), img.data.cast("B")))


__all__ = ["FixedLayout", "pose_layout", "wrench_layout", "stamp_fields", "raw_image", "IMAGE_ENCODINGS",
           "ENCAPSULATION"]
