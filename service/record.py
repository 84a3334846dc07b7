"""Recording a run tick by tick into preallocated arrays, and writing/reading it.

A live run streams its recording to a ``.pfrec`` file while it goes on (``Recorder(path=...)``:
a ring the tick fills, a writer thread that appends whole checked chunks and fsyncs every
0.25 s), so that a crash or ``kill -9`` keeps all but the last fraction of a second (S8);
``load_recording`` reads one back, up to its last whole chunk. Each tick's row also holds the
hold reasons (``holds``: the service's hold mask, then every arm's).

Outputs (arm 0, world frame) go to ``ticks.csv`` with exactly the columns ``TICK_COLUMNS``.
Inputs (every master's sample, the tick's dt and health flags, the control state, which
snapshot each tick saw and which camera frames built it) go to ``inputs.npz`` so that
``pointfence replay --recording DIR`` re-runs the same ticks exactly.
"""
from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from . import recfile

TICK_COLUMNS = ("t", "xm_x", "xm_y", "xm_z", "hip_x", "hip_y", "hip_z", "proxy_x", "proxy_y", "proxy_z",
                "xr_cmd_x", "xr_cmd_y", "xr_cmd_z", "xr_x", "xr_y", "xr_z", "f_x", "f_y", "f_z",
                "state", "frame_seq", "tick_us")
C = {name: i for i, name in enumerate(TICK_COLUMNS)}
#: per-tick inputs: k, dt, overrun, frame_age, architecture, haptics_on, teleop_on, and the tick's
#: time on the frames' clock (nan: unknown; motion prediction and the tool pose ring use it)
INPUT_COLUMNS = ("k", "dt", "overrun", "frame_age", "arch", "haptics_on", "teleop_on", "frame_time")


#: columns of the per-tick hold reasons: the service's hold mask, then each arm's (app.REASONS bits)
HOLD_COLUMNS = ("hold_mask",)
#: ring rows of a streamed recording (4 s at 1 kHz: the writer may fall that far behind)
STREAM_RING = 4096


def _layout(n: int) -> tuple:
    """(width, {part: (first column, shape of one tick's part)}) of one ring row for ``n`` arms:
    the tick columns, the inputs, every master's sample, every arm's X_r and X_r*, every master in
    the world frame, the hold masks. The recorder's arrays and the file reader both use it."""
    parts = (("rows", (len(TICK_COLUMNS),)), ("inputs", (len(INPUT_COLUMNS),)), ("masters", (n, 5)),
             ("robots", (n, 6)), ("masters_world", (n, 3)), ("holds", (1 + n,)))
    out, c = {}, 0
    for name, shape in parts:
        out[name] = (c, shape)
        c += int(np.prod(shape))
    return c, out


def _views(data: np.ndarray, n: int) -> dict:
    """The named parts of ring rows ``data`` (N, width), as views."""
    _, parts = _layout(n)
    views = {}
    for name, (c, shape) in parts.items():
        k = int(np.prod(shape))
        v = data[:, c: c + k].reshape((len(data),) + shape)
        assert np.shares_memory(v, data)
        views[name] = v
    return views


