"""The UDP hub's receiver in C (``native/udp_rx.c``): the STATE path in a thread that never takes
the interpreter lock, and the queue of everything else for the hub's Python.

``NativeReceiver`` owns one ``pf_rx`` over the hub's socket. Its C thread (``start``) reads the
socket and applies every STATE that names a live session from that session's own address
(window, tag, values: the session's latest sample); the other datagrams wait in a bounded queue
that the hub's Python receiver takes (``next``) and handles as before (rate limits, handshakes,
BYEs, counting). Sessions are registered with ``open`` when the hub opens them and removed with
``close``; the tick copies a slot's latest sample with ``sample`` (never waiting for the
writer). Without the thread (``UdpHub(receiver=False)``), ``poll`` reads what waits in the
calling thread through the same C path. Addresses are IPv4 ``(host, port)`` tuples; times are
``time.perf_counter_ns``.
"""
from __future__ import annotations

import ctypes
import socket
import struct
from ctypes import POINTER, Structure, c_double, c_int, c_int32, c_int64, c_uint8, c_uint32, c_uint64, c_void_p

from pointfence.clients import protocol as P
from pointfence.native import unchecked
from pointfence.native.build import load_udp_rx

#: the queue of datagrams for the hub's Python (each up to MAX_DATAGRAM bytes): a flood beyond
#: what Python reads in time is dropped here (``queue_dropped``), never the devices' STATEs
QUEUE = 1024
#: pf_rx_feed's answer for a datagram that is not a live session's STATE from its own address
NOT_MINE = -1
#: pf_rx_sample's answer when the sample was being written each time it looked
BUSY = (1 << 64) - 1
_N_CODES = P.E_COOKIE + 1
_ADDR = struct.Struct("!I")


class Sample(Structure):
    """``pf_rx_sample_t``: a session's latest sample as the tick copies it (metres, master frame;
    ``rx_ns``: its kernel arrival, perf_counter ns) and the session's rejections so far."""

    _fields_ = [("n", c_uint64), ("seq", c_uint64), ("t_client", c_uint64), ("rx_ns", c_int64),
                ("pos", c_double * 3), ("quat", c_double * 4), ("grasp", c_double), ("flags", c_uint32),
                ("buttons", c_uint32), ("rejected", c_uint64), ("error", c_int32), ("pad", c_int32)]


class Take(Structure):
    """``pf_rx_take_t`` (native/udp_tick.h): a session's tick state, what earlier ticks took of it
    (``udp_session.Session``'s tick fields read it) and what this tick takes; ``pos`` and ``quat``
    point at the master's own arrays (m, master frame; w x y z)."""

    _fields_ = [("sid", c_uint32), ("has_state", c_int32), ("timeout_s", c_double), ("max_age_ns", c_int64),
                ("seen", c_uint64), ("seq", c_uint64), ("t_client", c_uint64), ("rx_ns", c_int64),
                ("last_rx_t", c_double), ("tick_rejected", c_uint64), ("tick_error", c_int32), ("clutch", c_int32),
                ("ok", c_int32), ("buttons", c_uint32), ("grasp", c_double), ("age_ns", c_int64),
                ("pos", POINTER(c_double)), ("quat", POINTER(c_double))]


class FeedbackSource(Structure):
    """``pf_fb_src_t`` (native/udp_tick.h): every arm's FEEDBACK fields of the tick, pointing at
    the service's output (``tick_io.TickOutput``, bound once) and the robot modes the hub sets once
    a tick."""

    _fields_ = [("tick", c_uint64), ("t_tick_ns", c_uint64), ("fixture", c_uint32), ("n", c_uint32),
                ("proxy", POINTER(c_double)), ("robot", POINTER(c_double)), ("contact", POINTER(c_int32)),
                ("hold", POINTER(c_int64)), ("coupled", POINTER(c_uint8)), ("mode", POINTER(c_uint8))]


