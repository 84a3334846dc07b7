"""Malformed PCD and PCLZF headers: every declared size is checked against the file's size and
hard caps before anything is allocated, and the error is an InputError naming the file, the
field and the value (SAFETY.md S6)."""
import shutil
import struct
import tracemalloc

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.sources.imagefiles import read_pclzf_depth
from pointfence.service.sources.lzf import lzf_decompress
from pointfence.service.sources.pcd import read_pcd

#: the most a refused file may make the reader allocate (bytes); the files here are < 1 kB
PEAK_LIMIT = 8 << 20


def pcd_bytes(width=4, height=3, data="binary", points=None, fields="x y z", size="4 4 4", type_="F F F",
              count=None, body=None) -> bytes:
    lines = ["# .PCD v0.7", "VERSION 0.7", f"FIELDS {fields}", f"SIZE {size}", f"TYPE {type_}"]
    if count is not None:
        lines.append(f"COUNT {count}")
    lines += [f"WIDTH {width}", f"HEIGHT {height}", "VIEWPOINT 0 0 0 1 0 0 0"]
    if points is not None:
        lines.append(f"POINTS {points}")
    lines.append(f"DATA {data}")
    head = ("\n".join(lines) + "\n").encode()
    if body is None:
        body = np.full((4 * 3, 3), 0.5, "<f4").tobytes()
    return head + body


def pclzf_bytes(width, height, usize=None, csize=None, payload=b"\x00\x00\x00") -> bytes:
    usize = width * height * 2 if usize is None else usize
    csize = len(payload) if csize is None else csize
    return b"PCLZF" + struct.pack("<II", width, height) + b"depth16".ljust(16, b"\0") + struct.pack("<II", csize, usize) + payload


def refused_without_allocating(read, path, *needles):
    """``read(path)`` raises InputError naming the file and each needle, allocating < PEAK_LIMIT."""
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as e:
            read(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    msg = str(e.value)
    assert str(path) in msg, msg
    for n in needles:
        assert n in msg, msg
    assert peak < PEAK_LIMIT, f"{peak / 1e6:.0f} MB allocated before refusing: {msg}"
    return msg


def test_a_well_formed_small_pcd_reads(tmp_path):
    f = tmp_path / "ok.pcd"
    f.write_bytes(pcd_bytes(points=12))
    cloud = read_pcd(f)
    assert cloud.xyz.shape == (3, 4, 3) and np.all(cloud.xyz == 0.5) and cloud.rgb is None


@pytest.mark.parametrize("header, needles", [
    (dict(width=1000000000), ["WIDTH", "1000000000"]),
    (dict(width=1000000000, data="binary_compressed"), ["WIDTH", "1000000000"]),
    (dict(height=1000000000, data="ascii"), ["HEIGHT", "1000000000"]),
    (dict(width=16000, height=16000), ["WIDTH*HEIGHT", "256000000"]),
    (dict(points=13), ["POINTS", "13"]),
    (dict(width=-4), ["WIDTH", "-4"]),
    (dict(width="4x"), ["WIDTH", "'4x'"]),
    (dict(height="nan"), ["HEIGHT", "'nan'"]),
    (dict(count="1 1 100000"), ["COUNT", "100000"]),
    (dict(count="1 1 -1"), ["COUNT", "-1"]),
    (dict(size="4 4"), ["SIZE", "2 values"]),
    (dict(width=400, height=300), ["WIDTH*HEIGHT = 120000", "1440000 bytes", "144"]),   # truncated binary
    (dict(data="ascii", body=b"1 2 3\n" * 11), ["11 data lines", "12"]),                 # truncated ascii
    (dict(data="ascii", body=b"1 2 x\n" * 12), ["ascii data unreadable"]),
])
def test_malformed_pcd_headers_are_refused_before_allocating(tmp_path, header, needles):
    f = tmp_path / "bad.pcd"
    f.write_bytes(pcd_bytes(**header))
    refused_without_allocating(read_pcd, f, *needles)


def test_compressed_pcd_sizes_are_checked_against_the_file(tmp_path):
    n = 640 * 480
    # uncompressed size that matches the header (3.7 MB) but that 8 bytes of LZF cannot give
    f = tmp_path / "huge_usize.pcd"
    f.write_bytes(pcd_bytes(width=640, height=480, data="binary_compressed", body=struct.pack("<II", 8, n * 12) + b"\0" * 8))
    refused_without_allocating(read_pcd, f, "uncompressed size 3686400", "8 compressed bytes")
    # a compressed size beyond the file's end
    f = tmp_path / "huge_csize.pcd"
    f.write_bytes(pcd_bytes(width=640, height=480, data="binary_compressed", body=struct.pack("<II", 1 << 31, n * 12)))
    refused_without_allocating(read_pcd, f, "compressed size", str(1 << 31))
    # an uncompressed size that disagrees with WIDTH*HEIGHT
    f = tmp_path / "mismatch.pcd"
    f.write_bytes(pcd_bytes(data="binary_compressed", body=struct.pack("<II", 8, 4000000000) + b"\0" * 8))
    refused_without_allocating(read_pcd, f, "uncompressed size 4000000000", "12*12")
    # no room for the two sizes
    f = tmp_path / "no_sizes.pcd"
    f.write_bytes(pcd_bytes(data="binary_compressed", body=b"\0\0\0"))
    refused_without_allocating(read_pcd, f, "binary_compressed", "8 bytes")


@pytest.mark.parametrize("width, height, extra, needles", [
    (16384, 16384, {}, ["width*height", "268435456"]),                  # 512 MB declared, 3 bytes given
    (1000000000, 2, {"usize": 4000000000}, ["1000000000"]),            # usize disagrees with the size
    (4096, 4096, {}, ["uncompressed size 33554432", "3 compressed"]),  # 32 MB from 3 bytes
    (640, 480, {"csize": 1 << 30}, ["compressed size", str(1 << 30)]),  # beyond the file's end
    (0, 480, {}, ["width", "= 0"]),
])
def test_malformed_pclzf_headers_are_refused_before_allocating(tmp_path, width, height, extra, needles):
    f = tmp_path / "bad_depth.pclzf"
    f.write_bytes(pclzf_bytes(width, height, **extra))
    refused_without_allocating(read_pclzf_depth, f, *needles)


def test_lzf_refuses_an_output_size_its_input_cannot_give():
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match="cannot come from 3 compressed bytes"):
            lzf_decompress(b"\x00ab", 1 << 31, "block")
        with pytest.raises(InputError, match="-1"):
            lzf_decompress(b"\x00ab", -1, "block")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < PEAK_LIMIT
    assert lzf_decompress(bytes([2]) + b"abc" + bytes([0xE0, 0, 2]), 12) == b"abc" * 4


