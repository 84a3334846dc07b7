"""The shared memory between the service and its MCAP writer process (``mcap_record`` writes,
``mcap_writer`` reads): two files in ``/dev/shm`` (the temporary folder where there is none),
each mapped by both processes; the writer unlinks them once it has mapped them, so nothing is
left behind when both processes end (the service unlinks them too at ``close``, for a writer
that never started).

``TickBlock``: a header of int64 counters and the tick ring (``capacity`` float64 rows of
``tick_cdr.TickLayout.width``). The tick writes row j, then sets ``written`` = j + 1; the
writer reads the rows below ``written``, then sets ``flushed``; the tick reuses a row only below
``flushed``. Each side writes only its own counters, so no lock: on x86-64 (the service's
hosts, as for ``robot/hosted_block.py``) stores are seen in program order.

``JointBlock``: the robots' measured joints beside the tick ring, row for row (``capacity``
rows of ``arms`` x ``dof`` float64; made when the robots are known, ``McapRecorder.note_start``).
The tick fills row j before it sets ``written`` = j + 1, on the ticks whose joints are recorded;
the writer reads it with the tick row.

``FrameBlock``: a ring of ``slots`` snapshot entries, made when the cameras are known
(``McapRecorder.attach``). Entry i holds the snapshot's numbers (``ENTRY`` float64 per
camera, below) and, per camera, room for a new depth (uint16 H x W), colour (uint8 H x W x 3)
and mask (uint8 H x W) image. The ingest side fills entry ``written % slots`` and then sets
``written``; the writer encodes entries below ``written`` and sets ``consumed``.
"""
from __future__ import annotations

import mmap
import os
import tempfile

import numpy as np

# header counters (int64): the service's side, then the writer's
WRITTEN, FLUSHED, SNAPS_WRITTEN, SNAPS_CONSUMED, FRAMES_RECORDED, SNAPSHOTS_RECORDED, BEAT = range(7)
# the writer's timing counters (int64 us, cumulative): encoding ticks, encoding frames, chunk
# writes and fsync, the longest flush, and the writer's CPU time
US_TICKS, US_FRAMES, US_SYNC, US_FLUSH_MAX, US_CPU = range(7, 12)
#: the writer's: the last ``sync`` request it has carried out (``McapRecorder.seal``: every tick
#: and frame handed over before it is in whole chunks on disk)
SYNCED = 12
#: the service's: control messages sent to the writer so far (``McapRecorder._send``, counted
#: after each): the writer carries out every message counted before it reads a tick row, so
#: what was sent before a tick (the joint block, the frame block, the epoch) applies to it
SENT = 13
HEADER = 16
#: per camera in a snapshot entry: new (1: an image in this entry), frame seq, recorded index,
#: capture stamp (s), clock - stamp (s, NaN: none), colour (0/1), mask (0/1), 16 pose numbers (NaN: the camera's)
ENTRY = 23
NEW, FSEQ, INDEX, STAMP, CMS, COLOR, MASK, POSE = 0, 1, 2, 3, 4, 5, 6, 7


def shm_dir() -> str:
    return "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()


def create(nbytes: int, prefix: str) -> tuple:
    """A new zeroed file of ``nbytes`` in ``shm_dir()`` and its mapping: (path, mmap)."""
    fd, path = tempfile.mkstemp(prefix=prefix, dir=shm_dir())
    try:
        os.ftruncate(fd, nbytes)
        return path, mmap.mmap(fd, nbytes)
    finally:
        os.close(fd)


def attach(path: str, unlink: bool = True) -> mmap.mmap:
    """Map the file ``path`` that ``create`` made (and unlink it: the mapping keeps it)."""
    fd = os.open(path, os.O_RDWR)
    try:
        return mmap.mmap(fd, os.fstat(fd).st_size)
    finally:
        os.close(fd)
        if unlink:
            try:
                os.unlink(path)
            except FileNotFoundError:
                pass


class TickBlock:
    """Views of a tick block's mapping ``buf``: ``header`` (int64, ``HEADER``) and ``rows``
    (``capacity`` x ``width`` float64)."""

    def __init__(self, buf, capacity: int, width: int):
        self.buf, self.capacity, self.width = buf, int(capacity), int(width)
        self.header = np.frombuffer(buf, np.int64, HEADER)
        self.rows = np.frombuffer(buf, np.float64, self.capacity * self.width, 8 * HEADER).reshape(self.capacity,
                                                                                                     self.width)

    @staticmethod
    def nbytes(capacity: int, width: int) -> int:
        return 8 * HEADER + 8 * int(capacity) * int(width)


class JointBlock:
    """Views of a joint block's mapping ``buf``: ``rows`` (``capacity`` x ``arms`` x ``dof``
    float64; joint positions, rad or m)."""

    def __init__(self, buf, capacity: int, arms: int, dof: int):
        self.buf, self.capacity, self.arms, self.dof = buf, int(capacity), int(arms), int(dof)
        self.rows = np.frombuffer(buf, np.float64, self.capacity * self.arms * self.dof).reshape(
            self.capacity, self.arms, self.dof)

    @staticmethod
    def nbytes(capacity: int, arms: int, dof: int) -> int:
        return 8 * int(capacity) * int(arms) * max(1, int(dof))


class FrameBlock:
    """Views of a frame block's mapping ``buf`` for cameras of ``shapes`` [(height, width)] and
    ``slots`` entries: ``meta[slot]`` (float64: the snapshot seq, then ``ENTRY`` per camera) and
    ``depth[slot][cam]``, ``color[slot][cam]``, ``mask[slot][cam]``."""

    def __init__(self, buf, shapes, slots: int):
        self.buf, self.shapes, self.slots = buf, [tuple(s) for s in shapes], int(slots)
        ncam = len(self.shapes)
        width = 1 + ENTRY * ncam
        self.meta = np.frombuffer(buf, np.float64, self.slots * width).reshape(self.slots, width)
        off = 8 * self.slots * width
        self.depth, self.color, self.mask = [], [], []
        for _ in range(self.slots):
            d, c, m = [], [], []
            for h, w in self.shapes:
                d.append(np.frombuffer(buf, np.uint16, h * w, off).reshape(h, w))
                off += 2 * h * w
                c.append(np.frombuffer(buf, np.uint8, h * w * 3, off).reshape(h, w, 3))
                off += 3 * h * w
                m.append(np.frombuffer(buf, np.uint8, h * w, off).reshape(h, w))
                off += h * w
                off = (off + 7) // 8 * 8
            self.depth.append(d)
            self.color.append(c)
            self.mask.append(m)

    @staticmethod
    def nbytes(shapes, slots: int) -> int:
        per = sum((6 * h * w + 7) // 8 * 8 for h, w in shapes)
        return 8 * int(slots) * (1 + ENTRY * len(shapes)) + int(slots) * per

    def cam_meta(self, slot: int, cam: int) -> np.ndarray:
        """The ``ENTRY`` numbers of camera ``cam`` in entry ``slot`` (a view)."""
        return self.meta[slot, 1 + ENTRY * cam: 1 + ENTRY * (cam + 1)]


__all__ = ["TickBlock", "JointBlock", "FrameBlock", "SYNCED", "SENT", "create", "attach", "shm_dir", "HEADER", "ENTRY", "WRITTEN", "FLUSHED",
           "SNAPS_WRITTEN", "SNAPS_CONSUMED", "FRAMES_RECORDED", "SNAPSHOTS_RECORDED", "BEAT", "US_TICKS",
           "US_FRAMES", "US_SYNC", "US_FLUSH_MAX", "US_CPU"]
