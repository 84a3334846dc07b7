"""One authenticated client session of the UDP hub (``udp_server.UdpHub``) and its latest sample.

The receiver thread writes the sample (``publish``, under the session's own short lock); the
haptic tick copies it (``UdpMaster.poll``). Units: metres (master frame), nanoseconds.
"""
from __future__ import annotations

import threading

from pointfence.clients import protocol as P


class Session:
    """One authenticated client bound to a slot. Written by the receiver: the latest sample
    (under ``lock``), ``proven``, ``addr``, ``rejected``, ``error``, ``accepted``; by the tick:
    ``seen``, ``last_rx_t``, ``has_state``, ``seq``, ``t_client_ns``, ``tx_seq``."""

    __slots__ = ("id", "device_id", "slot", "key", "addr", "window", "workspace", "timeout_s", "max_age_ns", "max_force",
                 "hello", "t_open", "proven", "rejected", "error", "accepted",
                 "lock", "n", "s_seq", "s_pos", "s_flags", "s_buttons", "s_quat", "s_grasp", "s_t_client", "s_rx_ns",
                 "seen", "last_rx_t", "has_state", "seq", "t_client_ns", "rx_ns", "tx_seq")

    def __init__(self, sid, device_id, slot, key, addr, hello: P.Hello, timeout_s, max_force, t_open: float):
        self.id = sid
        self.device_id = device_id
        self.slot = slot
        self.key = key
        self.addr = addr
        self.window = P.ReplayWindow()
        self.workspace = (hello.workspace_min, hello.workspace_max)
        self.timeout_s = timeout_s
        #: a sample older than this at the tick (kernel arrival -> tick, ns) is not used: the timeout
        self.max_age_ns = int(round(timeout_s * 1e9))
        self.max_force = max_force
        self.hello = hello
        self.t_open = t_open             # receiver clock (monotonic s) at WELCOME
        self.proven = False              # a valid STATE arrived: the client holds the session key
        self.rejected = 0
        self.error = P.E_OK
        self.accepted = 0
        self.lock = threading.Lock()     # guards the latest sample below (held for a copy of a few values)
        self.n = 0                       # samples published so far
        self.s_seq = 0
        self.s_pos = [0.0, 0.0, 0.0]
        self.s_flags = 0
        self.s_buttons = 0
        self.s_quat = [1.0, 0.0, 0.0, 0.0]
        self.s_grasp = 0.0
        self.s_t_client = 0
        self.s_rx_ns = 0                 # kernel arrival of the sample (perf_counter ns; rx_stamps)
        self.seen = 0                    # tick: samples copied so far
        self.last_rx_t = None            # tick: loop time of the newest sample (or of the first tick that saw the session)
        self.has_state = False
        self.seq = 0
        self.t_client_ns = 0
        self.rx_ns = 0                   # tick: arrival of the sample it uses (perf_counter ns)
        self.tx_seq = 0

    def next_tx(self) -> int:
        """The sequence number of the next datagram the service sends in this session."""
        self.tx_seq += 1
        return self.tx_seq

    def publish(self, seq: int, st: P.State, rx_ns: int) -> None:
        """Receiver: make ``st`` (checked; arrived at ``rx_ns``, perf_counter ns) the session's latest sample."""
        p, q = st.position, st.orientation
        with self.lock:
            self.s_seq = seq
            self.s_pos[0], self.s_pos[1], self.s_pos[2] = p[0], p[1], p[2]
            self.s_flags = st.flags
            self.s_buttons = st.buttons
            if st.flags & P.F_ORIENTATION:
                self.s_quat[0], self.s_quat[1], self.s_quat[2], self.s_quat[3] = q[0], q[1], q[2], q[3]
            if st.flags & P.F_GRASP:
                self.s_grasp = st.grasp
            self.s_t_client = st.t_client_ns
            self.s_rx_ns = rx_ns
            self.n += 1
