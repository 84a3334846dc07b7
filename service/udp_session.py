"""One authenticated client session of the UDP hub (``udp_server.UdpHub``).

Its STATEs are checked and its latest sample kept by the C receiver (``udp_native``), which
also keeps its anti-replay window and counts; the haptic tick copies the sample
(``UdpMaster.poll``). Units: metres (master frame), nanoseconds.
"""
from __future__ import annotations

from pointfence.clients import protocol as P

from .udp_native import NativeReceiver, NativeWindow


class Session:
    """One authenticated client bound to a slot. ``proven``, ``accepted``, ``rejected`` and
    ``error`` are the C receiver's (read when asked); written by the tick: ``seen``,
    ``last_rx_t``, ``has_state``, ``seq``, ``t_client_ns``, ``rx_ns`` and the rejections as of its last copy (``tick_rejected``, ``tick_error``: what FEEDBACK reports)."""

    __slots__ = ("id", "device_id", "slot", "key", "addr", "window", "workspace", "timeout_s", "max_age_ns", "max_force",
                 "hello", "t_open", "rx", "seen", "last_rx_t", "has_state", "seq", "t_client_ns", "rx_ns", "tick_rejected",
                 "tick_error")

    def __init__(self, sid, device_id, slot, key, addr, hello: P.Hello, timeout_s, max_force, t_open: float,
                 rx: NativeReceiver):
        self.id = sid
        self.device_id = device_id
        self.slot = slot
        self.key = key
        self.addr = addr
        self.rx = rx
        self.window = NativeWindow(rx, slot, sid)
        self.workspace = (hello.workspace_min, hello.workspace_max)
        self.timeout_s = timeout_s
        #: a sample older than this at the tick (kernel arrival -> tick, ns) is not used: the timeout
        self.max_age_ns = int(round(timeout_s * 1e9))
        self.max_force = max_force
        self.hello = hello
        self.t_open = t_open             # receiver clock (monotonic s) at WELCOME
        self.seen = 0                    # tick: samples copied so far
        self.last_rx_t = None            # tick: loop time of the newest sample (or of the first tick that saw the session)
        self.has_state = False
        self.seq = 0
        self.t_client_ns = 0
        self.rx_ns = 0                   # tick: arrival of the sample it uses (perf_counter ns)
        self.tick_rejected = 0
        self.tick_error = P.E_OK

    def next_tx(self) -> int:
        """The sequence number of the next datagram the service sends in this session (its
        FEEDBACKs and BYE; counted by the C receiver, which sends the FEEDBACKs)."""
        return self.rx.next_tx(self.slot, self.id)

    def _stat(self, i: int):
        """Field ``i`` of the C receiver's counts for this session (``NativeReceiver.session_stats``)."""
        return self.rx.session_stats(self.slot, self.id)[i]

    accepted = property(lambda self: self._stat(0), doc="STATEs accepted as the session's sample.")
    rejected = property(lambda self: self._stat(1), doc="Datagrams of this session refused (tag, window, values, ...).")
    error = property(lambda self: self._stat(3), doc="The E_* code of the last refused one (E_OK: none).")
    proven = property(lambda self: self._stat(4), doc="A valid STATE arrived: the client holds the session key.")