class Recorder:
    """Per-tick recording: each tick's ``TickInput`` and ``TickOutput`` go into a row of
    preallocated arrays (``write``; its parts: ``rows[i]``, ``inputs[i]``, ``masters[i]``,
    ``robots[i]``, ``masters_world[i]``, ``holds[i]``); nothing is allocated and no I/O happens
    in the tick.

    In memory (``path`` None): room for ``capacity`` ticks of ``n`` arms; ``full`` once it is
    exhausted (recording stops, the loop does not; later ticks count in ``ticks_lost``).

    Streamed (``path``: a ``.pfrec`` file, service/recfile.py): the arrays are a ring of
    ``capacity`` rows (default ``STREAM_RING``) that a writer thread empties into the file every
    ``flush_s`` seconds (append, flush and fsync), so that a crash or ``kill -9`` loses at most
    the last ``flush_s`` of ticks plus the one in progress. A tick that finds the ring full (the
    writer behind) is not recorded and counts in ``ticks_lost``; ``full`` is then True for that
    tick only. ``count`` is one past the ring row of the latest tick (so ``rows[count - 1]`` is
    it, in both modes). ``describe(meta, snapshot_frames)`` adds what a replay needs;
    ``close()`` writes the rest and ends the writer. ``ticks_recorded``: ticks written (or
    kept, in memory)."""

    def __init__(self, capacity: int = STREAM_RING, n: int = 1, path=None, flush_s: float = 0.25):
        self.capacity = int(capacity)
        self.n = int(n)
        if self.capacity < 2 or self.n < 1:
            raise InputError(f"Recorder: capacity {capacity!r}, arms {n!r}; expected >= 2 rows and >= 1 arm")
        if not 0 < flush_s <= 1.0:
            raise InputError(f"Recorder: flush_s = {flush_s!r}; expected 0 < flush_s <= 1 s (S8: at most the "
                             "last second may be lost)")
        self.width, _ = _layout(self.n)
        self.data = np.zeros((self.capacity, self.width))
        v = _views(self.data, self.n)
        self.rows, self.inputs, self.masters = v["rows"], v["inputs"], v["masters"]
        self.robots, self.masters_world, self.holds = v["robots"], v["masters_world"], v["holds"]
        self.count = 0
        self.full = False
        self.ticks_recorded = 0
        self.ticks_lost = 0
        self.path = None if path is None else Path(path)
        self.flush_s = float(flush_s)
        self.write_error: Optional[str] = None
        self._next = 0            # running number of the next row
        self._flushed = 0         # rows before this one are in the file
        self._meta: Optional[dict] = None
        self._frames_src: Optional[dict] = None
        self._frames_last = None  # the newest snapshot whose frames were written
        self._counts_done: dict = {}
        self._stop = threading.Event()
        self._thread = None
        self._file = None
        if self.path is not None:
            self._file = recfile.RecordingFile(self.path, {"format": "pointfence recording", "version": 1, "arms": self.n,
                                                           "width": self.width, "tick_columns": list(TICK_COLUMNS),
                                                           "input_columns": list(INPUT_COLUMNS)})
            self._thread = threading.Thread(target=self._writer, name="pointfence-recorder", daemon=True)
            self._thread.start()

    @property
    def streaming(self) -> bool:
        return self.path is not None

    def next_row(self) -> int:
        """Index of the row for this tick, or -1 (not recorded: full, or the ring is)."""
        j = self._next
        if self.path is None:
            if j >= self.capacity:
                self.full = True
                self.ticks_lost += 1
                return -1
        elif j - self._flushed >= self.capacity:
            self.full = True
            self.ticks_lost += 1
            return -1
        else:
            self.full = False
        i = j % self.capacity
        self._next = j + 1
        self.count = i + 1
        self.ticks_recorded += 1
        return i

    def write(self, inp, out) -> None:
        """Record one tick: its ``tick_io.TickInput`` and ``TickOutput`` (arm 0's outputs in the
        tick columns; every arm's master sample, robot position and command, hold masks)."""
        i = self.next_row()
        if i < 0:
            return
        row = self.rows[i]
        row[0] = out.t
        row[1:4] = out.xm[0]
        row[4:7] = out.hip[0]
        row[7:10] = out.proxy[0]
        row[10:13] = out.command[0]
        row[13:16] = out.robot_pos[0]
        row[16:19] = out.force[0]
        row[19] = out.state[0]
        row[20] = out.frame_seq
        v = self.inputs[i]
        v[0], v[1], v[2], v[3] = inp.k, inp.dt, inp.overrun, min(inp.frame_age, 1e9)
        v[4], v[5], v[6], v[7] = inp.architecture, inp.haptics, inp.teleop, inp.frame_time
        m = self.masters[i]
        m[:, :3] = inp.master_pos
        m[:, 3] = inp.pedal
        m[:, 4] = inp.master_ok
        self.robots[i, :, :3] = out.robot_pos
        self.robots[i, :, 3:] = out.command
        self.masters_world[i] = out.xm
        self.holds[i, 0] = out.hold
        self.holds[i, 1:] = out.arm_hold

    def note_tick_us(self, us: float) -> None:
        """The loop's compute time of the tick just recorded (nothing if it was not recorded)."""
        if self.count > 0 and not self.full:
            self.rows[self.count - 1, C["tick_us"]] = us

    def describe(self, meta: dict, snapshot_frames: Optional[dict] = None) -> None:
        """What a replay of a streamed recording needs: ``meta`` (architecture, backend,
        device_spec, rate_hz, cameras: written once), ``snapshot_frames`` (the frame feeder's dict
        snapshot seq -> frame seqs, read by the writer thread: new entries are appended)."""
        self._meta = dict(meta)
        self._frames_src = snapshot_frames

    # --- the writer thread (streamed) ---------------------------------------------------------------
    def _writer(self) -> None:
        while not self._stop.wait(self.flush_s):
            self._flush(final=False)
        self._flush(final=True)

    def _new_snapshots(self, src: dict) -> list:
        """The snapshots added to ``src`` since the last flush, oldest first. Snapshot numbers
        only grow and the dict keeps them in insertion order, so this walks back from the newest
        and stops at the last one written: the work is the new entries', not the whole run's (a
        copy of every entry each flush grew with the run and, by its allocations, made the garbage
        collector run ever longer in this thread, holding the interpreter lock: issue 18)."""
        last = self._frames_last
        for _ in range(3):   # the ingest thread may add one while this reads
            new = []
            try:
                for seq in reversed(src):
                    if last is not None and seq <= last:
                        break
                    new.append(seq)
                return new[::-1]
            except RuntimeError:
                continue
        return []

    def _flush(self, final: bool) -> None:
        f = self._file
        try:
            meta, self._meta = self._meta, None
            add = {}
            src = self._frames_src
            if src is not None:
                for seq in self._new_snapshots(src):
                    add[str(int(seq))] = [int(x) for x in src[seq]]
                    self._frames_last = seq
            counts = {"ticks_recorded": self.ticks_recorded, "ticks_lost": self.ticks_lost}
            if meta is not None or add or counts != self._counts_done:
                self._counts_done = counts
                f.meta({**(meta or {}), **counts, "snapshot_frames": add})
            upto = self._next if final else self._next - 1   # (the newest row may still get its tick_us)
            a = self._flushed
            while a < upto:
                i = a % self.capacity
                m = min(upto - a, self.capacity - i)
                f.rows(a, self.data[i: i + m])
                a += m
                self._flushed = a
            f.sync()
        except (OSError, ValueError) as e:
            self.write_error = f"recording {self.path}: {e}"
            self._stop.set()

    def close(self) -> None:
        """Write every recorded row and end the writer thread (streamed; idempotent)."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None
            self._file.close()

    # --- reading --------------------------------------------------------------------------------------
    def arrays(self) -> dict:
        """Everything recorded, in tick order: ``rows``, ``inputs``, ``masters``, ``robots``,
        ``masters_world``, ``holds`` (streamed: read back from the file; call after ``close()``)."""
        if self.path is None:
            n = self.count
            return {"rows": self.rows[:n], "inputs": self.inputs[:n], "masters": self.masters[:n],
                    "robots": self.robots[:n], "masters_world": self.masters_world[:n], "holds": self.holds[:n]}
        if self._thread is not None:
            raise InputError("Recorder.arrays: a streamed recording is read back after close()")
        return load_recording(self.path)

    def ticks(self) -> np.ndarray:
        return self.arrays()["rows"]

    def column(self, name: str) -> np.ndarray:
        return self.ticks()[:, C[name]]

    # --- files -------------------------------------------------------------------------------------
    def write_csv(self, path) -> None:
        """``ticks.csv``: positions to 1e-9 m, forces to 1e-9 N (repr-exact enough for diffs)."""
        rows = self.ticks()
        with Path(path).open("w") as fh:
            fh.write(",".join(TICK_COLUMNS) + "\n")
            fmt = ",".join(["%.6f"] + ["%.9f"] * 18 + ["%d", "%d", "%.1f"]) + "\n"
            for i in range(0, len(rows), 1024):        # (a block of rows a formatting: no Python loop a row)
                block = rows[i: i + 1024]
                fh.write((fmt * len(block)) % tuple(block.ravel().tolist()))

    def save_inputs(self, path, schedule: dict, meta: dict) -> None:
        a = self.arrays()
        np.savez_compressed(path, inputs=a["inputs"], masters=a["masters"],
                            schedule_ticks=np.array(sorted(schedule), dtype=np.int64),
                            schedule_frames=np.array([schedule[k] for k in sorted(schedule)], dtype=np.int64).reshape(len(schedule), -1),
                            meta=np.array(json.dumps(meta)))


def load_recording(path) -> dict:
    """A streamed recording (``.pfrec``) as arrays in tick order: ``rows`` (TICK_COLUMNS),
    ``inputs``, ``masters``, ``robots``, ``masters_world``, ``holds``, plus ``meta`` (with
    ``snapshot_frames``, and the writer's ``ticks_recorded`` and ``ticks_lost``: ticks not recorded
    because the ring was full) and ``torn_bytes`` (bytes of a torn last chunk left unread: a
    crash)."""
    f = recfile.read(path)
    n = int(f["header"]["arms"])
    if int(f["header"]["width"]) != _layout(n)[0]:
        raise InputError(f"{path}: rows of {f['header']['width']} values for {n} arms; this version of "
                         f"pointfence writes {_layout(n)[0]}")
    out = {k: np.array(v) for k, v in _views(f["rows"], n).items()}
    out.update(meta=f["meta"], torn_bytes=f["torn_bytes"])
    return out


def recording_inputs(path) -> dict:
    """What ``replay`` needs of a streamed recording, as ``load_inputs`` gives it for an
    ``inputs.npz``: inputs, masters, schedule (snapshot seq -> frame seqs) and meta (with
    ``snapshot_ticks``: the first tick that saw each snapshot, from the recorded rows)."""
    r = load_recording(path)
    meta = dict(r["meta"])
    frames = meta.pop("snapshot_frames", {})
    first_tick: dict = {}
    for seq, k in zip(r["rows"][:, C["frame_seq"]], r["inputs"][:, 0]):
        first_tick.setdefault(str(int(seq)), int(k))
    first_tick.pop("0", None)
    meta["snapshot_ticks"] = first_tick
    return {"inputs": r["inputs"], "masters": r["masters"], "meta": meta,
            "schedule": {int(k): tuple(v) for k, v in frames.items()}}


def load_inputs(path) -> dict:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"recording inputs {str(p)!r} not found; expected the inputs.npz a recorded run wrote")
    z = np.load(p, allow_pickle=False)
    schedule = {int(k): tuple(int(x) for x in row) for k, row in zip(z["schedule_ticks"], z["schedule_frames"])}
    return {"inputs": z["inputs"], "masters": z["masters"], "schedule": schedule, "meta": json.loads(str(z["meta"]))}


def tick_input(data: dict, i: int, inp) -> None:
    """Recorded tick ``i`` of ``data`` (``load_inputs`` / ``recording_inputs``) into the
    ``tick_io.TickInput`` ``inp`` (the inverse of ``Recorder.write`` for the input; the loop
    time is ``k * period``, set by the caller). Older recordings have no frame time: NaN."""
    v, m = data["inputs"][i], data["masters"][i]
    inp.k, inp.dt, inp.overrun, inp.frame_age = int(v[0]), float(v[1]), bool(v[2]), float(v[3])
    inp.architecture, inp.haptics, inp.teleop = int(v[4]), bool(v[5]), bool(v[6])
    inp.frame_time = float(v[7]) if len(v) > 7 else float("nan")
    inp.frames_too_old = False           # (not recorded: the replay asks its own feeder)
    inp.law_change = False
    inp.master_pos[:] = m[:, :3]
    inp.pedal[:] = m[:, 3] != 0
    inp.master_ok[:] = m[:, 4] != 0


def read_ticks_csv(path) -> np.ndarray:
    """ticks.csv as an array (header checked)."""
    with Path(path).open() as fh:
        head = fh.readline().strip().split(",")
        if tuple(head) != TICK_COLUMNS:
            raise InputError(f"{path}: columns {head}; expected {list(TICK_COLUMNS)}")
        return np.loadtxt(fh, delimiter=",", ndmin=2)
