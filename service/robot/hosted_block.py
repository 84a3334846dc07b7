"""The shared-memory block between the service and its robot process (robot/hosted.py).

Everything both sides must agree on is defined here, once: the control words, the state row of
one arm (``StateLayout``: one NumPy structured dtype; both sides index a row through the slices
derived from it), the command record (``command_views``), the texts, and the channel that moves
a record across without either side waiting (``Channel``).

A record's checksum is a CRC-32 of its bytes, never a sum of floats: a float sum of a record
that holds a NaN is NaN, which equals nothing, so such a record would never read; the reader
must see the NaN to fault on it (hosted.py reports a non-finite state as a robot FAULT).
"""
from __future__ import annotations

import zlib
from typing import Optional

import numpy as np

#: mode commands (service -> child), in a ring per arm
HOLD, RESUME, ENABLE, FAULT = 1, 2, 3, 4
#: depth of each arm's mode-command ring
RING = 64
#: bytes of each arm's fault reason and last error text (UTF-8)
TEXT = 240
#: control words: stop request, child steps (the heartbeat), child pid, child ready
CTL_STOP, CTL_TICKS, CTL_PID, CTL_READY = 0, 1, 2, 3
#: per-arm fault injection codes (the service writes them; the child obeys): none, state NaN
INJECT_NONE, INJECT_NAN = 0, 1
#: the state fields a NaN injection poisons (what a controller with a broken estimator publishes)
POISONED = ("q", "T_meas")


def state_dtype(dof: int) -> np.dtype:
    """One arm's state row (all float64, SI units): child time (s), RobotMode, rejected and ignored
    command counts, servo setpoints applied, mode commands applied, fault text version, error
    text version; joints q (rad or m), dq, tau (Nm or N), setpoint q_d; measured and setpoint
    poses T_meas, T_d (4x4 world, row-major)."""
    j = ("f8", (dof,))
    return np.dtype([("t", "f8"), ("mode", "f8"), ("rejected", "f8"), ("ignored", "f8"), ("servo_seq", "f8"),
                     ("mode_seq", "f8"), ("fault_ver", "f8"), ("error_ver", "f8"),
                     ("q",) + j, ("dq",) + j, ("tau",) + j, ("q_d",) + j,
                     ("T_meas", "f8", (16,)), ("T_d", "f8", (16,))])


class StateLayout:
    """The state row of ``state_dtype(dof)`` as a flat float row: ``size`` floats, and for each
    field name an attribute holding its index (scalars) or slice (arrays) into the row."""

    def __init__(self, dof: int):
        self.dtype = state_dtype(dof)
        self.names = self.dtype.names
        self.size = self.dtype.itemsize // 8
        for name in self.names:
            sub, off = self.dtype.fields[name][:2]
            i, k = off // 8, sub.itemsize // 8
            setattr(self, name, i if sub.shape == () else slice(i, i + k))

    def nonfinite_fields(self, row: np.ndarray) -> list:
        """Names of the fields of ``row`` (flat floats) that hold a NaN or an infinity."""
        rec = row.view(self.dtype)[0]
        return [name for name in self.names if not np.isfinite(rec[name]).all()]


class Channel:
    """One writer, one reader: a record of ``size`` floats in two slots. The writer fills the slot
    the reader was not pointed at (its counter odd while it writes, then the CRC-32 of the bytes),
    then points the reader at it; the reader copies the slot it is pointed at and keeps the copy if
    that slot's counter was even and unchanged around the copy and the CRC matches. Neither side
    ever waits for the other: a reader only retries if the writer lapped it (two whole writes
    during one copy), and a writer preempted mid-write leaves the previous record readable."""

    def __init__(self, take, size: int):
        self.size = size
        self.data = take((2, size), np.float64)
        self.meta = take((4,), np.int64)        # counter of slot 0, of slot 1, slot to read
        self.sums = take((2,), np.int64)        # CRC-32 of each slot's bytes

    def write(self, rec: np.ndarray) -> None:
        w = 1 - int(self.meta[2])
        self.meta[w] += 1
        np.copyto(self.data[w], rec)
        self.sums[w] = zlib.crc32(rec)
        self.meta[w] += 1
        self.meta[2] = w

    def read(self, out: np.ndarray, tries: int = 8) -> bool:
        """Copy the latest whole record into ``out`` (contiguous floats); False if none was
        consistent in ``tries`` attempts (the writer lapped this reader)."""
        for _ in range(tries):
            i = int(self.meta[2])
            s1 = int(self.meta[i])
            if s1 & 1:
                continue
            np.copyto(out, self.data[i])
            if int(self.meta[i]) == s1 and zlib.crc32(out) == int(self.sums[i]):
                return True
        return False


class Block:
    """The shared block for ``n`` arms of ``dof`` joints: control words (``CTL_*``), per-arm
    fault injection codes, the state channel (child -> service: ``n`` rows of ``layout.size``
    floats), the command channel (service -> child: ``command_views``) and the arms' texts
    (fault reason, last error; versioned in the state rows). ``buf`` None: only the size."""

    def __init__(self, buf, n: int, dof: int):
        self.n, self.dof = n, dof
        self.layout = StateLayout(dof)
        self.S = self.layout.size
        self.C = n * (2 + 16 + RING)
        off = 0

        def take(shape, dtype):
            nonlocal off
            a = np.empty(shape, dtype) if buf is None else np.ndarray(shape, dtype, buffer=buf, offset=off)
            off += a.nbytes
            return a

        self.ctl = take((4,), np.int64)
        self.inject = take((n,), np.int64)
        self.state = Channel(take, n * self.S)
        self.cmd = Channel(take, self.C)
        self.text = take((n, 2, TEXT), np.uint8)   # fault reason, last error (UTF-8)
        self.size = off

    @staticmethod
    def nbytes(n: int, dof: int) -> int:
        return Block(None, n, dof).size


def command_views(rec: np.ndarray, n: int) -> tuple:
    """(counts (n, 2): setpoints and mode commands sent, poses (n, 16), ring (n, RING)): views of
    a command record of ``n * (2 + 16 + RING)`` floats."""
    return (rec[: 2 * n].reshape(n, 2), rec[2 * n: 18 * n].reshape(n, 16), rec[18 * n:].reshape(n, RING))


def put_text(dst: np.ndarray, s: Optional[str]) -> None:
    b = (s or "").encode("utf-8", "replace")[:TEXT]
    dst[:] = 0
    dst[: len(b)] = np.frombuffer(b, np.uint8)


def get_text(src: np.ndarray) -> Optional[str]:
    b = bytes(src).rstrip(b"\0")
    return b.decode("utf-8", "replace") if b else None
