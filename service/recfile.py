"""The streamed recording file (``*.pfrec``): append-only, readable after a crash.

Layout (little-endian)::

    header  MAGIC (8 bytes) | u32 length | JSON (columns, arms, width) | u32 CRC-32 of the JSON
    chunk   b"PFCK" | u8 kind | u64 first tick row | u32 rows | u32 payload bytes | u32 CRC-32 | payload

A ``ROWS`` chunk's payload is ``rows`` records of ``width`` float64 (the recorder's ring rows,
``record.Recorder``); ``first`` is the recorder's running row number of the first one (gaps:
rows lost to a full ring). A ``META`` chunk's payload is a JSON object merged into the
recording's metadata (later chunks win key by key; ``snapshot_frames`` entries accumulate).

Every chunk is self-delimiting and checked, so a file cut anywhere (``kill -9`` in the middle
of a write, a full disk) reads up to its last whole chunk: ``read`` stops at a torn or corrupt
chunk and says how many bytes it left (``torn_bytes``).
"""
from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from pointfence.kernels.errors import InputError

MAGIC = b"PFREC\x001\n"
_CHUNK = struct.Struct("<4sBQIII")
_CHUNK_MAGIC = b"PFCK"
ROWS, META = 0, 1
#: a chunk larger than this is corrupt, not read (a ring of 65,536 rows of 512 floats)
MAX_CHUNK_BYTES = 1 << 28


class RecordingFile:
    """Writes a recording: ``header`` (a JSON-able dict) at once, then ``rows``/``meta`` chunks;
    ``sync()`` flushes and fsyncs. Only one thread writes (the recorder's writer)."""

    def __init__(self, path, header: dict):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = self.path.open("wb")
        head = json.dumps(header).encode()
        self._fh.write(MAGIC + struct.pack("<I", len(head)) + head + struct.pack("<I", zlib.crc32(head)))
        self.sync()

    def rows(self, first: int, block: np.ndarray) -> None:
        """Append ``block`` (rows, width) float64 whose first row is running row ``first``."""
        payload = np.ascontiguousarray(block, dtype="<f8")
        self._chunk(ROWS, first, len(payload), payload.tobytes())

    def meta(self, d: dict) -> None:
        self._chunk(META, 0, 0, json.dumps(d).encode())

    def _chunk(self, kind: int, first: int, n: int, payload: bytes) -> None:
        self._fh.write(_CHUNK.pack(_CHUNK_MAGIC, kind, first, n, len(payload), zlib.crc32(payload)) + payload)

    def flush(self) -> None:
        self._fh.flush()

    def sync(self) -> None:
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self) -> None:
        if not self._fh.closed:
            self.sync()
            self._fh.close()


def read(path) -> dict:
    """A recording file as ``{"header", "meta", "first" (running row numbers, int64),
    "rows" (N, width) float64, "torn_bytes"}``; stops cleanly at a torn or corrupt last chunk.
    Raises InputError if the file is not a recording (or its header is damaged)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"recording {str(p)!r} not found; expected a .pfrec file a recorded run wrote")
    data = p.read_bytes()
    if data[: len(MAGIC)] != MAGIC:
        raise InputError(f"{p}: not a pointfence recording (its first bytes are {data[:8]!r}, expected {MAGIC!r})")
    off = len(MAGIC)
    try:
        (hl,) = struct.unpack_from("<I", data, off)
        head = data[off + 4: off + 4 + hl]
        (crc,) = struct.unpack_from("<I", data, off + 4 + hl)
    except struct.error:
        raise InputError(f"{p}: the recording's header is cut short ({len(data)} bytes); the run ended before "
                         "its first write") from None
    if len(head) != hl or zlib.crc32(head) != crc:
        raise InputError(f"{p}: the recording's header is damaged (checksum mismatch)")
    header = json.loads(head)
    width = int(header["width"])
    off += 8 + hl
    meta: dict = {}
    frames: dict = {}
    firsts, blocks = [], []
    while off + _CHUNK.size <= len(data):
        magic, kind, first, n, size, crc = _CHUNK.unpack_from(data, off)
        body = off + _CHUNK.size
        if (magic != _CHUNK_MAGIC or size > MAX_CHUNK_BYTES or body + size > len(data)
                or zlib.crc32(data[body: body + size]) != crc):
            break
        payload = data[body: body + size]
        if kind == ROWS:
            if size != n * width * 8:
                break
            blocks.append(np.frombuffer(payload, "<f8").reshape(n, width))
            firsts.append(np.arange(first, first + n, dtype=np.int64))
        elif kind == META:
            d = json.loads(payload)
            frames.update(d.pop("snapshot_frames", {}))
            meta.update(d)
        off = body + size
    meta["snapshot_frames"] = frames
    rows = np.concatenate(blocks) if blocks else np.zeros((0, width))
    first = np.concatenate(firsts) if firsts else np.zeros(0, np.int64)
    return {"header": header, "meta": meta, "first": first, "rows": rows, "torn_bytes": len(data) - off}