#: ``NativeReceiver.take``'s answers: taken (``Take.ok`` says whether the master has a valid
#: sample); the session was silent past its timeout (the hub drops it); the newest sample is
#: older than the session's ``max_age_ns`` (not used, S9)
TAKE_OK, TAKE_SILENT, TAKE_STALE = 0, 1, 2
#: the tick's two calls, without argtypes (``pointfence.native.unchecked``)
_TICK_SIGNATURES = {
    "pf_rx_take": (c_int, [c_void_p, c_int, POINTER(Take), c_double, c_int64]),
    "pf_rx_send_arm": (c_int, [c_void_p, c_int, POINTER(Take), POINTER(FeedbackSource), POINTER(c_double)]),
}


def _declare(lib) -> None:
    P_ = POINTER
    sigs = {
        "pf_rx_new": ([c_int, c_int, c_int], c_void_p),
        "pf_rx_open": ([c_void_p, c_int, c_uint32, c_uint32, P_(c_uint8), c_int, c_uint32, c_uint32, P_(c_double),
                        c_double], None),
        "pf_rx_next_tx": ([c_void_p, c_int, c_uint32], c_uint64),
        "pf_rx_close": ([c_void_p, c_int, c_uint32], None),
        "pf_rx_window": ([c_void_p, c_int, c_uint32, c_uint64, c_int], c_int),
        "pf_rx_note": ([c_void_p, c_int, c_uint32, c_int], None),
        "pf_rx_feed": ([c_void_p, c_void_p, c_int, c_uint32, c_uint32, c_int64], c_int),
        "pf_rx_next": ([c_void_p, c_int, c_void_p, c_int, P_(c_uint32), P_(c_uint32), P_(c_int64)], c_int),
        "pf_rx_poll": ([c_void_p, c_int], c_int),
        "pf_rx_start": ([c_void_p], c_int),
        "pf_rx_stop": ([c_void_p], None),
        "pf_rx_free": ([c_void_p], None),
        "pf_rx_sample": ([c_void_p, c_int, c_uint32, P_(Sample)], c_uint64),
        "pf_rx_session_stats": ([c_void_p, c_int, c_uint32, P_(c_uint64)], None),
        "pf_rx_stats": ([c_void_p, P_(c_uint64)], None),
        "pf_rx_limits": ([c_void_p, c_double, c_double, c_double], None),
    }
    for name, (args, res) in sigs.items():
        f = getattr(lib, name)
        f.argtypes, f.restype = args, res


def _ip(addr) -> tuple:
    """(host, port) -> (IPv4 as an integer, port)."""
    return _ADDR.unpack(socket.inet_aton(addr[0]))[0], int(addr[1])


