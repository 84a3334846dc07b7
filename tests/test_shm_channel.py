"""The shared-memory channel of the robot process, the grasper and the ROS 2 master bridge
(robot/hosted_block.py ``Channel`` over native/shm_exchange.c): a reader keeps only whole,
unchanged records, and the checksum is zlib's CRC-32, so a record that holds a NaN still reads
(the reader must see the NaN to fault on it)."""
import math
import zlib

import numpy as np
import pytest

from pointfence.native import lib
from pointfence.service.robot.hosted_block import Block


def _block(n=2, dof=3):
    return Block(None, n, dof)


def test_the_native_crc_is_zlibs_on_random_bytes():
    """Every length and start (the eight-byte folds, their tails, unaligned starts)."""
    rng = np.random.default_rng(7)
    buf = rng.integers(0, 256, 4200, dtype=np.uint8)
    for size in (*range(0, 40), 63, 64, 65, 561, 4096):
        for start in (0, 1, 3, 7):
            a = buf[start:start + size]
            assert lib.pf_crc32(a.ctypes.data, size) == zlib.crc32(a.tobytes()), (size, start)


def test_a_written_record_reads_back_whole_and_its_checksum_is_zlibs():
    blk = _block()
    ch = blk.state
    rec = np.arange(ch.size, dtype=float) * 0.5
    ch.write(rec)
    w = int(ch.meta[2])
    assert ch.meta[w] % 2 == 0 and ch.meta[w] > 0            # even: whole
    assert int(ch.sums[w]) == zlib.crc32(rec.tobytes())
    out = np.zeros(ch.size)
    assert ch.read(out) and np.array_equal(out, rec)
    rec2 = rec + 1.0                                          # the next write goes to the other slot
    ch.write(rec2)
    assert int(ch.meta[2]) == 1 - w
    assert ch.read(out) and np.array_equal(out, rec2)


def test_a_record_with_a_nan_reads_so_that_the_reader_can_fault_on_it():
    ch = _block().state
    rec = np.ones(ch.size)
    rec[3] = math.nan
    ch.write(rec)
    out = np.zeros(ch.size)
    assert ch.read(out) and math.isnan(out[3]) and np.count_nonzero(out == 1.0) == ch.size - 1


def test_a_slot_being_written_or_corrupt_is_not_read():
    ch = _block().state
    ch.write(np.full(ch.size, 2.0))
    w = int(ch.meta[2])
    out = np.zeros(ch.size)
    ch.meta[w] += 1                                           # odd: a writer is in the middle of it
    assert not ch.read(out, tries=3)
    ch.meta[w] += 1
    assert ch.read(out)
    ch.data[w, 5] = 7.0                                       # bytes that do not match the CRC
    out[:] = 0.0
    assert not ch.read(out, tries=3)
    ch.meta[2] = 5                                            # a slot index that is no slot
    assert not ch.read(out, tries=3)


def test_a_record_of_the_wrong_size_or_type_is_refused_before_any_copy():
    ch = _block().state
    with pytest.raises(TypeError, match="contiguous float64"):
        ch.write(np.zeros(ch.size - 1))
    with pytest.raises(TypeError, match="contiguous float64"):
        ch.read(np.zeros(ch.size, np.float32))
    with pytest.raises(TypeError, match="contiguous float64"):
        ch.read(np.zeros((ch.size, 2))[:, 0])
