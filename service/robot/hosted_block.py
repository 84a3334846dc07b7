"""The shared-memory block between the service and its robot process (robot/hosted.py).

Everything both sides must agree on is declared here, once, as NumPy structured dtypes:
``block_dtype(n, dof)`` is the whole block (control words, fault injection codes, the state and
command channels, the texts), built from ``state_dtype(dof)`` (one arm's state row) and
``COMMAND`` (one arm's command row). Neither side computes an offset: ``Block`` lays the dtype
over the shared buffer and takes every region from it by name, and each row is read as flat
floats through a ``RowLayout`` derived from its dtype (an attribute per field: its index or
slice). ``Channel`` moves a record across without either side waiting.

A record's checksum is a CRC-32 of its bytes, never a sum of floats: a float sum of a record
that holds a NaN is NaN, which equals nothing, so such a record would never read; the reader
must see the NaN to fault on it (hosted.py reports a non-finite state as a robot FAULT).
"""
from __future__ import annotations

import ctypes
from multiprocessing import shared_memory
from typing import Optional

import numpy as np

from pointfence.native import ChannelCore, fast, ptr

#: mode commands (service -> child), in a ring per arm
HOLD, RESUME, ENABLE, FAULT = 1, 2, 3, 4
#: depth of each arm's mode-command ring
RING = 64
#: bytes of each arm's fault reason and last error text (UTF-8)
TEXT = 240
#: control words: stop request (service -> child), periods stepped (the child's heartbeat),
#: the child's pid, child ready (it has built the arms)
CONTROL = np.dtype([("stop", "i8"), ("ticks", "i8"), ("pid", "i8"), ("ready", "i8")])
#: index of the heartbeat in ``Block.ctl_words`` (the control words as int64)
TICKS = CONTROL.fields["ticks"][1] // 8
#: per-arm fault injection codes (the service writes them; the child obeys): none, state NaN
INJECT_NONE, INJECT_NAN = 0, 1
#: the state fields a NaN injection poisons (what a controller with a broken estimator publishes)
POISONED = ("q", "T_meas")


def state_dtype(dof: int) -> np.dtype:
    """One arm's state row (all float64, SI units): child time (s), RobotMode, rejected and ignored
    command counts, servo setpoints applied, mode commands applied, fault text version, error
    text version; joints q (rad or m), dq, tau (Nm or N), setpoint q_d; measured and setpoint
    poses T_meas, T_d (4x4 world, row-major); the measured jaw angle (rad) and whether it is known
    (1.0; 0.0: no jaw, or not reported yet: the angle is then 0, never NaN, which would read as a
    broken state)."""
    j = ("f8", (dof,))
    return np.dtype([("t", "f8"), ("mode", "f8"), ("rejected", "f8"), ("ignored", "f8"), ("servo_seq", "f8"),
                     ("mode_seq", "f8"), ("fault_ver", "f8"), ("error_ver", "f8"),
                     ("q",) + j, ("dq",) + j, ("tau",) + j, ("q_d",) + j,
                     ("T_meas", "f8", (16,)), ("T_d", "f8", (16,)), ("jaw", "f8"), ("jaw_known", "f8")])


#: one arm's command row (service -> child), float64: setpoints sent (a sequence number), mode
#: commands sent (a count), the latest setpoint pose (4x4 world, row-major), the ring of mode
#: commands (``HOLD`` ...; command i at ``i % RING``), jaw setpoints sent (a sequence number) and
#: the latest (rad)
COMMAND = np.dtype([("servo_seq", "f8"), ("mode_seq", "f8"), ("pose", "f8", (16,)), ("ring", "f8", (RING,)),
                    ("jaw_seq", "f8"), ("jaw", "f8")])


def _channel_dtype(row: np.dtype, n: int) -> np.dtype:
    """A ``Channel`` of ``n`` rows of ``row``: two slots, their counters and the slot to read
    (``meta``), and each slot's CRC-32 (``sums``)."""
    return np.dtype([("data", row, (2, n)), ("meta", "i8", (4,)), ("sums", "i8", (2,))])


