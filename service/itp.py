"""Raven II ITP master adapter (optional, off by default; ``pointfence serve --itp``).

Existing Raven II masters send the ITP ``u_struct`` over UDP: 124 bytes, packed, little-endian
on the x86 hosts that run them::

    uint32 sequence, pactyp, version
    int32  delx[2], dely[2], delz[2]        position increments per arm, micrometres
    double Qx[2], Qy[2], Qz[2], Qw[2]       orientation quaternions per arm
    int32  buttonstate[2], grasp[2]         buttons; grasp in milliradians
    int32  surgeon_mode                     1: pedal down (engaged), 0: up
    int32  checksum

THIS LINK IS UNAUTHENTICATED: anyone who can send a datagram to the port can move the robot
(the published Raven II vulnerability). The adapter therefore binds to loopback unless told
otherwise, and exists only so that existing masters can be used on a trusted host; use the
authenticated protocol (``clients/PROTOCOL.md``) for anything else. It still rejects what it
can: wrong size, bad checksum (``checksum="raven"``, the default: the Raven II's own
``UDPChecksum``, a sum of the fields that its masters fill in; ``"sum"``: the unsigned 32-bit sum of
bytes 0..119; ``"none"`` for masters that leave the field unset), a sequence not newer than the last one
(32-bit, wrapping), a sequence more than ``max_jump`` ahead of the last one (``jump``: one
spoofed packet numbered last + 2^31 - 1 must not make every genuine packet look old), packets
from any source other than the one the link is locked to (``source``: the address of the first
valid packet; the lock is released after ``lock_timeout_s`` without an accepted packet, so a
restarted master gets the link back), non-finite or non-unit quaternions, increments above
``max_step_um`` per packet and surgeon modes other than 0/1. Rejected packets are counted and
change nothing. An arm whose packets stop for longer than the timeout reports ``ok = False``
(its robot holds). Bound to a non-loopback address, the adapter logs a warning and its status
says ``exposed``.
Positions are the increments integrated from zero (master frame, m); the adapter sends no force
back.

Two sides, two threads, as in ``udp_server.UdpHub``:

* **The receiver** (a thread of its own, or ``pump()`` called by the owner outside the tick when
  built with ``receiver=False``) reads the socket, drops floods per source address before any
  parsing (``udp_ratelimit.SourceLimiter``, counted as ``rate_limited``), checks every packet
  (``handle``: source lock, size, checksum, sequence, values; its clock is ``time.monotonic``)
  and integrates the accepted increments into the latest sample: a few floats per arm written
  under one short lock.
* **The haptic tick** (``ItpArmMaster.poll``) copies its arm's part of the newest sample under
  that lock (no socket, no parsing, no allocation) and decides the arm's timeout in loop time,
  counted from the tick that first saw the newest sample. The sample is used only if its newest
  packet reached the socket (kernel stamp, ``rx_stamps``) no longer than the timeout before the
  tick: increments must all be integrated, so a backlog that queued while the receiver was
  starved is worked through in order, but the arm holds (``ok = False``, S9; ``stale_ticks``)
  until the sample is fresh again, rather than following the operator seconds late. The receive
  buffer holds tens of milliseconds of packets, not seconds.
"""
from __future__ import annotations

import ipaddress
import logging
import math
import socket
import struct
import threading
import time
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

from .age_hist import AgeHistogram
from .masters import Master
from .osthread import set_fifo
from .rx_stamps import RCVBUF_BYTES, StampedReader
from .udp_ratelimit import SourceLimiter, poll_loop

log = logging.getLogger("pointfence.itp")

ITP = struct.Struct("<III2i2i2i2d2d2d2d2i2iii")
ITP_SIZE = ITP.size   # 124
assert ITP_SIZE == 124


def _i32(x: int) -> int:
    """``x`` wrapped to a C int (two's complement, 32 bits)."""
    x &= 0xFFFFFFFF
    return x - 0x100000000 if x & 0x80000000 else x


def udp_checksum(sequence: int, delx, dely, delz, buttonstate, surgeon_mode: int) -> int:
    """The Raven II's ``UDPChecksum`` (network_layer.cpp): the C ``int`` sum of surgeon_mode, the
    six position increments, both button states and ``(int)sequence`` (wrapping at 32 bits). The
    Raven's masters fill the checksum field with it; the released Raven computes it but does not
    check it."""
    return _i32(surgeon_mode + delx[0] + dely[0] + delz[0] + delx[1] + dely[1] + delz[1]
                + buttonstate[0] + buttonstate[1] + _i32(sequence))


