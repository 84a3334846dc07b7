"""The service side of the wire protocol: authenticated UDP clients as masters of the haptic loop.

``UdpHub`` owns one UDP socket and ``slots`` :class:`UdpMaster` objects (one per proxy of the
service). A client's HELLO (tagged with the pre-shared key) opens a session on a free slot; its
STATE messages (tagged with the session key) drive that slot's master; every tick the slot's
force goes back in a FEEDBACK message. See ``clients/PROTOCOL.md``.

The socket is drained inside the haptic tick, by the first master polled on a new tick (at most
``budget`` datagrams per tick; the rest wait for the next tick): no receiver thread competes
with the loop for the interpreter, and a sample that arrives just before a tick is used by it.

A datagram that is truncated, oversized or malformed, fails authentication, replays or is older
than the newest sample, belongs to no session, or carries non-finite or out-of-workspace values
is counted (``counters``, per reason) and dropped: it never touches a slot's sample, so it never
changes a robot command. A session silent for longer than its timeout (default 50 ms, measured
in loop time) is dropped: its master reports ``ok = False``, so the service holds that arm's
robot and ramps its force to zero (``service.app``, hold reason "master input invalid").
"""
from __future__ import annotations

import collections
import os
import socket
import time
from typing import Optional

import numpy as np

from pointfence.clients import protocol as P
from pointfence.kernels.errors import InputError

from .masters import Master


class Session:
    """One authenticated client bound to a slot."""

    __slots__ = ("id", "device_id", "slot", "key", "addr", "window", "workspace", "timeout_s", "max_force",
                 "last_rx_t", "has_state", "seq", "t_client_ns", "tx_seq", "rejected", "error", "hello",
                 "accepted")

    def __init__(self, sid, device_id, slot, key, addr, hello: P.Hello, timeout_s, max_force, t):
        self.id = sid
        self.device_id = device_id
        self.slot = slot
        self.key = key
        self.addr = addr
        self.window = P.ReplayWindow()
        self.workspace = (hello.workspace_min, hello.workspace_max)
        self.timeout_s = timeout_s
        self.max_force = max_force
        self.last_rx_t = t
        self.has_state = False
        self.seq = 0
        self.t_client_ns = 0
        self.tx_seq = 0
        self.rejected = 0
        self.error = P.E_OK
        self.hello = hello
        self.accepted = 0


#: drains per window of the deadline-grid estimate (UdpHub.drain)
BASE_WINDOW = 1000


class UdpMaster(Master):
    """Slot ``slot`` of a :class:`UdpHub`: the master of one proxy, driven by whichever client
    holds the slot (``ok`` is False while no fresh authenticated sample exists)."""

    name = "udp"

    def __init__(self, hub: "UdpHub", slot: int):
        super().__init__()
        self.hub = hub
        self.slot = slot
        self.name = f"udp{slot}"
        self.ok = False
        self.clutch = False
        self.orientation = np.array([1.0, 0.0, 0.0, 0.0])
        self.grasp = 0.0
        self.session: Optional[Session] = None

    def poll(self, t: float) -> None:
        hub = self.hub
        if t != hub.t:
            hub.drain(t)
        s = self.session
        self.ok = s is not None and s.has_state

    def send_force(self, f: np.ndarray) -> None:
        self.force[:] = f
        s = self.session
        if s is not None and s.has_state:
            self.hub.send_feedback(self, s, f)