def block_dtype(n: int, dof: int) -> np.dtype:
    """The whole shared block for ``n`` arms of ``dof`` joints: control words (``CONTROL``),
    per-arm fault injection codes (``INJECT_*``) and the time each injection took effect
    (``inject_t``: when the child first published the injected state, ``time.perf_counter`` s,
    the service's clock: both read CLOCK_MONOTONIC; NaN until then), the state channel (child ->
    service: ``n`` rows of ``state_dtype(dof)``), the command channel (service -> child: ``n`` rows
    of ``COMMAND``) and per arm two texts (fault reason, last error; UTF-8, ``TEXT`` bytes each)."""
    return np.dtype([("ctl", CONTROL), ("inject", "i8", (n,)), ("inject_t", "f8", (n,)),
                     ("state", _channel_dtype(state_dtype(dof), n)),
                     ("cmd", _channel_dtype(COMMAND, n)), ("text", "u1", (n, 2, TEXT))])


class RowLayout:
    """A row of ``dtype`` (all float64 fields) as flat floats: ``size`` floats, and for each field
    name an attribute holding its index (scalars) or slice (arrays) into the row."""

    def __init__(self, dtype: np.dtype):
        self.dtype = dtype
        self.names = dtype.names
        self.size = dtype.itemsize // 8
        for name in self.names:
            sub, off = dtype.fields[name][:2]
            if sub.base != np.float64:
                raise TypeError(f"RowLayout: field {name!r} is {sub.base}; a row holds float64 fields only")
            i, k = off // 8, sub.itemsize // 8
            setattr(self, name, i if sub.shape == () else slice(i, i + k))

    def nonfinite_fields(self, row: np.ndarray) -> list:
        """Names of the fields of ``row`` (flat floats) that hold a NaN or an infinity."""
        rec = row.view(self.dtype)[0]
        return [name for name in self.names if not np.isfinite(rec[name]).all()]


def StateLayout(dof: int) -> RowLayout:
    """The layout of one arm's state row, ``state_dtype(dof)``."""
    return RowLayout(state_dtype(dof))


#: the layout of one arm's command row
COMMAND_LAYOUT = RowLayout(COMMAND)


class Channel:
    """One writer, one reader: a record of ``size`` floats in two slots. The writer fills the slot
    the reader was not pointed at (its counter odd while it writes, then the CRC-32 of the bytes),
    then points the reader at it; the reader copies the slot it is pointed at and keeps the copy if
    that slot's counter was even and unchanged around the copy and the CRC matches. Neither side
    ever waits for the other: a reader only retries if the writer lapped it (two whole writes
    during one copy), and a writer preempted mid-write leaves the previous record readable.

    The protocol is the compiled core's (``native/shm_exchange.c``: ``pf_chan_write``,
    ``pf_chan_read``; its CRC-32 is zlib's), one implementation for both sides of every block.

    ``region``: the channel's part of the block (a ``_channel_dtype`` record over the buffer)."""

    def __init__(self, region: np.ndarray):
        data = region["data"]
        self.size = data.dtype.itemsize * data.shape[1] // 8
        self.data = data.view(np.float64).reshape(2, self.size)   # the two slots as flat floats
        self.meta = region["meta"]              # counter of slot 0, of slot 1, slot to read
        self.sums = region["sums"]              # CRC-32 of each slot's bytes
        self.core = ChannelCore(ptr(self.meta, np.int64, "channel meta"), ptr(self.sums, np.int64, "channel sums"),
                                ptr(self.data, np.float64, "channel slots"), self.size)
        self._core = ctypes.byref(self.core)
        self._addresses: dict = {}              # id -> (record, its data address): ``_address``

    def _address(self, rec) -> ctypes.c_void_p:
        """The data address of ``rec`` (``size`` contiguous float64: an array, or a memoryview of
        one), kept per object (the entry holds it, so its id is not reused while cached)."""
        got = self._addresses.get(id(rec))
        if got is None or got[0] is not rec:
            a = np.frombuffer(rec, np.float64) if type(rec) is memoryview else rec
            if not isinstance(a, np.ndarray) or a.dtype != np.float64 or not a.flags.c_contiguous or a.size != self.size:
                raise TypeError(f"Channel: a record is {self.size} contiguous float64; got "
                                f"{getattr(a, 'dtype', type(a).__name__)} of size {getattr(a, 'size', '?')}")
            if len(self._addresses) >= 16:
                self._addresses.clear()
            got = self._addresses[id(rec)] = (rec, ctypes.c_void_p(a.ctypes.data))
        return got[1]

    def write(self, rec) -> None:
        """Publish ``rec`` (``size`` contiguous float64: an array or a memoryview of one; pass the
        same object every time: its address is looked up once)."""
        fast.pf_chan_write(self._core, self._address(rec))

    def read(self, out, tries: int = 8) -> bool:
        """Copy the latest whole record into ``out`` (``size`` contiguous float64: an array or a
        memoryview of one; the same object every time); False if none was consistent in ``tries``
        attempts (the writer lapped this reader)."""
        return bool(fast.pf_chan_read(self._core, self._address(out), tries))