#: the checksum rules a receiver may hold masters to: the Raven's own, a byte sum, none
CHECKSUMS = ("raven", "sum", "none")


def itp_checksum(data, rule: str = "raven") -> int:
    """The checksum of packet ``data`` (its first 120 bytes) by ``rule``: ``"raven"``, the Raven
    II's ``UDPChecksum`` of the fields (what its masters send), or ``"sum"``, the unsigned 32-bit
    sum of bytes 0..119; as the unsigned 32-bit value of the field."""
    if rule == "sum":
        return sum(bytes(data[:120])) & 0xFFFFFFFF
    v = ITP.unpack_from(bytes(data[:120]) + bytes(4))
    return udp_checksum(v[0], v[3:5], v[5:7], v[7:9], v[17:19], v[21]) & 0xFFFFFFFF


def pack_itp(sequence, delta_um, quats, buttons=(0, 0), grasp_mrad=(0, 0), surgeon_mode=1, pactyp=0, version=0,
             checksum=None, rule: str = "raven") -> bytes:
    """An ITP master packet: ``delta_um`` (2, 3) int, ``quats`` (2, 4) as x, y, z, w; its checksum
    ``checksum``, else by ``rule`` (``itp_checksum``)."""
    d = np.asarray(delta_um, dtype=np.int64).reshape(2, 3)
    q = np.asarray(quats, dtype=float).reshape(2, 4)
    body = ITP.pack(sequence, pactyp, version, *d[:, 0].tolist(), *d[:, 1].tolist(), *d[:, 2].tolist(),
                    *q[:, 0].tolist(), *q[:, 1].tolist(), *q[:, 2].tolist(), *q[:, 3].tolist(),
                    *[int(b) for b in buttons], *[int(g) for g in grasp_mrad], int(surgeon_mode), 0)
    c = itp_checksum(body, rule) if checksum is None else checksum
    return body[:120] + struct.pack("<I", c & 0xFFFFFFFF)


class ItpArmMaster(Master):
    """One arm of the ITP master as a ``Master`` of the haptic loop."""

    name = "itp"

    def __init__(self, receiver: "ItpReceiver", arm: int, poll_also=None):
        super().__init__()
        self.receiver = receiver
        self.arm = arm
        self.name = f"itp{arm}"
        self.poll_also = poll_also
        self.ok = False                  # (no sample yet; orientation and grasp: the base's defaults)
        self.clutch = False
        self.seen = 0                    # the receiver's sample count at the last copy
        self.last_t = -math.inf          # loop time of the tick that first saw the newest sample, s
        self.rx_ns = 0                   # kernel arrival of its newest packet (perf_counter ns)

    def poll(self, t: float) -> None:
        """The tick's read (loop time ``t``, s): copy the newest sample if there is one, decide
        the arm's timeout. Never reads the socket."""
        hub = self.poll_also
        if hub is not None and t != hub.t:
            hub.tick(t)
        r = self.receiver
        if r.n != self.seen:
            r.copy_to(self, t)
        if self.seen == 0 or t - self.last_t > r.timeout_s:
            self.ok = False
            return
        age = (hub.t_ns if hub is not None else time.perf_counter_ns()) - self.rx_ns
        r.ages.record(age)
        self.ok = age <= r.max_age_ns
        if not self.ok:          # the newest packet waited longer than the timeout: none (S9)
            r.stale_ticks += 1


