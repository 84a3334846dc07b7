"""One authenticated client session of the UDP hub (``udp_server.UdpHub``).

Its STATEs are checked and its latest sample kept by the C receiver (``udp_native``), which
also keeps its anti-replay window and counts; the haptic tick copies the sample
(``UdpMaster.poll``). Units: metres (master frame), nanoseconds.
"""
from __future__ import annotations

import ctypes
import math

from pointfence.clients import protocol as P

from .udp_native import NativeReceiver, NativeWindow, Take


class Session:
    """One authenticated client bound to a slot. ``proven``, ``accepted``, ``rejected`` and
    ``error`` are the C receiver's (read when asked); the tick's state of the session is
    ``take`` (``udp_native.Take``: the tick's compiled take writes it, ``UdpMaster.poll``), read
    through ``seen``, ``last_rx_t``, ``has_state``, ``seq``, ``t_client_ns``, ``rx_ns`` and the
    rejections as of its last copy (``tick_rejected``, ``tick_error``: what FEEDBACK reports);
    ``timeout_s`` and ``max_age_ns`` are the take's limits."""

    __slots__ = ("id", "device_id", "slot", "key", "addr", "window", "workspace", "max_force",
                 "hello", "t_open", "rx", "take", "take_ref")

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
        self.max_force = max_force
        self.hello = hello
        self.t_open = t_open             # receiver clock (monotonic s) at WELCOME
        # the tick's state: no sample yet, silence counted from the first tick that sees it; a
        # sample older than the timeout at the tick (kernel arrival -> tick) is not used
        self.take = Take(sid=sid, timeout_s=timeout_s, max_age_ns=int(round(timeout_s * 1e9)), last_rx_t=math.nan,
                         tick_error=P.E_OK, age_ns=-1)
        self.take_ref = ctypes.byref(self.take)

    def next_tx(self) -> int:
        """The sequence number of the next datagram the service sends in this session (its
        FEEDBACKs and BYE; counted by the C receiver, which sends the FEEDBACKs)."""
        return self.rx.next_tx(self.slot, self.id)

    # --- the tick's state (``take``) ---------------------------------------------------------------
    @property
    def timeout_s(self) -> float:
        """Silence (loop time, s) after which the tick drops the session."""
        return self.take.timeout_s

    @property
    def max_age_ns(self) -> int:
        """A sample older than this at the tick (kernel arrival -> tick, ns) is not used."""
        return self.take.max_age_ns

    @max_age_ns.setter
    def max_age_ns(self, ns: int) -> None:
        self.take.max_age_ns = int(ns)

    seen = property(lambda self: self.take.seen, doc="Samples published when the tick took the newest.")
    has_state = property(lambda self: bool(self.take.has_state), doc="The tick took a sample of this session.")
    seq = property(lambda self: self.take.seq, doc="The taken sample's sequence number.")
    t_client_ns = property(lambda self: self.take.t_client, doc="The taken sample's client time (ns).")
    rx_ns = property(lambda self: self.take.rx_ns, doc="The taken sample's kernel arrival (perf_counter ns).")
    tick_rejected = property(lambda self: self.take.tick_rejected, doc="Rejections as of the tick's last copy.")
    tick_error = property(lambda self: self.take.tick_error, doc="The last error code as of the tick's last copy.")

    @property
    def last_rx_t(self):
        """Loop time (s) of the newest sample, or of the first tick that saw the session (None
        before that)."""
        t = self.take.last_rx_t
        return None if math.isnan(t) else t

    def _stat(self, i: int):
        """Field ``i`` of the C receiver's counts for this session (``NativeReceiver.session_stats``)."""
        return self.rx.session_stats(self.slot, self.id)[i]

    accepted = property(lambda self: self._stat(0), doc="STATEs accepted as the session's sample.")
    rejected = property(lambda self: self._stat(1), doc="Datagrams of this session refused (tag, window, values, ...).")
    error = property(lambda self: self._stat(3), doc="The E_* code of the last refused one (E_OK: none).")
    proven = property(lambda self: self._stat(4), doc="A valid STATE arrived: the client holds the session key.")
