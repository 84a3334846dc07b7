"""Streamed recordings (service/record.py, service/recfile.py): a run killed with SIGKILL keeps all
but its last second on disk, in order and uncorrupted; a torn last chunk is left out cleanly; a
full ring is counted, never silent; a streamed recording replays (S8)."""
from __future__ import annotations

import mmap
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service import recfile, replay
from pointfence.service.clock import FakeClock
from pointfence.service.frames import SimFrames
from pointfence.service.loop import HapticLoop
from pointfence.service.record import TICK_COLUMNS, Recorder, load_recording
from pointfence.service.app import Service

from service_cases import balloon_config, push

#: a live-like run: 1 kHz ticks that fill every part of their row from the tick number k, the
#: latest k in a shared progress word
CHILD = textwrap.dedent("""
    import mmap, sys, time
    import numpy as np
    from pointfence.service.record import Recorder
    path, progress = sys.argv[1], sys.argv[2]
    with open(progress, "r+b") as fh:
        word = np.ndarray((1,), np.int64, buffer=mmap.mmap(fh.fileno(), 8))
    rec = Recorder(4096, 2, path=path)
    rec.describe({"architecture": "III"}, {1: (1, 1)})
    t0, k = time.monotonic(), 0
    while True:
        i = rec.next_row()
        if i >= 0:
            rec.rows[i] = k + np.arange(rec.rows.shape[1]) * 1e-3
            rec.inputs[i] = k
            rec.masters[i] = k + 0.5
            rec.robots[i] = -k
            rec.masters_world[i] = 2 * k
            rec.holds[i] = k % 7
            rec.note_tick_us(12.5)
        word[0] = k
        k += 1
        time.sleep(max(0.0, t0 + k * 1e-3 - time.monotonic()))
""")


def expect_row(got: dict, j: int, k: int) -> None:
    np.testing.assert_array_equal(got["rows"][j, :-1], k + np.arange(len(TICK_COLUMNS) - 1) * 1e-3)
    assert got["rows"][j, -1] == 12.5
    assert (got["inputs"][j] == k).all() and (got["masters"][j] == k + 0.5).all()
    assert (got["robots"][j] == -k).all() and (got["masters_world"][j] == 2 * k).all()
    assert (got["holds"][j] == k % 7).all()


def test_a_run_killed_with_sigkill_keeps_all_but_its_last_second(tmp_path):
    path, progress = tmp_path / "run.pfrec", tmp_path / "progress"
    progress.write_bytes(bytes(8))
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    proc = subprocess.Popen([sys.executable, str(script), str(path), str(progress)])
    with open(progress, "r+b") as fh:
        word = np.ndarray((1,), np.int64, buffer=mmap.mmap(fh.fileno(), 8))
        end = time.monotonic() + 60.0
        while word[0] < 2500:                       # 2.5 s of ticks (a loaded machine: longer)
            assert proc.poll() is None and time.monotonic() < end
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        k_kill = int(word[0])
    got = load_recording(path)
    ks = got["inputs"][:, 0].astype(np.int64)
    assert len(ks) > 0
    np.testing.assert_array_equal(ks, np.arange(len(ks)))        # every tick, in order, from the first
    assert ks[-1] >= k_kill - 1000                                # all but (at most) the last second
    for j in range(len(ks)):                                       # no corrupted row
        expect_row(got, j, int(ks[j]))
    assert got["meta"]["architecture"] == "III" and got["meta"]["snapshot_frames"] == {"1": [1, 1]}
    assert got["meta"]["ticks_lost"] == 0


def _recording(tmp_path, ticks=600, flush_s=0.05):
    path = tmp_path / "r.pfrec"
    rec = Recorder(256, 1, path=path, flush_s=flush_s)
    for k in range(ticks):
        i = rec.next_row()
        while i < 0:                                # (the test writes faster than a tick: wait for room)
            time.sleep(0.001)
            i = rec.next_row()
        rec.rows[i] = k
        rec.inputs[i, 0] = k
        if k % 100 == 99:
            time.sleep(2 * flush_s)                 # several chunks
    rec.close()
    return path, rec


def test_a_torn_or_corrupt_last_chunk_is_left_out_and_the_rest_reads(tmp_path):
    path, rec = _recording(tmp_path)
    whole = load_recording(path)
    assert len(whole["rows"]) == 600 == rec.ticks_recorded and whole["torn_bytes"] == 0
    data = path.read_bytes()
    # the last rows chunk: cut it in the middle (a write torn by the crash)
    starts = [i for i in range(len(data)) if data.startswith(b"PFCK", i)]
    last_rows = max(s for s in starts if data[s + 4] == recfile.ROWS)
    n_last = int.from_bytes(data[last_rows + 13: last_rows + 17], "little")
    path.write_bytes(data[: last_rows + 40])
    torn = load_recording(path)
    assert len(torn["rows"]) == 600 - n_last and torn["torn_bytes"] > 0
    np.testing.assert_array_equal(torn["inputs"][:, 0], np.arange(600 - n_last))
    # a flipped byte in its payload: the checksum leaves it out too
    bad = bytearray(data)
    bad[last_rows + recfile._CHUNK.size + 3] ^= 0xFF
    path.write_bytes(bytes(bad))
    assert len(load_recording(path)["rows"]) == 600 - n_last
    # not a recording at all: a clear error
    path.write_bytes(b"t,xm_x\n")
    with pytest.raises(InputError, match="not a pointfence recording"):
        load_recording(path)