class Block:
    """The shared block for ``n`` arms of ``dof`` joints (``block_dtype``) over ``buf`` (None: a
    private zeroed copy). Its regions, by name: ``ctl`` (``CONTROL``: ``ctl["ticks"]`` etc.),
    ``ctl_words`` (the same as int64), ``inject`` and ``inject_t`` (n), ``state`` and ``cmd`` (``Channel``: rows of
    ``S`` and ``C`` floats per arm, read through ``layout`` and ``command_layout``), ``text``
    (n, 2, TEXT)."""

    def __init__(self, buf, n: int, dof: int):
        self.n, self.dof = n, dof
        self.dtype = block_dtype(n, dof)
        self.size = self.dtype.itemsize
        rec = np.zeros((), self.dtype) if buf is None else np.ndarray((), self.dtype, buffer=buf)
        self.layout = StateLayout(dof)
        self.command_layout = COMMAND_LAYOUT
        self.S = self.layout.size
        self.C = COMMAND_LAYOUT.size
        self.ctl = rec["ctl"]
        #: the control words as a memoryview of int64 (``ctl_words[TICKS]``: a Python int)
        self.ctl_words = memoryview(self.ctl.reshape(1).view(np.int64))
        #: the heartbeat word alone, as an int64 array of one (the compiled exchange reads it)
        self.heartbeat = self.ctl.reshape(1).view(np.int64)[TICKS:TICKS + 1]
        self.inject = rec["inject"]
        self.inject_t = rec["inject_t"]
        self.state = Channel(rec["state"])
        self.cmd = Channel(rec["cmd"])
        self.text = rec["text"]
        self.raw = np.ndarray((self.size,), np.uint8, buffer=buf) if buf is not None else rec.reshape(1).view(np.uint8)

    @staticmethod
    def nbytes(n: int, dof: int) -> int:
        return block_dtype(n, dof).itemsize


class Commands:
    """The command record of ``n`` arms (``n`` rows of ``COMMAND`` as flat floats, ``rec``) and
    views of its fields, one row per arm: ``servo_seq`` (n,), ``mode_seq`` (n,), ``pose`` (n, 16),
    ``ring`` (n, RING), ``jaw_seq`` (n,), ``jaw`` (n,)."""

    def __init__(self, n: int, rec: Optional[np.ndarray] = None):
        L = COMMAND_LAYOUT
        self.rec = np.zeros(n * L.size) if rec is None else rec
        rows = self.rec.reshape(n, L.size)
        self.servo_seq, self.mode_seq = rows[:, L.servo_seq], rows[:, L.mode_seq]
        self.pose, self.ring = rows[:, L.pose], rows[:, L.ring]
        self.jaw_seq, self.jaw = rows[:, L.jaw_seq], rows[:, L.jaw]


def put_text(dst: np.ndarray, s: Optional[str]) -> None:
    b = (s or "").encode("utf-8", "replace")[:TEXT]
    dst[:] = 0
    dst[: len(b)] = np.frombuffer(b, np.uint8)


def get_text(src: np.ndarray) -> Optional[str]:
    b = bytes(src).rstrip(b"\0")
    return b.decode("utf-8", "replace") if b else None


def attach_child(name: str) -> shared_memory.SharedMemory:
    """The parent's shared-memory block ``name``, attached in a child process. The parent owns it:
    this process's resource tracker is told to leave it, or it would unlink the block when the
    child exits."""
    shm = shared_memory.SharedMemory(name=name)
    try:
        from multiprocessing import resource_tracker

        resource_tracker.unregister(shm._name, "shared_memory")
    except Exception:   # noqa: BLE001 -- a tracker that does not know the block: nothing to undo
        pass
    return shm
