"""service/mcap_scan.py: the fast scan reads what mcap's own StreamReader reads, record for record,
on whole, cut and damaged files, and checks the same CRCs."""
from __future__ import annotations

import io

import pytest
from mcap.exceptions import McapError
from mcap.records import Channel, DataEnd, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from pointfence.service.mcap_scan import scan


def _file(compression=CompressionType.ZSTD, crcs: bool = True) -> bytes:
    """Three channels, 3,000 messages of random sizes over several chunks, metadata between them."""
    buf = io.BytesIO()
    w = Writer(buf, chunk_size=16 << 10, compression=compression, enable_data_crcs=crcs)
    w.start("test", "pointfence")
    sid = w.register_schema("s", "ros2msg", b"int32 x")
    chans = [w.register_channel(f"/topic{i}", "cdr", sid) for i in range(3)]
    rng = __import__("random").Random(7)
    for k in range(3000):
        c = chans[k % 3]
        w.add_message(c, log_time=k * 1000, publish_time=k * 1000 + 1, sequence=k * 7 % 65536,
                      data=rng.randbytes(rng.randrange(0, 300)))
        if k % 1000 == 500:
            w.add_metadata(f"meta{k}", {"k": str(k), "text": "x" * (k % 13)})
    w.finish()
    return buf.getvalue()


def _theirs(data: bytes):
    """(records of the data section as tuples, error) from mcap's StreamReader (the summary
    section after DataEnd repeats the channels: the scan stops at DataEnd)."""
    out, err = [], None
    try:
        for r in StreamReader(io.BytesIO(data), validate_crcs=True, record_size_limit=1 << 30).records:
            if isinstance(r, DataEnd):
                break
            if isinstance(r, Channel):
                out.append(("channel", r.id, r.topic))
            elif isinstance(r, Message):
                out.append(("message", r.channel_id, r.sequence, bytes(r.data)))
            elif isinstance(r, Metadata):
                out.append(("metadata", r.name, dict(r.metadata)))
    except Exception as e:   # noqa: BLE001  (what it raises on a cut or damaged file)
        err = e
    return out, err


def _ours(data: bytes, workers: int = 0):
    out, err = [], None
    try:
        for r in scan(io.BytesIO(data), workers=workers):
            if r[0] == "metadata":
                out.append(("metadata", r[1].name, dict(r[1].metadata)))
            elif r[0] == "message":
                out.append(("message", r[1], r[2], bytes(r[3])))
            else:
                out.append(r)
    except (McapError, ValueError) as e:
        err = e
    return out, err


@pytest.mark.parametrize("workers", [1, 3])
@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.LZ4, CompressionType.NONE])
def test_the_scan_reads_every_record_mcaps_reader_reads(compression, workers):
    """(Its chunks, about 30, are decompressed ahead in ``workers`` threads: the records come in
    file order all the same.)"""
    data = _file(compression)
    theirs, err = _theirs(data)
    assert err is None and sum(r[0] == "message" for r in theirs) == 3000
    ours, err = _ours(data, workers)
    assert err is None
    assert ours == theirs


@pytest.mark.parametrize("workers", [1, 3])
def test_a_cut_file_reads_the_same_whole_chunks_then_stops_with_an_error(workers):
    data = _file()
    full, _ = _theirs(data)
    end = data.rindex(b"\x0f\x04" + b"\x00" * 7)            # DataEnd: the scan reads no further
    for cut in range(9, end, max(1, end // 37)):
        theirs, terr = _theirs(data[:cut])
        ours, oerr = _ours(data[:cut], workers)
        assert oerr is not None, f"cut at {cut} of {len(data)}: no error"
        assert ours == theirs, f"cut at {cut}: {len(ours)} records vs mcap's {len(theirs)}"
        assert ours == full[: len(ours)]


@pytest.mark.parametrize("workers", [1, 3])
def test_damaged_bytes_stop_the_scan_at_the_damaged_chunk_as_mcaps_reader_does(workers):
    data = _file()
    full, _ = _theirs(data)
    for at in range(200, len(data) - 200, len(data) // 11):
        bad = bytearray(data)
        bad[at] ^= 0x5A
        theirs, terr = _theirs(bytes(bad))
        ours, oerr = _ours(bytes(bad), workers)
        assert ours == full[: len(ours)], f"byte {at}: the scan yielded a record that is not in the file"
        # where mcap saw the damage, so does the scan: at the same chunk, or (damage in an index
        # record, which the scan skips unread) at the data section's CRC, after the intact records
        if terr is not None:
            assert oerr is not None, f"byte {at}: mcap's reader saw damage ({terr}); the scan did not"
            assert len(ours) >= len(theirs)


def test_a_wrong_data_section_crc_and_a_foreign_file_are_errors():
    data = _file()
    end = data.rindex(b"\x0f\x04" + b"\x00" * 7)            # the DataEnd record: opcode, length 4, CRC
    bad = bytearray(data)
    bad[end + 9] ^= 0xFF
    with pytest.raises(ValueError, match="data section CRC"):
        list(scan(io.BytesIO(bytes(bad))))
    with pytest.raises(McapError, match="not an MCAP file"):
        list(scan(io.BytesIO(b"PK\x03\x04" + data[4:])))
    plain = _file(crcs=False)
    assert _ours(plain) == (_theirs(plain)[0], None)
