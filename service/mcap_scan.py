"""A fast sequential scan of an MCAP file's data section: what a recording's reader needs.

``scan(fh)`` yields, in file order, ``("channel", id, topic)``, ``("metadata", Metadata)`` and
``("message", channel id, sequence, data)`` for every message, inside chunks or not. It checks
what ``mcap``'s ``StreamReader(validate_crcs=True)`` checks (the magic, each chunk's CRC of its
uncompressed records, the data section's CRC at DataEnd) and stops at DataEnd or the footer.

Why not ``StreamReader`` itself: it builds a Python object for every record and reads each field
through a stream object (about 8 us a message on the 2-core VM), and it parses every MessageIndex
record that follows a chunk. A recording of a 1 kHz run holds 3,000+ messages a second, so
reading a 20 s run took 0.6 s of a replay's 4 s. Here a chunk's records are walked with
``struct.unpack_from`` over the decompressed bytes, and the records a reader never uses
(schemas, indexes, statistics, attachments) are skipped by their length without being parsed.
Chunks are decompressed and CRC-checked ahead in worker threads (a recording's raw depth and
colour images make most of its bytes), while the caller takes the records before them.
The record layouts are MCAP's (https://mcap.dev/spec); records inside a chunk are Schema,
Channel and Message. Anything malformed raises ``McapError`` (or ``ValueError`` for a CRC), at
the first bad record: everything yielded before it stands, as with a torn file's tail (S8).
"""
from __future__ import annotations

import os
import struct
import zlib
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from io import BytesIO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.records import Channel, Metadata

MAGIC = b"\x89MCAP0\r\n"
#: opcodes (MCAP spec)
HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK, METADATA, DATA_END = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0C, 0x0F
_REC = struct.Struct("<BQ")                 # opcode, length
_MSG_IDS = struct.Struct("<HI")             # a message's channel id and sequence (then two u64 times, data)
_CHUNK = struct.Struct("<QQQII")            # start, end, uncompressed size, uncompressed CRC, compression length
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
_MSG_HEAD = 22                              # channel id, sequence, log time, publish time


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame
        return lz4.frame.decompress(data)
    raise McapError(f"chunk compressed with {compression!r}; expected zstd, lz4 or none")


def _message(buf, body: int, end: int) -> tuple:
    """The message record whose content is ``buf[body:end]``."""
    if end - body < _MSG_HEAD:
        raise McapError(f"a message record of {end - body} bytes; expected at least {_MSG_HEAD}")
    ch, seq = _MSG_IDS.unpack_from(buf, body)
    return "message", ch, seq, buf[body + _MSG_HEAD: end]


def _channel(content) -> tuple:
    ch = Channel.read(ReadDataStream(BytesIO(content)))
    return "channel", ch.id, ch.topic


def _inflate(content: bytes) -> bytes:
    """The records of one chunk record's content, decompressed and checked (size and CRC). Runs
    in the scan's worker threads: zstd, lz4 and zlib's CRC hand the interpreter lock over."""
    if len(content) < _CHUNK.size:
        raise McapError(f"a chunk record of {len(content)} bytes; expected at least {_CHUNK.size}")
    _, _, size, crc, nc = _CHUNK.unpack_from(content, 0)
    off = _CHUNK.size
    compression = bytes(content[off: off + nc]).decode()
    off += nc
    (n,) = _U64.unpack_from(content, off)
    off += 8
    if off + n > len(content):
        raise McapError(f"a chunk's records run {off + n - len(content)} bytes past the chunk")
    data = _decompress(compression, bytes(content[off: off + n]), size)
    if len(data) != size:
        raise McapError(f"a chunk decompressed to {len(data)} bytes; its header says {size}")
    if crc != 0 and zlib.crc32(data) != crc:
        raise ValueError(f"chunk CRC mismatch: expected {crc}, calculated {zlib.crc32(data)}")
    return data


def _chunk_records(data: bytes):
    """The records of a chunk's decompressed ``data``: channels and messages (schemas skipped)."""
    off, end, unpack = 0, len(data), _REC.unpack_from
    while off < end:
        if off + 9 > end:
            raise McapError("a record header runs past the end of its chunk")
        op, length = unpack(data, off)
        body = off + 9
        nxt = body + length
        if nxt > end:
            raise McapError(f"a record of {length} bytes runs past the end of its chunk")
        if op == MESSAGE:
            yield _message(data, body, nxt)
        elif op == CHANNEL:
            yield _channel(data[body: nxt])
        off = nxt


def _records(fh, record_size_limit: int):
    """The file's records in order: ("chunk", its content) or a record as ``scan`` yields it;
    ends at DataEnd (its CRC checked) or the footer."""
    head = fh.read(8)
    if head != MAGIC:
        raise McapError(f"not an MCAP file (its first bytes are {head!r})")
    crc = zlib.crc32(head)
    while True:
        rh = fh.read(9)
        if len(rh) < 9:
            raise McapError("the file ends inside a record header (no footer: cut short)")
        op, length = _REC.unpack(rh)
        if length > record_size_limit:
            raise McapError(f"a record of {length} bytes (opcode {op:#x}), over the limit of {record_size_limit}")
        content = fh.read(length)
        if len(content) < length:
            raise McapError(f"the file ends {length - len(content)} bytes into a record of {length} (cut short)")
        if op == DATA_END:
            if length >= 4:
                (want,) = _U32.unpack_from(content, 0)
                if want != 0 and want != crc:
                    raise ValueError(f"data section CRC mismatch: expected {want}, calculated {crc}")
            return
        if op == FOOTER:
            return
        crc = zlib.crc32(content, zlib.crc32(rh, crc))
        if op == CHUNK:
            yield "chunk", content
        elif op == MESSAGE:
            yield _message(content, 0, length)
        elif op == CHANNEL:
            yield _channel(content)
        elif op == METADATA:
            yield "metadata", Metadata.read(ReadDataStream(BytesIO(content)))


def scan(fh, record_size_limit: int = 1 << 30, workers: int = 0):
    """The records of the MCAP file open as ``fh`` (binary, at its start); see the module
    docstring. Chunks are decompressed and checked ahead, ``workers`` threads at a time (0: one
    a core, at most 4) while the caller takes the records before them; the order, and where an
    error is raised, are a sequential scan's."""
    workers = workers or max(1, min(4, os.cpu_count() or 1))
    pending: deque = deque()          # in file order: a chunk's Future, or a record
    records, error = _records(fh, record_size_limit), None
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="pf-mcap-scan") as pool:
        try:
            while True:
                try:
                    rec = next(records)
                except StopIteration:
                    break
                except Exception as e:     # the file's own fault: every record before it stands
                    error = e
                    break
                pending.append(pool.submit(_inflate, rec[1]) if rec[0] == "chunk" else rec)
                while pending and (len(pending) > 2 * workers or not isinstance(pending[0], Future)):
                    yield from _take(pending.popleft())
            while pending:
                yield from _take(pending.popleft())
        finally:                           # (a reader that stops early leaves no work queued)
            for f in pending:
                if isinstance(f, Future):
                    f.cancel()
    if error is not None:
        raise error


def _take(item):
    if isinstance(item, Future):
        yield from _chunk_records(item.result())
    else:
        yield item


__all__ = ["scan"]