class NativeReceiver:
    """The C receiver over ``sock`` (a bound IPv4 UDP socket, non-blocking, kept open by its
    owner for as long as this lives) for ``slots`` sessions at most."""

    def __init__(self, sock: socket.socket, slots: int, queue: int = QUEUE):
        self._wait_lib, lib = load_udp_rx()
        for L in (self._wait_lib, lib):
            _declare(L)
        self._lib = lib
        self._tick = unchecked(lib, _TICK_SIGNATURES)
        self.sock = sock
        self._h = lib.pf_rx_new(sock.fileno(), int(slots), int(queue))
        if not self._h:
            raise MemoryError(f"the UDP receiver could not allocate its queue of {queue} datagrams")
        self._hv = c_void_p(self._h)         # (the handle as the tick's calls pass it)
        self._buf = (c_uint8 * P.MAX_DATAGRAM)()
        self._ip, self._port, self._rx = c_uint32(), c_uint32(), c_int64()
        self._ip_p, self._port_p, self._rx_p = ctypes.byref(self._ip), ctypes.byref(self._port), ctypes.byref(self._rx)
        self._stats = (c_uint64 * (8 + _N_CODES))()
        self._sstats = (c_uint64 * 5)()
        self._addrs: dict = {}               # (ip, port) -> (host, port): the peers' tuples, built once
        self.thread_id = None                # the C thread's OS id once started

    # --- sessions (the hub, under its lock) ----------------------------------------------------------
    def open(self, slot: int, sid: int, device_id: int, key: bytes, addr, ws_min, ws_max, max_force: float) -> None:
        """Slot ``slot`` holds session ``sid`` of ``device_id`` from ``addr`` from now on: its
        STATEs are checked against ``key`` and the workspace (m), its FEEDBACK saturated at
        ``max_force`` (N)."""
        if not 1 <= len(key) <= 64:
            raise ValueError(f"a session key of {len(key)} bytes; expected 1..64")
        ip, port = _ip(addr)
        kb = (c_uint8 * len(key)).from_buffer_copy(key)
        ws = (c_double * 6)(*ws_min, *ws_max)
        self._lib.pf_rx_open(self._h, slot, sid, device_id, kb, len(key), ip, port, ws, float(max_force))

    def limits(self, rate: float, burst: float, idle_s: float) -> None:
        """Per source address, before any header is read: ``rate`` datagrams/s on average and
        ``burst`` at once; a source silent for ``idle_s`` may give its bucket to a new one."""
        if not (rate > 0 and burst >= 1 and idle_s > 0):
            raise ValueError(f"rate {rate}/s, burst {burst}, idle_s {idle_s}: expected positive values (burst >= 1)")
        self._lib.pf_rx_limits(self._h, float(rate), float(burst), float(idle_s))

    def close(self, slot: int, sid: int) -> None:
        self._lib.pf_rx_close(self._h, slot, sid)

    def window(self, slot: int, sid: int, seq: int, commit: bool) -> int:
        """The session's anti-replay window: check ``seq`` (and record it with ``commit``); an E_* code."""
        return self._lib.pf_rx_window(self._h, slot, sid, seq & 0xFFFFFFFFFFFFFFFF, int(commit))

    def note(self, slot: int, sid: int, code: int) -> None:
        """Count a datagram the hub refused against the session (its ``rejected`` and ``error``)."""
        self._lib.pf_rx_note(self._h, slot, sid, code)

    def session_stats(self, slot: int, sid: int) -> tuple:
        """(accepted, rejected, superseded, last error code, proven) of the session on ``slot``."""
        s = self._sstats
        self._lib.pf_rx_session_stats(self._h, slot, sid, s)
        return int(s[0]), int(s[1]), int(s[2]), int(s[3]), bool(s[4])

    # --- datagrams ---------------------------------------------------------------------------------------
    def feed(self, data, addr, rx_ns: int) -> int:
        """Apply one datagram as the thread would: its E_* code if it is a live session's STATE
        from its own address (counted here), else NOT_MINE (the hub's Python handles it)."""
        n = len(data)
        if n > P.MAX_DATAGRAM:
            return NOT_MINE
        buf = self._buf
        ctypes.memmove(buf, bytes(data), n)
        ip, port = _ip(addr)
        return self._lib.pf_rx_feed(self._h, buf, n, ip, port, rx_ns)

    def next(self, into: bytearray, timeout_ms: int = 0):
        """The next queued datagram copied into ``into``: ``(nbytes, address, arrival ns)``, None if
        none came within ``timeout_ms`` (0: do not wait; the call keeps the interpreter lock), or
        False once the receiver stopped."""
        lib = self._wait_lib if timeout_ms > 0 else self._lib
        n = lib.pf_rx_next(self._h, int(timeout_ms), self._buf, len(into), self._ip_p, self._port_p, self._rx_p)
        if n <= 0:
            return None if n == 0 else False
        into[:n] = memoryview(self._buf)[:n]
        key = (self._ip.value, self._port.value)
        addr = self._addrs.get(key)
        if addr is None:
            if len(self._addrs) >= 4096:
                self._addrs.clear()
            addr = self._addrs[key] = (socket.inet_ntoa(_ADDR.pack(key[0])), key[1])
        return n, addr, self._rx.value

    def poll(self, limit: int) -> int:
        """Read what waits in the socket now (no thread running): STATEs applied, the rest queued; how many read."""
        return self._wait_lib.pf_rx_poll(self._h, int(limit))

    # --- the tick --------------------------------------------------------------------------------------
    def sample(self, slot: int, sid: int, out: Sample) -> int:
        """Copy the slot's latest sample of session ``sid`` into ``out``: samples published so far
        (0: none or another session), or BUSY (being written: keep the last copy)."""
        return self._lib.pf_rx_sample(self._h, slot, sid, out)

    def take(self, slot: int, take, t: float, t_ns: int) -> int:
        """The tick's take of the slot's session (``take``: ``byref`` of its ``Take``) at loop time
        ``t`` (s), the tick having started at ``t_ns`` (perf_counter ns): a new sample goes into
        the master's arrays and the take's fields; a ``TAKE_*`` answer."""
        if not self._h:
            return TAKE_SILENT                # (freed: nothing arrives any more)
        return self._tick.pf_rx_take(self._hv, slot, take, c_double(t), c_int64(t_ns))

    def send_arm(self, slot: int, take, source, force) -> int:
        """The tick: arm ``slot``'s FEEDBACK to the session of ``take`` (``byref`` of its
        ``Take``), force ``force`` (a pointer to 3 doubles, N, master frame), the rest from
        ``source`` (``byref`` of a ``FeedbackSource``), its force saturated at the session's limit,
        stamped, tagged (never blocks): 1 sent, 0 the send failed, -1 no such session."""
        if not self._h:
            return -1
        return self._tick.pf_rx_send_arm(self._hv, slot, take, source, force)

    def next_tx(self, slot: int, sid: int) -> int:
        """The session's next outgoing sequence number (0: the slot holds another session)."""
        return self._lib.pf_rx_next_tx(self._h, slot, sid)

    # --- the thread --------------------------------------------------------------------------------------
    def start(self) -> int:
        """Start the C thread; its OS thread id (for its scheduling)."""
        tid = self._lib.pf_rx_start(self._h)
        if tid < 0:
            raise OSError("the UDP receiver's thread could not be started")
        self.thread_id = tid
        return tid

    def stop(self) -> None:
        """Stop the thread (within 20 ms) and wake a waiting ``next``. Call before the socket closes."""
        if self._h:
            self._wait_lib.pf_rx_stop(self._h)

    def free(self) -> None:
        if self._h:
            self._wait_lib.pf_rx_free(self._h)
            self._h = None
            self._hv = c_void_p(None)

    def stats(self) -> dict:
        """Counts since the start: datagrams read, STATEs accepted and superseded, datagrams the
        kernel dropped (receive buffer full), the queue dropped and the rate limit dropped, the
        sources with a bucket of their own and the datagrams of new sources beyond them
        (``overflowed``), and rejections per E_* code."""
        s = self._stats
        self._lib.pf_rx_stats(self._h, s)
        return {"received": int(s[0]), "accepted": int(s[1]), "superseded": int(s[2]), "kernel_dropped": int(s[3]),
                "queue_dropped": int(s[4]), "rate_limited": int(s[5]), "sources": int(s[6]), "overflowed": int(s[7]),
                "codes": [int(s[8 + i]) for i in range(_N_CODES)]}

    def __del__(self):
        try:
            self.free()
        except Exception:
            pass


class NativeWindow:
    """A session's anti-replay window, kept by the C receiver (it moves with every STATE there);
    the hub's BYE checks and records through it."""

    __slots__ = ("rx", "slot", "sid")

    def __init__(self, rx: NativeReceiver, slot: int, sid: int):
        self.rx, self.slot, self.sid = rx, slot, sid

    def check(self, seq: int) -> None:
        code = self.rx.window(self.slot, self.sid, seq, False)
        if code != P.E_OK:
            raise P.ProtocolError(code, f"sequence {seq}: {P.ERROR_NAMES[code]}")

    def commit(self, seq: int) -> None:
        code = self.rx.window(self.slot, self.sid, seq, True)
        if code != P.E_OK:
            raise P.ProtocolError(code, f"sequence {seq}: {P.ERROR_NAMES[code]}")


__all__ = ["FeedbackSource", "NativeReceiver", "NativeWindow", "Sample", "Take", "NOT_MINE", "BUSY", "QUEUE",
           "TAKE_OK", "TAKE_SILENT", "TAKE_STALE"]
