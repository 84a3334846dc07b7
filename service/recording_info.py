"""What an MCAP recording holds, from one pass over its records (``pointfence inspect``): every
topic with its schema, message count, first and last log time; every metadata record; the
decoded ``pointfence_msgs/Event`` messages (faults, holds with their reasons and invariants,
control changes); and whether the file is whole (it ends in a footer) or torn.

Read record by record (``mcap``'s ``StreamReader``, chunk CRCs checked), as ``mcap_read``
reads, so a file that a crash or ``kill -9`` cut short is scanned up to its last whole chunk
and ``torn`` says where and why it ends.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import Optional

from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from pointfence.kernels.errors import InputError

from .ros2_schemas import EVENTS


class TopicStats:
    """One topic: its schema name, message count, first and last log time (ns, wall clock)."""

    def __init__(self, topic: str, schema: str):
        self.topic, self.schema = topic, schema
        self.count = 0
        self.first_ns: Optional[int] = None
        self.last_ns: Optional[int] = None

    def add(self, log_ns: int) -> None:
        self.count += 1
        self.first_ns = log_ns if self.first_ns is None else min(self.first_ns, log_ns)
        self.last_ns = log_ns if self.last_ns is None else max(self.last_ns, log_ns)

    @property
    def rate_hz(self) -> Optional[float]:
        """Messages per second between the first and the last (None for fewer than two)."""
        if self.count < 2 or self.last_ns == self.first_ns:
            return None
        return (self.count - 1) / ((self.last_ns - self.first_ns) * 1e-9)


class Scan:
    """``topics`` (topic -> ``TopicStats``, in first-seen order), ``metadata`` (name -> values of
    its last record), ``events`` (decoded Event messages as dicts, in file order), ``library``
    and ``profile`` of the writer, ``complete`` (the file ends in its footer) and ``torn``
    (None, or why the file ends early)."""

    def __init__(self, path: Path):
        self.path = path
        self.bytes = path.stat().st_size
        self.topics: dict = {}
        self.metadata: dict = {}
        self.events: list = []
        self.library = self.profile = ""
        self.complete = False
        self.torn: Optional[str] = None

    @property
    def span_ns(self) -> tuple:
        """(first, last) log time of any message (ns), or (None, None) for none."""
        firsts = [s.first_ns for s in self.topics.values() if s.first_ns is not None]
        lasts = [s.last_ns for s in self.topics.values() if s.last_ns is not None]
        return (min(firsts), max(lasts)) if firsts else (None, None)


def scan(path) -> Scan:
    """Scan recording ``path`` (see the module docstring). Raises InputError if it is missing or
    not an MCAP file; a damaged or cut tail is not an error (``Scan.torn``)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"recording {str(p)!r} not found; expected an .mcap file that `pointfence serve --record` or "
                         "`demo --record` wrote")
    out = Scan(p)
    schemas: dict = {}
    channels: dict = {}
    decoders: dict = {}
    with p.open("rb") as fh:
        head = fh.read(8)
        if head != b"\x89MCAP0\r\n":
            raise InputError(f"{p}: not an MCAP file (its first bytes are {head!r}, expected b'\\x89MCAP0\\r\\n')")
        fh.seek(0)
        try:
            for rec in StreamReader(fh, validate_crcs=True, record_size_limit=1 << 30).records:
                if isinstance(rec, Message):
                    st = channels.get(rec.channel_id)
                    if st is not None:
                        st.add(int(rec.log_time))
                        if st.topic == EVENTS:
                            out.events.append(_event(rec, schemas, decoders))
                elif isinstance(rec, Channel):
                    if rec.id not in channels:
                        name = schemas.get(rec.schema_id, (f"schema {rec.schema_id}", b""))[0]
                        st = out.topics.setdefault(rec.topic, TopicStats(rec.topic, name))
                        channels[rec.id] = st
                elif isinstance(rec, Schema):
                    schemas[rec.id] = (rec.name, bytes(rec.data))
                elif isinstance(rec, Metadata):
                    out.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Header):
                    out.library, out.profile = rec.library, rec.profile
                elif isinstance(rec, Footer):
                    out.complete = True
        except (McapError, struct.error, ValueError, EOFError, OSError, Exception) as e:   # noqa: BLE001
            out.torn = f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
    if not out.complete and out.torn is None:
        out.torn = "the file ends without its summary and footer (the recorder did not close it)"
    return out


def _event(rec, schemas: dict, decoders: dict) -> dict:
    """A ``pointfence_msgs/Event`` message as a dict (its schema is the file's own)."""
    from mcap_ros2._dynamic import generate_dynamic

    dec = decoders.get("event")
    if dec is None:
        name, text = next(((n, d) for n, d in schemas.values() if n == "pointfence_msgs/Event"),
                          ("pointfence_msgs/Event", b""))
        if not text:
            from .ros2_schemas import msgdef

            text = msgdef(name).encode()
        dec = decoders["event"] = generate_dynamic(name, text.decode())[name]
    m = dec(bytes(rec.data))
    return {"log_ns": int(rec.log_time), "tick": int(m.tick), "arm": int(m.arm), "kind": str(m.kind),
            "reason": str(m.reason), "invariant": str(m.invariant), "hold_mask": int(m.hold_mask),
            "detail": str(m.detail)}


__all__ = ["scan", "Scan", "TopicStats"]