def test_a_full_ring_counts_lost_ticks_and_never_overwrites_unwritten_rows(tmp_path):
    path = tmp_path / "r.pfrec"
    rec = Recorder(8, 1, path=path, flush_s=1.0)      # the writer sleeps for a second: the ring fills
    kept = []
    for k in range(100):
        i = rec.next_row()
        if i >= 0:
            rec.rows[i] = k
            rec.inputs[i, 0] = k
            kept.append(k)
        else:
            assert rec.full
    assert rec.ticks_recorded == len(kept) == 8 and rec.ticks_lost == 92
    rec.close()
    got = load_recording(path)
    np.testing.assert_array_equal(got["inputs"][:, 0], kept)
    assert got["meta"]["ticks_lost"] == 92 and got["meta"]["ticks_recorded"] == 8
    mem = Recorder(4, 1)                              # in memory: full stops the recording, counted too
    assert [mem.next_row() for _ in range(6)] == [0, 1, 2, 3, -1, -1]
    assert mem.full and mem.ticks_lost == 2 and mem.count == 4


def test_recorder_limits_are_checked():
    with pytest.raises(InputError, match="flush_s"):
        Recorder(16, 1, path="/nonexistent/x.pfrec", flush_s=5.0)
    with pytest.raises(InputError, match="capacity"):
        Recorder(1, 1)


def test_a_streamed_recording_replays_the_run(tmp_path):
    # the way a live run streams (the service's recorder replaced by a streamed one), offline
    # on the NumPy reference so that the replay is exact
    cfg = balloon_config(tmp_path, arch="III")
    n_ticks = 900
    svc = Service(cfg, [push(0.10, t_end=0.7, hold=0.2)], backend="numpy", record=0)
    rec = svc.recorder = Recorder(512, 1, path=tmp_path / "run" / "recording.pfrec", flush_s=0.05)
    sources = cfg.open_sources()
    feeder = SimFrames(svc.pipeline, sources, cfg.service.stale_s, cfg.service.max_frame_age_s)
    svc.attach_frames(feeder)
    rec.describe({"architecture": svc.architecture, "backend": "numpy", "device_spec": None,
                  "rate_hz": svc.rate_hz, "cameras": feeder.names}, feeder.snapshot_frames)
    feeder.poll(0.0)
    loop = HapticLoop(svc, FakeClock(), cfg.service.rate_hz, cfg.service.max_lateness_s, switch_interval_s=None)
    for k in range(n_ticks):
        if k == 500:
            svc.set_architecture("I")
        loop.run_ticks(1)
        if k % 200 == 0:
            time.sleep(0.1)                             # (the offline ticks outrun the writer's ring)
    rec.close()
    for s in sources:
        s.close()
    assert rec.ticks_lost == 0 and rec.ticks_recorded == n_ticks
    a = rec.ticks()
    assert len(a) == n_ticks and np.abs(a[:, 16:19]).max() > 0.5     # it was in contact
    svc2, sources2 = replay.replay_recording(cfg, tmp_path / "run")    # the folder: recording.pfrec
    for s in sources2:
        s.close()
    b = svc2.recorder.ticks()
    np.testing.assert_array_equal(a[:, :-1], b[:, :-1])
    assert svc2.architecture == "I"


class _CountingDict(dict):
    """A snapshot -> frames dict that counts the entries read through it."""

    reads = 0

    def items(self):
        for kv in super().items():
            self.reads += 1
            yield kv

    def __reversed__(self):
        for k in super().__reversed__():
            self.reads += 1
            yield k


def test_a_flush_reads_only_the_snapshots_added_since_the_last_one(tmp_path):
    """The writer thread adds each new snapshot's frames to the file's metadata. Its work per
    flush must be the new snapshots', not the run's: a copy of every entry each flush grew with
    the run (about 30 a second) and, by its allocations, made the garbage collector run ever
    longer in the writer thread while it held the interpreter lock (the soak's loop misses grew
    from 0.2 to 9 % over 10 minutes). All snapshots still reach the file."""
    path = tmp_path / "r.pfrec"
    rec = Recorder(256, 1, path=path, flush_s=1.0)
    src = _CountingDict({k: (k, k) for k in range(1, 20001)})
    try:
        rec.describe({"architecture": "III"}, src)
        rec._flush(final=False)
        src[20001], src[20002] = (7, 8), (9, 10)
        src.reads = 0
        rec._flush(final=False)
        assert src.reads <= 3, src.reads            # the two new ones and the one that stops the walk
    finally:
        rec.close()
    meta = recfile.read(path)["meta"]["snapshot_frames"]
    assert len(meta) == 20002 and meta["20002"] == [9, 10] and meta["1"] == [1, 1]


def test_ticks_csv_formats_every_row_as_one_row_at_a_time_did(tmp_path):
    """write_csv formats blocks of rows at once: the text is the same as row by row, across
    block boundaries, with NaN and negative values."""
    rng = np.random.default_rng(3)
    n = 2500
    rec = Recorder(capacity=n, n=1)
    for k in range(n):
        rec.next_row()
    rec.rows[:n] = rng.normal(size=(n, len(TICK_COLUMNS))) * 10.0 ** rng.integers(-9, 3, (n, len(TICK_COLUMNS)))
    rec.rows[:n, 19:21] = rng.integers(-5, 1 << 20, (n, 2))
    rec.rows[7, 3] = np.nan
    rec.write_csv(tmp_path / "ticks.csv")
    fmt = ",".join(["%.6f"] + ["%.9f"] * 18 + ["%d", "%d", "%.1f"]) + "\n"
    want = ",".join(TICK_COLUMNS) + "\n" + "".join(fmt % tuple(r) for r in rec.ticks())
    assert (tmp_path / "ticks.csv").read_text() == want
    assert want.count("\n") == n + 1