# -- the real PCL Kinect frames: read whole, refused when truncated -------------------------

def test_real_pcd_and_pclzf_frames_read_and_truncated_copies_are_refused(shared_data, tmp_path):
    seq = shared_data / "pcl_kinect_grabber_seq"
    pcds, zfs = sorted((seq / "pcd").glob("*.pcd")), sorted((seq / "pclzf").glob("*_depth.pclzf"))
    assert len(pcds) == 3 and len(zfs) == 3
    for f in pcds:
        cloud = read_pcd(f)
        assert cloud.xyz.shape == (480, 640, 3) and 0.8 < np.isfinite(cloud.xyz[..., 2]).mean() < 0.95
    for f in zfs:
        d = read_pclzf_depth(f)
        assert d.shape == (480, 640) and 800 < np.median(d[d > 0]) < 1000
    for src, read in ((pcds[0], read_pcd), (zfs[0], read_pclzf_depth)):
        raw = src.read_bytes()
        # where the compressed block ends (PCL pads its PCD files beyond it: cutting there is harmless)
        at = raw.index(b"DATA binary_compressed\n") + 23 + 8 if src.suffix == ".pcd" else 37
        end = at + struct.unpack_from("<I", raw, at - 8)[0]
        assert end <= len(raw)
        for keep in (end - 1, len(raw) // 2, 300, 40):
            cut = tmp_path / f"cut{keep}{src.suffix}"
            cut.write_bytes(raw[:keep])
            refused_without_allocating(read, cut)
        copy = tmp_path / src.name
        shutil.copyfile(src, copy)
        assert np.array_equal(np.nan_to_num(read(copy) if read is read_pclzf_depth else read(copy).xyz),
                              np.nan_to_num(read(src) if read is read_pclzf_depth else read(src).xyz))
