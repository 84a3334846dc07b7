"""Master trajectories as files: ``t,x,y,z[,clutch]`` CSV (master frame, m, s; clutch 0/1, the
foot pedal held from each sample to the next), and their playback by linear interpolation (the
ends hold). ``pointfence device-sim --trajectory`` plays one over the protocol; the service's
``masters.ScriptedMaster`` plays one inside the loop."""
from __future__ import annotations

import bisect
import csv
from pathlib import Path

import numpy as np

from pointfence.kernels.errors import InputError


def read_trajectory(path):
    """(times (N,), positions (N, 3), clutch (N,) bool) from a ``t,x,y,z[,clutch]`` CSV."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"trajectory {str(p)!r} not found; expected a CSV with columns t,x,y,z[,clutch]")
    with p.open(newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise InputError(f"{p}: empty; expected a header t,x,y,z[,clutch] and rows")
    head = [h.strip() for h in rows[0]]
    need = ["t", "x", "y", "z"]
    if head[:4] != need or (len(head) > 4 and head[4:] != ["clutch"]):
        raise InputError(f"{p}: header {','.join(head)}; expected t,x,y,z or t,x,y,z,clutch")
    try:
        data = np.array([[float(v) for v in r] for r in rows[1:] if r], dtype=float)
    except ValueError as e:
        raise InputError(f"{p}: {e}") from None
    if data.ndim != 2 or data.shape[0] < 1 or data.shape[1] != len(head):
        raise InputError(f"{p}: expected rows of {len(head)} numbers")
    clutch = data[:, 4] != 0 if len(head) == 5 else np.ones(len(data), bool)
    return data[:, 0], data[:, 1:4], clutch


def write_trajectory(path, times, positions, clutch=None) -> None:
    with Path(path).open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "x", "y", "z"] + (["clutch"] if clutch is not None else []))
        for i in range(len(times)):
            row = [repr(float(times[i]))] + [repr(float(v)) for v in positions[i]]
            if clutch is not None:
                row.append(int(bool(clutch[i])))
            w.writerow(row)


class Trajectory:
    """A trajectory for playback: ``at(t)`` -> ((x, y, z) m, clutch) at ``t`` s after its start."""

    def __init__(self, times, positions, clutch):
        self.times = [float(x) for x in times]
        self.positions = np.asarray(positions, dtype=float)
        self.clutch = [bool(c) for c in clutch]

    @classmethod
    def from_csv(cls, path) -> "Trajectory":
        return cls(*read_trajectory(path))

    @property
    def duration(self) -> float:
        return self.times[-1] - self.times[0]

    def at(self, t: float) -> tuple:
        s = self.times[0] + t
        tl, p = self.times, self.positions
        i = bisect.bisect_right(tl, s) - 1
        if i < 0:
            return tuple(float(v) for v in p[0]), self.clutch[0]
        if i >= len(tl) - 1:
            return tuple(float(v) for v in p[-1]), self.clutch[-1]
        w = (s - tl[i]) / (tl[i + 1] - tl[i])
        return tuple(float(v) for v in p[i] + (p[i + 1] - p[i]) * w), self.clutch[i]