class ItpReceiver:
    """The ITP socket, its receiver and its two arms (see the module docstring).

    Args:
        host, port: where to bind (loopback unless the masters are on another host: then the
            link is exposed to anyone on that network, and a warning says so).
        timeout_ms: an arm silent this long reports ``ok = False``.
        checksum: "raven" (the Raven II's own ``UDPChecksum``, what its masters send), "sum" or
            "none" (see ``itp_checksum``).
        max_step_um: largest increment per packet and axis, micrometres.
        max_jump: largest sequence advance accepted from one packet to the next (packets).
        lock_timeout_s: the source lock is released after this long without an accepted packet, s
            (receiver clock).
        receiver: run the receiver thread (default); False: the owner calls ``pump()`` itself,
            outside the tick (deterministic tests).
        limiter: the per-source rate limiter (default: 4,000 packets/s, bursts of 400; a genuine
            ITP master sends 1,000 a second).
        rcvbuf_bytes: the socket's receive buffer (default ``rx_stamps.RCVBUF_BYTES``: tens of
            milliseconds of packets, not seconds).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 36000, timeout_ms: int = 50, checksum: str = "raven",
                 max_step_um: int = 10000, max_jump: int = 1000, lock_timeout_s: float = 1.0, receiver: bool = True,
                 limiter: Optional[SourceLimiter] = None, rcvbuf_bytes: int = RCVBUF_BYTES):
        if not 1 <= int(max_jump) < 0x80000000:
            raise ValueError(f"max_jump = {max_jump}; expected 1 .. 2^31 - 1 packets")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, int(port)))
        except BaseException:
            self.sock.close()
            raise
        self.reader = StampedReader(self.sock, rcvbuf_bytes)
        self.timeout_s = timeout_ms / 1000.0
        self.max_age_ns = int(round(self.timeout_s * 1e9))   # a sample older at the tick is not used
        self.ages = AgeHistogram()       # ages of the samples the ticks used (kernel arrival -> tick)
        self.stale_ticks = 0
        if checksum not in CHECKSUMS:
            raise InputError(f"ITP checksum rule {checksum!r}; expected one of {', '.join(CHECKSUMS)}")
        self.checksum = checksum
        self.max_step_um = int(max_step_um)
        self.max_jump = int(max_jump)
        self.lock_timeout_s = float(lock_timeout_s)
        self.limiter = limiter if limiter is not None else SourceLimiter()
        self.arms = [None, None]
        self.seq = None
        self.source = None               # the address the link is locked to
        self.last_accept_t = None        # receiver clock at the last accepted packet, s
        self._buf = bytearray(2048)
        self._view = memoryview(self._buf)
        self.received = 0                # packets read from the socket
        self.accepted = 0
        self.counters = {"rate_limited": 0, "size": 0, "checksum": 0, "stale": 0, "jump": 0, "source": 0,
                         "non_finite": 0, "range": 0}
        # the latest sample (receiver: integrated under _lock; tick: copied under it)
        self._lock = threading.Lock()
        self.n = 0                       # samples published so far
        self._pos = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
        self._quat = [[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]   # w, x, y, z
        self._buttons = [0, 0]
        self._grasp = [0.0, 0.0]
        self._mode = 0
        self._rx_ns = 0                  # kernel arrival of the newest accepted packet (perf_counter ns)
        self.exposed = not ipaddress.ip_address(self.sock.getsockname()[0]).is_loopback
        self.warning = None
        if self.exposed:
            self.warning = (f"ITP adapter bound to {self.sock.getsockname()[0]}:{self.sock.getsockname()[1]}, which is "
                            "not loopback: the ITP link is UNAUTHENTICATED, anyone who can reach this port can move the "
                            "robot; bind to 127.0.0.1 or use the authenticated protocol (clients/PROTOCOL.md)")
            log.warning(self.warning)
        self._stop = threading.Event()
        self._thread = None
        self.scheduling = "normal"        # the receiver thread's (set_rt_priority)
        if receiver:
            self._thread = threading.Thread(target=self._run, name="pointfence-itp-rx", daemon=True)
            self._thread.start()

    def set_rt_priority(self, priority: int) -> str:
        """SCHED_FIFO ``priority`` for the receiver thread where the OS allows it (0: leave it
        normal), as ``UdpHub.set_rt_priority``; returns what was applied."""
        if self._thread is not None and self._thread.is_alive():
            self.scheduling = set_fifo(self._thread.native_id, priority)
        return self.scheduling

    @property
    def address(self):
        return self.sock.getsockname()

    def arm_master(self, arm: int, poll_also=None) -> ItpArmMaster:
        m = ItpArmMaster(self, arm, poll_also)
        self.arms[arm] = m
        return m

    # --- the tick ---------------------------------------------------------------------------------------
    def copy_to(self, m: ItpArmMaster, t: float) -> None:
        """The tick: copy arm ``m.arm`` of the newest sample into ``m`` (loop time ``t``, s)."""
        a = m.arm
        with self._lock:
            n = self.n
            x, y, z = self._pos[a]
            qw, qx, qy, qz = self._quat[a]
            buttons = self._buttons[a]
            grasp = self._grasp[a]
            mode = self._mode
            rx_ns = self._rx_ns
        p = m.position
        p[0], p[1], p[2] = x, y, z
        o = m.orientation
        o[0], o[1], o[2], o[3] = qw, qx, qy, qz
        m.buttons = buttons
        m.grasp = grasp
        m.clutch = mode == 1
        m.seen = n
        m.last_t = t
        m.rx_ns = rx_ns

    # --- the receiver (outside the tick) ------------------------------------------------------------------
    def _run(self) -> None:
        poll_loop(self.sock, self._stop, self.pump)

    def pump(self, limit: int = 4096) -> int:
        """Receive and handle the waiting packets (at most ``limit``); returns how many."""
        buf, view, read = self._buf, self._view, self.reader.read
        allow = self.limiter.allow
        self.reader.begin()
        k = 0
        while k < limit and not self._stop.is_set():
            got = read(buf)
            if got is None:
                break
            n, addr, rx_ns = got
            k += 1
            self.received += 1
            now = time.monotonic()
            if not allow(addr, now):
                self.counters["rate_limited"] += 1
                continue
            self.handle(view[:n], now, addr, rx_ns)
        return k

    def handle(self, data, t: float, addr, rx_ns: Optional[int] = None) -> bool:
        """Check and apply one packet from ``addr`` received at time ``t`` (receiver clock, s;
        it reached the socket at ``rx_ns``, perf_counter ns, default now); False: rejected (counted)."""
        if self.source is not None and self.last_accept_t is not None and t - self.last_accept_t > self.lock_timeout_s:
            self.source = None           # the locked master fell silent: the next valid packet may take the link
            self.seq = None
        if self.source is not None and addr != self.source:
            self.counters["source"] += 1
            return False
        if len(data) != ITP_SIZE:
            self.counters["size"] += 1
            return False
        v = ITP.unpack_from(data, 0)
        if self.checksum != "none" and (v[22] & 0xFFFFFFFF) != itp_checksum(data, self.checksum):
            self.counters["checksum"] += 1
            return False
        seq = v[0]
        if self.seq is not None:
            d = (seq - self.seq) & 0xFFFFFFFF
            if d == 0 or d >= 0x80000000:
                self.counters["stale"] += 1
                return False
            if d > self.max_jump:
                self.counters["jump"] += 1
                return False
        dx, dy, dz = v[3:5], v[5:7], v[7:9]
        qx, qy, qz, qw = v[9:11], v[11:13], v[13:15], v[15:17]
        if not all(math.isfinite(x) for x in v[9:17]):
            self.counters["non_finite"] += 1
            return False
        mode = v[21]
        for a in range(2):
            n = math.sqrt(qx[a] ** 2 + qy[a] ** 2 + qz[a] ** 2 + qw[a] ** 2)
            if (self.arms[a] is not None and abs(n - 1.0) > 1e-3) or max(abs(dx[a]), abs(dy[a]), abs(dz[a])) > self.max_step_um:
                self.counters["range"] += 1
                return False
        if mode not in (0, 1):
            self.counters["range"] += 1
            return False
        self.seq = seq
        self.source = addr
        self.last_accept_t = t
        self.accepted += 1
        with self._lock:
            for a in range(2):
                if self.arms[a] is None:
                    continue
                p, q = self._pos[a], self._quat[a]
                p[0] += dx[a] * 1e-6
                p[1] += dy[a] * 1e-6
                p[2] += dz[a] * 1e-6
                q[0], q[1], q[2], q[3] = qw[a], qx[a], qy[a], qz[a]
                self._buttons[a] = v[17 + a] & 0xFFFFFFFF
                self._grasp[a] = v[19 + a] * 1e-3
            self._mode = mode
            self._rx_ns = time.perf_counter_ns() if rx_ns is None else rx_ns
            self.n += 1
        return True

    def status(self) -> dict:
        src = self.source
        return {"address": list(self.address) if self.sock.fileno() >= 0 else None, "received": self.received,
                "accepted": self.accepted, "rejected": dict(self.counters),
                "receiver": "thread" if self._thread is not None else "pump", "receiver_scheduling": self.scheduling,
                "rate_limited_sources": len(self.limiter), "rate_limit_overflow": self.limiter.overflowed,
                "authenticated": False, "exposed": self.exposed, "warning": self.warning,
                "stale_ticks": self.stale_ticks, "state_age_ms": self.ages.summary(), "kernel_dropped": self.reader.dropped,
                "locked_to": list(src) if src is not None else None}

    def close(self) -> None:
        """Stop the receiver and close the socket (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(2.0)
        self.sock.close()
