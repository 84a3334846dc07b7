"""Recording a run tick by tick into preallocated arrays, and writing/reading it.

Outputs (arm 0, world frame) go to ``ticks.csv`` with exactly the columns ``TICK_COLUMNS``.
Inputs (every master's sample, the tick's dt and health flags, the control state, which
snapshot each tick saw and which camera frames built it) go to ``inputs.npz`` so that
``pointfence replay --recording DIR`` re-runs the same ticks exactly.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pointfence.kernels.errors import InputError

TICK_COLUMNS = ("t", "xm_x", "xm_y", "xm_z", "hip_x", "hip_y", "hip_z", "proxy_x", "proxy_y", "proxy_z",
                "xr_cmd_x", "xr_cmd_y", "xr_cmd_z", "xr_x", "xr_y", "xr_z", "f_x", "f_y", "f_z",
                "state", "frame_seq", "tick_us")
C = {name: i for i, name in enumerate(TICK_COLUMNS)}
#: per-tick inputs: k, dt, overrun, frame_age, architecture, haptics_on, teleop_on, and the tick's
#: time on the frames' clock (nan: unknown; motion prediction and the tool pose ring use it)
INPUT_COLUMNS = ("k", "dt", "overrun", "frame_age", "arch", "haptics_on", "teleop_on", "frame_time")


class Recorder:
    """Room for ``capacity`` ticks of ``n`` arms; ``full`` once it is exhausted (recording stops,
    the loop does not)."""

    def __init__(self, capacity: int, n: int):
        self.capacity = int(capacity)
        self.n = int(n)
        self.rows = np.zeros((self.capacity, len(TICK_COLUMNS)))
        self.inputs = np.zeros((self.capacity, len(INPUT_COLUMNS)))
        self.masters = np.zeros((self.capacity, self.n, 5))     # x, y, z, pedal, ok (master frame)
        self.robots = np.zeros((self.capacity, self.n, 6))      # X_r (3), X_r* (3) of every arm
        self.masters_world = np.zeros((self.capacity, self.n, 3))
        self.count = 0
        self.full = False

    def next_row(self) -> int:
        """Index of the row for this tick, or -1 when full."""
        if self.count >= self.capacity:
            self.full = True
            return -1
        i = self.count
        self.count += 1
        return i

    def ticks(self) -> np.ndarray:
        return self.rows[: self.count]

    def column(self, name: str) -> np.ndarray:
        return self.rows[: self.count, C[name]]

    # --- files -------------------------------------------------------------------------------------
    def write_csv(self, path) -> None:
        """``ticks.csv``: positions to 1e-9 m, forces to 1e-9 N (repr-exact enough for diffs)."""
        rows = self.ticks()
        with Path(path).open("w") as fh:
            fh.write(",".join(TICK_COLUMNS) + "\n")
            fmt = ",".join(["%.6f"] + ["%.9f"] * 18 + ["%d", "%d", "%.1f"]) + "\n"
            for r in rows:
                fh.write(fmt % tuple(r))

    def save_inputs(self, path, schedule: dict, meta: dict) -> None:
        n = self.count
        np.savez_compressed(path, inputs=self.inputs[:n], masters=self.masters[:n],
                            schedule_ticks=np.array(sorted(schedule), dtype=np.int64),
                            schedule_frames=np.array([schedule[k] for k in sorted(schedule)], dtype=np.int64).reshape(len(schedule), -1),
                            meta=np.array(json.dumps(meta)))


def load_inputs(path) -> dict:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"recording inputs {str(p)!r} not found; expected the inputs.npz a recorded run wrote")
    z = np.load(p, allow_pickle=False)
    schedule = {int(k): tuple(int(x) for x in row) for k, row in zip(z["schedule_ticks"], z["schedule_frames"])}
    return {"inputs": z["inputs"], "masters": z["masters"], "schedule": schedule, "meta": json.loads(str(z["meta"]))}


def read_ticks_csv(path) -> np.ndarray:
    """ticks.csv as an array (header checked)."""
    with Path(path).open() as fh:
        head = fh.readline().strip().split(",")
        if tuple(head) != TICK_COLUMNS:
            raise InputError(f"{path}: columns {head}; expected {list(TICK_COLUMNS)}")
        return np.loadtxt(fh, delimiter=",", ndmin=2)
