"""The shared-memory block between a ``ros2:`` camera source (ros2/camera_source.py) and its ROS 2
bridge process (ros2/camera_bridge.py).

The bridge's executor thread writes each image message's serialized bytes (CDR, as the
middleware delivered them) into one of ``SLOTS`` slots in turn, and the CameraInfo's bytes into
the info slot whenever they change other than in their stamp; the source's reader thread reads
the newest image in place. Each slot is a sequence lock: the writer makes its ``seq`` odd, writes,
then makes it even (image ``c``: ``2c - 1`` while written, ``2c`` when complete) and only then
publishes ``c`` in ``ctl["latest"]``; a reader that finds the same even ``seq`` before and after
its read has read one whole image. With three slots the writer comes back to the slot being read
only two images later (66 ms at 30 Hz), and a reader that was lapped all the same sees it and
drops that image. Neither side ever waits for the other.

Control words (int64): ``stop`` (source -> bridge), ``pid``, ``ready`` (its node and both
subscriptions exist), ``failed`` (1: the bridge failed, ``text`` says why), ``beat`` (the
bridge's main loop, every 50 ms), ``latest`` (images written so far), ``received`` (image
messages received, written or not), ``oversize`` (images larger than a slot: refused),
``info_seq`` (CameraInfo contents written so far), ``infos`` (CameraInfo messages received).
Arrival times are ``time.time()`` seconds at the bridge's callback (the clock ROS stamps are on
when the publisher runs on this machine).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..robot.hosted_block import TEXT, get_text, put_text

#: image slots (the writer reuses a slot after SLOTS - 1 newer images)
SLOTS = 3
#: the largest CameraInfo message a block holds, bytes (one with 5 coefficients is about 400)
INFO_BYTES = 16384

CONTROL = np.dtype([("stop", "i8"), ("pid", "i8"), ("ready", "i8"), ("failed", "i8"), ("beat", "i8"),
                    ("latest", "i8"), ("received", "i8"), ("oversize", "i8"), ("info_seq", "i8"), ("infos", "i8")])
#: a slot's header: its sequence lock, the message's length in bytes, its arrival (time.time() s)
HEAD = np.dtype([("seq", "i8"), ("nbytes", "i8"), ("arrival", "f8")])


def block_dtype(capacity: int) -> np.dtype:
    """The block for image messages of up to ``capacity`` bytes."""
    return np.dtype([("ctl", CONTROL), ("text", "u1", (TEXT,)), ("info_head", HEAD), ("info", "u1", (INFO_BYTES,)),
                     ("head", HEAD, (SLOTS,)), ("data", "u1", (SLOTS, int(capacity)))])


class CameraBlock:
    """The block over ``buf`` for messages of up to ``capacity`` bytes: ``ctl``, ``text`` (the
    bridge's last error), and the writer's (``write_image``, ``write_info``) and reader's
    (``newest``, ``intact``, ``read_info``) sides."""

    def __init__(self, buf, capacity: int):
        self.capacity = int(capacity)
        rec = np.ndarray((), block_dtype(self.capacity), buffer=buf)
        self.ctl = rec["ctl"]
        self.text = rec["text"]
        self._info_head = rec["info_head"]
        self._info = rec["info"]
        self._head = rec["head"]
        self._data = rec["data"]

    @staticmethod
    def nbytes(capacity: int) -> int:
        return block_dtype(capacity).itemsize

    # -- the bridge's side ---------------------------------------------------------------
    def write_image(self, raw, arrival: float) -> bool:
        """Write image message ``raw`` (bytes) that arrived at ``arrival``; False (counted in
        ``oversize``, ``text`` says so) when it is larger than a slot."""
        ctl = self.ctl
        ctl["received"] += 1
        n = len(raw)
        if n > self.capacity:
            ctl["oversize"] += 1
            put_text(self.text, f"an image message of {n} bytes arrived; the source takes up to {self.capacity} "
                                "(set its max_bytes option higher)")
            return False
        c = int(ctl["latest"]) + 1
        head = self._head[c % SLOTS]
        head["seq"] = 2 * c - 1
        self._data[c % SLOTS, :n] = np.frombuffer(raw, np.uint8)
        head["nbytes"] = n
        head["arrival"] = arrival
        head["seq"] = 2 * c
        ctl["latest"] = c
        return True

    def write_info(self, raw) -> bool:
        """Write CameraInfo message ``raw`` (bytes); False (``text`` says why) when it is larger
        than ``INFO_BYTES``."""
        n = len(raw)
        self.ctl["infos"] += 1
        if n > INFO_BYTES:
            put_text(self.text, f"a CameraInfo message of {n} bytes arrived; at most {INFO_BYTES} are taken")
            return False
        c = int(self.ctl["info_seq"]) + 1
        head = self._info_head
        head["seq"] = 2 * c - 1
        self._info[:n] = np.frombuffer(raw, np.uint8)
        head["nbytes"] = n
        head["seq"] = 2 * c
        self.ctl["info_seq"] = c
        return True

    # -- the source's side ---------------------------------------------------------------
    def newest(self) -> Optional[tuple]:
        """(c, the bytes of image c as a view into the block, its arrival) of the newest image,
        or None when none was written or it is being overwritten. The view is valid only while
        ``intact(c)`` holds after reading it."""
        c = int(self.ctl["latest"])
        if c <= 0:
            return None
        head = self._head[c % SLOTS]
        if int(head["seq"]) != 2 * c:
            return None
        n, arrival = int(head["nbytes"]), float(head["arrival"])
        return c, memoryview(self._data[c % SLOTS, :n]), arrival

    def intact(self, c: int) -> bool:
        """Whether image ``c``'s slot still holds it (read after the bytes were)."""
        return int(self._head[c % SLOTS]["seq"]) == 2 * c

    def read_info(self) -> Optional[tuple]:
        """(its sequence number, a copy of the newest CameraInfo's bytes), or None when none was
        written or it is being rewritten."""
        c = int(self.ctl["info_seq"])
        head = self._info_head
        if c <= 0 or int(head["seq"]) != 2 * c:
            return None
        raw = bytes(self._info[:int(head["nbytes"])])
        return (c, raw) if int(head["seq"]) == 2 * c else None

    def error(self) -> Optional[str]:
        return get_text(self.text)

    def detach(self) -> None:
        """Let go of the shared memory: the control words and the text stay readable as copies,
        the slots are gone (``newest`` and ``read_info`` give None)."""
        self.ctl, self.text = self.ctl.copy(), self.text.copy()
        self.ctl["latest"] = self.ctl["info_seq"] = 0
        self._info_head, self._head = self._info_head.copy(), self._head.copy()
        self._info = self._data = None