class UdpHub:
    """The UDP endpoint of the service: sessions, counters and ``slots`` masters.

    Args:
        psk: the pre-shared key (16 to 64 bytes).
        slots: number of masters (one per proxy; the service is built with ``hub.masters``).
        host, port: where to bind (port 0: any free port, see ``address``).
        timeout_ms: the default and largest session timeout (a client may ask for less).
        rate_hz: the service tick rate, told to clients.
        max_force: the service's force limit, N (the lower of it and the device's is used).
        budget: datagrams handled per tick at most.
    """

    def __init__(self, psk: bytes, slots: int = 1, host: str = "127.0.0.1", port: int = 0,
                 timeout_ms: int = P.DEFAULT_TIMEOUT_MS, rate_hz: float = 1000.0, max_force: float = 10.0,
                 budget: int = 64):
        self.psk = P.check_key(psk)
        if int(slots) < 1:
            raise InputError(f"slots = {slots}; expected at least one master slot")
        if not 1 <= int(timeout_ms) <= P.MAX_TIMEOUT_MS:
            raise InputError(f"timeout_ms = {timeout_ms}; expected 1..{P.MAX_TIMEOUT_MS}")
        self.timeout_ms = int(timeout_ms)
        self.rate_hz = float(rate_hz)
        self.max_force = float(max_force)
        self.budget = int(budget)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        except OSError:
            pass
        self.sock.bind((host, int(port)))
        self.sock.setblocking(False)
        self.masters = [UdpMaster(self, i) for i in range(int(slots))]
        self.sessions: dict = {}          # session id -> Session
        self.by_device: dict = {}         # device id -> Session
        self._nonces = collections.OrderedDict()   # recent HELLO nonces (replayed HELLOs are refused)
        self._buf = bytearray(P.MAX_DATAGRAM)
        self._view = memoryview(self._buf)
        self.t = None                     # loop time of the last drain
        self._base_ns = None              # perf_counter_ns at loop time 0 (tick deadlines): see drain
        self._base_win = [None, None]     # minima of the current and the previous window of drains
        self._base_n = 0
        self.service = None
        self.counters = {name: 0 for name in P.ERROR_NAMES.values() if name != "ok"}
        self.accepted = 0                 # STATE messages applied
        self.hellos = 0
        self.sessions_opened = 0
        self.sessions_dropped = 0         # timeouts
        self.sessions_closed = 0          # BYE
        self.feedback_sent = 0
        self.send_errors = 0

    @property
    def address(self):
        return self.sock.getsockname()

    def attach(self, service) -> None:
        """The service whose proxies, robots and status go into FEEDBACK messages."""
        self.service = service

    def close(self) -> None:
        for s in list(self.sessions.values()):
            self._send(s.addr, P.Bye(P.E_OK).encode(s.key, s.device_id, s.id, self._next_tx(s)))
            self._end(s)
        self.sock.close()

    # --- receive (in the tick) --------------------------------------------------------------------
    def drain(self, t: float) -> None:
        """Handle waiting datagrams (at most ``budget``), then drop silent sessions."""
        self.t = t
        now_ns = time.perf_counter_ns()
        # the deadline grid's origin: drain time minus loop time, at its minimum (the least late
        # tick). A windowed minimum (the last 1,000 to 2,000 drains), so that a drain outside the
        # loop's timeline (the service's start-up poll at loop time 0, before the first tick;
        # measured 32 ms early) cannot shift the clients' phase lock for good.
        base = now_ns - int(round(t * 1e9))
        w = self._base_win
        if w[0] is None or base < w[0]:
            w[0] = base
        self._base_n += 1
        if self._base_n >= BASE_WINDOW:
            w[1], w[0], self._base_n = w[0], None, 0
        self._base_ns = w[0] if w[1] is None else (w[1] if w[0] is None else min(w[0], w[1]))
        sock, buf = self.sock, self._buf
        for _ in range(self.budget):
            try:
                n, addr = sock.recvfrom_into(buf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:      # e.g. ICMP port unreachable reported on a UDP socket
                continue
            self.handle(self._view[:n], addr, t)
        for s in list(self.sessions.values()):
            if t - s.last_rx_t > s.timeout_s:
                self.counters["timeout"] += 1
                self.sessions_dropped += 1
                self._end(s)

    def handle(self, data, addr, t: float) -> int:
        """Check and apply one datagram; returns the E_* code (E_OK when accepted)."""
        session = None
        try:
            h = P.parse_header(data)
            typ = h.type
            if typ == P.STATE:
                session = self.sessions.get(h.session)
                if session is None or session.device_id != h.device_id:
                    session = None
                    raise P.ProtocolError(P.E_NO_SESSION)
                P.verify(data, session.key)
                session.window.check(h.seq)
                st = P.State.decode(data, session.workspace)
                if not session.window.commit(h.seq):
                    raise P.ProtocolError(P.E_STALE, "older than the newest sample")
                self._apply(session, h, st, addr, t)
                return P.E_OK
            if typ == P.HELLO:
                P.verify(data, self.psk)
                try:
                    hello = P.Hello.decode(data)
                except P.ProtocolError as e:   # authentic but unusable: say why
                    self._reject(addr, h.device_id, bytes(data[P.HEADER_LEN:P.HEADER_LEN + 16]), e.code)
                    raise
                self._hello(h, hello, addr, t)
                return P.E_OK
            if typ == P.BYE:
                session = self.sessions.get(h.session)
                if session is None or session.device_id != h.device_id:
                    session = None
                    raise P.ProtocolError(P.E_NO_SESSION)
                P.verify(data, session.key)
                session.window.check(h.seq)
                P.Bye.decode(data)
                session.window.commit(h.seq)
                self.sessions_closed += 1
                self._end(session)
                return P.E_OK
            raise P.ProtocolError(P.E_DIRECTION, f"{P.TYPE_NAMES[typ]} is never sent to the service")
        except P.ProtocolError as e:
            self.counters[P.ERROR_NAMES[e.code]] += 1
            if session is not None:
                session.rejected += 1
                session.error = e.code
            return e.code

    def _apply(self, s: Session, h, st: P.State, addr, t: float) -> None:
        m = self.masters[s.slot]
        m.position[0], m.position[1], m.position[2] = st.position
        m.clutch = bool(st.flags & P.F_CLUTCH)
        m.buttons = st.buttons
        if st.flags & P.F_ORIENTATION:
            m.orientation[:] = st.orientation
        if st.flags & P.F_GRASP:
            m.grasp = st.grasp
        s.has_state = True
        s.seq = h.seq
        s.t_client_ns = st.t_client_ns
        s.last_rx_t = t
        s.addr = addr
        s.accepted += 1
        self.accepted += 1

    def _hello(self, h, hello: P.Hello, addr, t: float) -> None:
        self.hellos += 1
        if hello.nonce in self._nonces:
            raise P.ProtocolError(P.E_REPLAY, "HELLO nonce already used")
        self._nonces[hello.nonce] = None
        if len(self._nonces) > 4096:
            self._nonces.popitem(last=False)
        old = self.by_device.get(h.device_id)
        if old is not None:
            self._reject(addr, h.device_id, hello.nonce, P.E_BUSY)
            raise P.ProtocolError(P.E_BUSY, f"device {h.device_id} already has session {old.id}")
        slot = next((m.slot for m in self.masters if m.session is None), None)
        if slot is None:
            self._reject(addr, h.device_id, hello.nonce, P.E_FULL)
            raise P.ProtocolError(P.E_FULL, f"all {len(self.masters)} slots in use")
        sid = 0
        while sid == 0 or sid in self.sessions:
            sid = int.from_bytes(os.urandom(4), "little")
        server_nonce = os.urandom(16)
        key = P.session_key(self.psk, hello.nonce, server_nonce, h.device_id, sid)
        tmo = min(hello.timeout_ms or self.timeout_ms, self.timeout_ms)
        fmax = min(hello.max_force, self.max_force)
        s = Session(sid, h.device_id, slot, key, addr, hello, tmo / 1000.0, fmax, t)
        self.sessions[sid] = s
        self.by_device[h.device_id] = s
        m = self.masters[slot]
        m.session = s
        m.ok = False
        self.sessions_opened += 1
        w = P.Welcome(hello.nonce, server_nonce, slot, tmo, self.rate_hz, fmax, time.perf_counter_ns())
        self._send(addr, w.encode(self.psk, h.device_id, sid, 0))

    def _reject(self, addr, device_id, nonce, code) -> None:
        self._send(addr, P.Reject(nonce, code).encode(self.psk, device_id, 0))

    def _end(self, s: Session) -> None:
        self.sessions.pop(s.id, None)
        if self.by_device.get(s.device_id) is s:
            del self.by_device[s.device_id]
        m = self.masters[s.slot]
        if m.session is s:
            m.session = None
            m.ok = False
            m.clutch = False

    # --- send (in the tick) -----------------------------------------------------------------------------
    def _next_tx(self, s: Session) -> int:
        s.tx_seq += 1
        return s.tx_seq

    def _send(self, addr, data: bytes) -> None:
        try:
            self.sock.sendto(data, addr)
        except OSError:
            self.send_errors += 1

    def send_feedback(self, m: UdpMaster, s: Session, f) -> None:
        fx, fy, fz = float(f[0]), float(f[1]), float(f[2])
        if not (np.isfinite(fx) and np.isfinite(fy) and np.isfinite(fz)):
            fx = fy = fz = 0.0
        n2 = fx * fx + fy * fy + fz * fz
        if n2 > s.max_force * s.max_force:
            k = s.max_force / n2 ** 0.5
            fx, fy, fz = fx * k, fy * k, fz * k
        b = m.slot
        t = self.t or 0.0
        fb = P.Feedback(tick=int(round(t * self.rate_hz)), t_tick_ns=(self._base_ns or 0) + int(round(t * 1e9)),
                        echo_seq=s.seq, echo_t_client_ns=s.t_client_ns, force=(fx, fy, fz), slot=b,
                        error=s.error, rejected=s.rejected)
        svc = self.service
        if svc is not None:
            batch = svc.batch
            if batch is not None:
                fb.proxy = tuple(float(v) for v in batch.positions[b])
                fb.contact = int(batch.states[b])
            fb.robot = tuple(float(v) for v in svc.xr[b])
            r = svc.robots[b]
            fb.robot_mode = P.ROBOT_IDEAL if r is None else (P.ROBOT_ENABLED, P.ROBOT_HOLDING, P.ROBOT_FAULT)[int(r.state)]
            fb.hold = int(svc.arm_hold[b])
            fb.fixture = ((P.FX_HAPTICS if svc.haptics_on else 0) | (P.FX_TELEOP if svc.teleop_on else 0)
                          | (P.FX_COUPLED if svc.coupled[b] else 0) | (P.FX_FIXTURE if svc.cfg.mode == "fixture" else 0))
        fb.t_sent_ns = time.perf_counter_ns()
        self._send(s.addr, fb.encode(s.key, s.device_id, s.id, self._next_tx(s)))
        self.feedback_sent += 1

    # --- status -------------------------------------------------------------------------------------
    def status(self) -> dict:
        return {
            "address": list(self.address) if self.sock.fileno() >= 0 else None,
            "slots": len(self.masters),
            "sessions": [{"session": s.id, "device_id": s.device_id, "slot": s.slot, "model": s.hello.model,
                          "accepted": s.accepted, "rejected": s.rejected, "timeout_ms": round(s.timeout_s * 1000)}
                         for s in self.sessions.values()],
            "accepted": self.accepted, "hellos": self.hellos, "sessions_opened": self.sessions_opened,
            "sessions_timed_out": self.sessions_dropped, "sessions_closed": self.sessions_closed,
            "feedback_sent": self.feedback_sent, "send_errors": self.send_errors,
            "rejected": dict(self.counters), "rejected_total": sum(v for k, v in self.counters.items() if k != "timeout"),
        }
