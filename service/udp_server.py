"""The service side of the wire protocol: authenticated UDP clients as masters of the haptic loop.

``UdpHub`` owns one UDP socket and ``slots`` ``udp_master.UdpMaster`` objects (one per proxy of
the service). See ``clients/PROTOCOL.md``. Two sides, two threads:

* **The receiver**, in two parts. A C thread (``udp_native``, ``native/udp_rx.c``) reads the
  socket with each datagram's kernel arrival time, never taking the interpreter lock. It drops
  floods per source address before any header is read (token buckets, ``source_rate``) and
  applies every STATE that names a live session from that session's own address: of each
  session's STATEs in one read it checks the newest first (window, tag, values) and makes the
  first one accepted the session's latest sample; the older ones are checked after it and
  counted (``superseded`` when authentic), never used. A flood, an operator action or a control
  request that keeps the interpreter busy therefore never delays a device's samples. Every
  other datagram is queued (bounded) for the hub's Python thread, which limits handshakes per
  source and answers handshakes and BYEs in arrival order. Built with ``receiver=False`` the
  owner calls ``pump()`` outside the tick instead, which reads through the same C path.
* **The haptic tick** (``UdpMaster.poll``) takes the newest sample of its slot from the C
  receiver in one compiled call (``pf_rx_take``, native/udp_tick.h: a seqlock it never waits
  on; no socket, no HMAC, no allocation), which decides timeouts in loop time and uses the
  sample only if it reached the socket no longer than the session's timeout before the tick
  (else the master reports ``ok = False``: the arm holds, S9; ``stale_ticks``); it records each
  sample's age (``ages``, status ``state_age_ms``) and sends FEEDBACK through the C receiver
  (``pf_rx_send_arm``: filled from the service's output, tagged, a ``sendto`` that never
  blocks).

Handshake (PROTOCOL.md section 6): a HELLO without a valid cookie is answered with a COOKIE
(``udp_cookies.CookieJar``; no state kept); the HELLO that repeats the cookie opens a session.
A session that has not proved its key with a valid STATE (``proven``) never makes its device
``busy`` and gives up its slot to a new handshake after ``PROOF_S``; a captured HELLO replayed
after its cookie expired, after a restart or inside the validity opens nothing.

A session is locked to the address its handshake came from: a STATE or BYE from any other
address names no session (``no_session``, refused before its tag is computed), so a replay that
overtakes the original cannot move the session. A datagram that is truncated, oversized or
malformed, fails authentication, replays or is older than the newest sample, belongs to no
session of its address, or carries non-finite or out-of-workspace values
is counted (``counters``, per reason) and dropped: it never touches a slot's sample, so it never
changes a robot command. A session silent for longer than its timeout (default 50 ms, measured
in loop time by the tick) is dropped: its master reports ``ok = False``, so the service holds
that arm's robot and ramps its force to zero (``service.app``, hold reason "master input invalid").
"""
from __future__ import annotations

import os
import socket
import threading
import time
from typing import Optional

from pointfence.clients import protocol as P
from pointfence.kernels.errors import InputError

from .age_hist import AgeHistogram
from .held_io import Sender
from .osthread import set_fifo
from .rx_stamps import RCVBUF_BYTES, stamp_socket
from .udp_cookies import CookieJar
from .udp_feedback import FeedbackFields
from .udp_master import UdpMaster
from .udp_native import NOT_MINE, NativeReceiver
from .udp_ratelimit import SourceLimiter
from .udp_session import Session


#: drains per window of the deadline-grid estimate (UdpHub.tick)
BASE_WINDOW = 1000
#: handshakes a source may start per second, and at once: a device needs a few, and each costs
#: the service two MACs and an answer (a flood of replayed HELLOs is dropped before them)
HELLO_RATE, HELLO_BURST = 20.0, 10.0
_TYPE_AT = 3       # offset of the message type in the header (magic 2 bytes, version 1 byte)
#: per source address: datagrams/s on average, at once, and the silence after which its bucket
#: may go to a new source (s)
SOURCE_RATE, SOURCE_BURST, SOURCE_IDLE_S = 4000.0, 400.0, 10.0
#: how long the Python receiver waits for a queued datagram before it looks at its stop flag (ms)
WAIT_MS = 50


class UdpHub:
    """The UDP endpoint of the service: sessions, counters and ``slots`` masters.

    Args:
        psk: the pre-shared key (16 to 64 bytes).
        slots: number of masters (one per proxy; the service is built with ``hub.masters``).
        host, port: where to bind (port 0: any free port, see ``address``).
        timeout_ms: the default and largest session timeout (a client may ask for less).
        rate_hz: the service tick rate, told to clients.
        max_force: the service's force limit, N (the lower of it and the device's is used).
        receiver: run the receiver thread (default); False: the owner calls ``pump()`` itself,
            outside the tick (deterministic tests on a simulated clock).
        source_rate, source_burst: every source address may send this many datagrams/s on
            average, and at once (the C receiver drops the rest before reading any header).
        rcvbuf_bytes: the socket's receive buffer (default ``rx_stamps.RCVBUF_BYTES``: tens of
            milliseconds of traffic, not seconds).
        max_age_ms: a sample that reached the socket longer than this before the tick is not used
            (the master reports ``ok = False``: its arm holds); default: the session's timeout.
            At most MAX_TIMEOUT_MS. (A run on a simulated clock, whose loop time is not the wall
            clock the arrival stamps are on, gives the ceiling.)
    """

    def __init__(self, psk: bytes, slots: int = 1, host: str = "127.0.0.1", port: int = 0,
                 timeout_ms: int = P.DEFAULT_TIMEOUT_MS, rate_hz: float = 1000.0, max_force: float = 10.0,
                 receiver: bool = True, source_rate: float = SOURCE_RATE,
                 source_burst: float = SOURCE_BURST, rcvbuf_bytes: int = RCVBUF_BYTES,
                 max_age_ms: Optional[int] = None):
        self.psk = P.check_key(psk)
        if int(slots) < 1:
            raise InputError(f"slots = {slots}; expected at least one master slot")
        if not 1 <= int(timeout_ms) <= P.MAX_TIMEOUT_MS:
            raise InputError(f"timeout_ms = {timeout_ms}; expected 1..{P.MAX_TIMEOUT_MS}")
        self.timeout_ms = int(timeout_ms)
        if max_age_ms is not None and not 1 <= int(max_age_ms) <= P.MAX_TIMEOUT_MS:
            raise InputError(f"max_age_ms = {max_age_ms}; expected 1..{P.MAX_TIMEOUT_MS} (ms)")
        self.max_age_ms = None if max_age_ms is None else int(max_age_ms)
        self.rate_hz = float(rate_hz)
        self.max_force = float(max_force)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, int(port)))
        self.stamps = stamp_socket(self.sock, rcvbuf_bytes)     # kernel arrival stamps (Linux)
        self.rx = NativeReceiver(self.sock, int(slots))          # every read, and the STATE path, in C
        self.sender = Sender(self.sock)   # the handshake's answers (sends that keep the interpreter lock)
        self.masters = [UdpMaster(self, i) for i in range(int(slots))]
        self._fields = FeedbackFields(len(self.masters))    # every arm's FEEDBACK fields, once a tick
        self.sessions: dict = {}          # session id -> Session
        self.by_device: dict = {}         # device id -> Session
        self.cookies = CookieJar()
        self.rx.limits(source_rate, source_burst, SOURCE_IDLE_S)
        #: handshakes per source (a device needs a few; each costs two MACs and an answer)
        self.hello_limiter = SourceLimiter(rate=HELLO_RATE, burst=HELLO_BURST)
        self._lock = threading.Lock()     # session table changes (receiver: open, BYE; tick: timeout)
        self._buf = bytearray(P.MAX_DATAGRAM)
        self.t = None                     # loop time of the last tick
        self.t_ns = 0                     # its start (perf_counter ns): the "now" of the samples' ages
        self.ages = AgeHistogram()        # ages of the samples the ticks used (kernel arrival -> tick)
        self._base_ns = None              # perf_counter_ns at loop time 0 (tick deadlines): see tick
        self._base_win = [None, None]     # minima of the current and the previous window of ticks
        self._base_n = 0
        self.service = None
        #: rejections counted by this Python side, per reason (``counters`` adds the C receiver's)
        self._counts = {name: 0 for name in P.ERROR_NAMES.values() if name != "ok"}
        self._counts["rate_limited"] = 0
        self.stale_ticks = 0              # master reads whose newest sample was older than the timeout
        self.hellos = 0
        self.cookies_sent = 0
        self.sessions_opened = 0
        self.sessions_dropped = 0         # timeouts
        self.sessions_closed = 0          # BYE
        self.sessions_displaced = 0       # unproven sessions given up to a new handshake
        self.feedback_sent = 0
        self.send_errors = 0
        self._stop = threading.Event()
        self._thread = None
        self.scheduling = "normal"        # the receiver threads' (set_rt_priority)
        if receiver:
            self.rx.start()
            self._thread = threading.Thread(target=self._run, name="pointfence-udp-rx", daemon=True)
            self._thread.start()

    @property
    def counters(self) -> dict:
        """Datagrams refused so far, per reason (the C receiver's and this side's)."""
        rx = self.rx.stats()
        codes = rx["codes"]
        out = dict(self._counts)
        out["rate_limited"] += rx["rate_limited"]
        for code, n in enumerate(codes):
            if n:
                out[P.ERROR_NAMES[code]] += n
        return out

    @property
    def accepted(self) -> int:
        """STATEs accepted as a session's sample."""
        return self.rx.stats()["accepted"]

    @property
    def superseded(self) -> int:
        """Authentic STATEs a newer one of their session beat in the same read."""
        return self.rx.stats()["superseded"]

    @property
    def received(self) -> int:
        """Datagrams read from the socket."""
        return self.rx.stats()["received"]

    @property
    def address(self):
        return self.sock.getsockname()

    def set_rt_priority(self, priority: int) -> str:
        """SCHED_FIFO ``priority`` for both receiver threads where the OS allows it (0: leave them
        normal; ``runner.LiveRun`` gives them the frame threads'). The C thread carries every
        tick's samples: at normal priority on a loaded machine it would wait for a core behind
        other processes. The Python thread holds the interpreter lock while it works: preempted
        with it, it would keep the loop waiting. Both block whenever they have nothing to read.
        Returns what was applied."""
        if self.rx.thread_id is not None:
            self.scheduling = set_fifo(self.rx.thread_id, priority)
        if self._thread is not None and self._thread.is_alive():
            set_fifo(self._thread.native_id, priority)
        return self.scheduling

    def attach(self, service) -> None:
        """The service whose proxies, robots and status go into FEEDBACK messages."""
        self.service = service

    def close(self) -> None:
        """Stop the receiver, end every session (BYE) and close the socket."""
        self._stop.set()
        self.rx.stop()
        if self._thread is not None:
            self._thread.join(2.0)
        if self.sock.fileno() >= 0:
            for s in list(self.sessions.values()):
                self._send(s.addr, P.Bye(P.E_OK).encode(s.key, s.device_id, s.id, s.next_tx()))
                self._end(s)
            self.sock.close()

    # --- receiver (outside the tick) ------------------------------------------------------------------
    def _run(self) -> None:
        """The Python receiver thread: the datagrams the C thread queued (the wait hands the lock over)."""
        buf, nxt = self._buf, self.rx.next
        while not self._stop.is_set():
            got = nxt(buf, WAIT_MS)
            if got is False:
                return
            while got:
                self._apply(buf, got)
                if self._stop.is_set():
                    return
                got = nxt(buf, 0)

    def pump(self, limit: int = 4096) -> int:
        """Without the receiver threads: read what waits in the socket (at most ``limit``
        datagrams) through the C path (STATEs of live sessions applied there, each session's
        newest first) and handle the rest here; returns how many were read."""
        buf, nxt, k = self._buf, self.rx.next, 0
        while k < limit and not self._stop.is_set():
            got = self.rx.poll(limit - k)
            k += got
            item = nxt(buf, 0)
            while item:
                self._apply(buf, item)
                item = nxt(buf, 0)
            if got == 0:
                break
        return k

    def _apply(self, buf, got) -> None:
        """One queued datagram (``got``: size, address, arrival; the C receiver already applied the
        per-source rate limit): handshakes limited per source, then handled in arrival order."""
        n, addr, rx_ns = got
        if n > _TYPE_AT and buf[_TYPE_AT] == P.HELLO and not self.hello_limiter.allow(addr, time.monotonic()):
            self._counts["rate_limited"] += 1
            return
        self.handle(memoryview(buf)[:n], addr, rx_ns)

    def handle(self, data, addr, rx_ns: Optional[int] = None) -> int:
        """Check and apply one datagram from ``addr`` (arrived at ``rx_ns``, perf_counter ns;
        default: now); returns the E_* code (E_OK when accepted)."""
        session = None
        try:
            h = P.parse_header(data)
            typ = h.type
            if typ == P.STATE:      # a live session's own: the C receiver applies and counts it
                code = self.rx.feed(data, addr, time.perf_counter_ns() if rx_ns is None else rx_ns)
                if code != NOT_MINE:
                    return code
                session = self._session_of(h, addr)     # (raises: no session of this address)
                raise P.ProtocolError(P.E_NO_SESSION, "no such session for this device and address")
            if typ == P.HELLO:
                P.verify(data, self.psk)
                try:
                    hello = P.Hello.decode(data)
                except P.ProtocolError as e:   # authentic but unusable: say why
                    self._reject(addr, h.device_id, bytes(data[P.HEADER_LEN:P.HEADER_LEN + 16]), e.code)
                    raise
                self._hello(h, hello, addr)
                return P.E_OK
            if typ == P.BYE:
                session = self._session_of(h, addr)     # (unset if not: no session to count against)
                P.verify(data, session.key)
                session.window.check(h.seq)
                P.Bye.decode(data)
                session.window.commit(h.seq)
                self.sessions_closed += 1
                self._end(session)
                return P.E_OK
            raise P.ProtocolError(P.E_DIRECTION, f"{P.TYPE_NAMES[typ]} is never sent to the service")
        except P.ProtocolError as e:
            self._count(e, session)
            return e.code

    def _session_of(self, h, addr) -> Session:
        """The live session a STATE's or BYE's header names, sent from the address its handshake
        came from (a session is locked to it: an authentic datagram replayed from elsewhere, even
        ahead of the original, cannot move the session or its FEEDBACK); raises
        E_NO_SESSION."""
        session = self.sessions.get(h.session)
        if session is None or session.device_id != h.device_id or session.addr != addr:
            raise P.ProtocolError(P.E_NO_SESSION, "no such session for this device and address")
        return session

    def _count(self, e: P.ProtocolError, session: Optional[Session]) -> None:
        """A rejected datagram: counted per reason, and against its session if it named a live one."""
        self._counts[P.ERROR_NAMES[e.code]] += 1
        if session is not None:
            self.rx.note(session.slot, session.id, e.code)

    def _hello(self, h, hello: P.Hello, addr) -> None:
        self.hellos += 1
        dev, nonce = h.device_id, hello.nonce
        if not hello.has_cookie:
            self._send_cookie(addr, dev, nonce)
            return
        try:
            t_issue = self.cookies.check(hello.cookie, addr, dev, nonce)
        except P.ProtocolError:
            self._send_cookie(addr, dev, nonce)      # expired or foreign: a fresh challenge (no session)
            raise
        with self._lock:
            self.cookies.consume(nonce, t_issue)     # a cookie'd HELLO counts once: a replay is E_REPLAY, unanswered
        now = time.monotonic()
        with self._lock:
            old = self.by_device.get(dev)
            if old is not None and old.proven:
                code, why = P.E_BUSY, f"device {dev} already has session {old.id}"
            else:
                code, why = P.E_OK, ""
                slot = old.slot if old is not None else next((m.slot for m in self.masters if m.session is None), None)
                if slot is None:
                    slot = self._displace(now)
                if slot is None:
                    code, why = P.E_FULL, f"all {len(self.masters)} slots in use"
            if code == P.E_OK:
                if old is not None:                  # an unproven session of this device: a new handshake wins
                    self.sessions_displaced += 1
                    self._end_locked(old)
                s, server_nonce = self._open(dev, hello, addr, slot, now)
        if code != P.E_OK:
            self._reject(addr, dev, nonce, code)
            raise P.ProtocolError(code, why)
        w = P.Welcome(nonce, server_nonce, slot, round(s.timeout_s * 1000), self.rate_hz, s.max_force,
                      time.perf_counter_ns())
        self._send(addr, w.encode(self.psk, dev, s.id, 0))

    def _displace(self, now: float):
        """The slot of the oldest session that never proved its key within PROOF_S (or None)."""
        victim = None
        for m in self.masters:
            s = m.session
            if isinstance(s, Session) and not s.proven and now - s.t_open > P.PROOF_S:
                if victim is None or s.t_open < victim.t_open:
                    victim = s
        if victim is None:
            return None
        self.sessions_displaced += 1
        self._end_locked(victim)
        return victim.slot

    def _open(self, dev: int, hello: P.Hello, addr, slot: int, now: float):
        """A new (unproven) session on ``slot``: (Session, server nonce). Called under the lock."""
        sid = 0
        while sid == 0 or sid in self.sessions:
            sid = int.from_bytes(os.urandom(4), "little")
        server_nonce = os.urandom(16)
        key = P.session_key(self.psk, hello.nonce, server_nonce, dev, sid)
        tmo = min(hello.timeout_ms or self.timeout_ms, self.timeout_ms)
        s = Session(sid, dev, slot, key, addr, hello, tmo / 1000.0, min(hello.max_force, self.max_force), now, self.rx)
        if self.max_age_ms is not None:
            s.max_age_ns = self.max_age_ms * 1_000_000
        self.rx.open(slot, sid, dev, key, addr, hello.workspace_min, hello.workspace_max, s.max_force)  # before WELCOME
        self.sessions[sid] = s
        self.by_device[dev] = s
        self.masters[slot].session = s
        self.sessions_opened += 1
        return s, server_nonce

    def _send_cookie(self, addr, dev: int, nonce: bytes) -> None:
        self.cookies_sent += 1
        self._send(addr, P.Cookie(nonce, self.cookies.issue(addr, dev, nonce)).encode(self.psk, dev, 0))

    def _reject(self, addr, device_id, nonce, code) -> None:
        self._send(addr, P.Reject(nonce, code).encode(self.psk, device_id, 0))

    def _end(self, s: Session) -> None:
        with self._lock:
            self._end_locked(s)

    def _end_locked(self, s: Session) -> None:
        self.sessions.pop(s.id, None)
        if self.by_device.get(s.device_id) is s:
            del self.by_device[s.device_id]
        m = self.masters[s.slot]
        if m.session is s:
            m.session = None
        self.rx.close(s.slot, s.id)

    # --- the tick ------------------------------------------------------------------------------------
    def tick(self, t: float) -> None:
        """Once per tick (by the first master polled): the deadline grid's origin for FEEDBACK."""
        self.t = t
        self.t_ns = now = time.perf_counter_ns()
        # the deadline grid's origin: tick time minus loop time, at its minimum (the least late
        # tick). A windowed minimum (the last 1,000 to 2,000 ticks), so that a poll outside the
        # loop's timeline (the service's start-up poll at loop time 0, before the first tick;
        # measured 32 ms early) cannot shift the clients' phase lock for good.
        base = now - int(round(t * 1e9))
        w = self._base_win
        if w[0] is None or base < w[0]:
            w[0] = base
        self._base_n += 1
        if self._base_n >= BASE_WINDOW:
            w[1], w[0], self._base_n = w[0], None, 0
        self._base_ns = w[0] if w[1] is None else (w[1] if w[0] is None else min(w[0], w[1]))

    def drop(self, s: Session) -> None:
        """The tick: session ``s`` was silent longer than its timeout (loop time)."""
        self._counts["timeout"] += 1
        self.sessions_dropped += 1
        self._end(s)

    def _send(self, addr, data: bytes) -> None:
        if not self.sender.send(addr, data):
            self.send_errors += 1

    def send_feedback(self, m: UdpMaster, s: Session, force) -> None:
        """The tick: FEEDBACK to ``m``'s session, force ``force`` (a pointer to the master's 3
        doubles, N, master frame), with its arm's state from the service's output of this tick
        (``udp_feedback.FeedbackFields``), filled and sent by the C receiver (tagged with the
        session's key; a send that never blocks)."""
        t = self.t or 0.0
        src = self._fields.of(self.service, int(round(t * self.rate_hz)), (self._base_ns or 0) + int(round(t * 1e9)),
                              self.t_ns)
        if self.rx.send_arm(m.slot, s.take_ref, src, force) > 0:
            self.feedback_sent += 1
        else:
            self.send_errors += 1

    # --- status -------------------------------------------------------------------------------------
    def status(self) -> dict:
        rx, counters = self.rx.stats(), self.counters
        return {
            "address": list(self.address) if self.sock.fileno() >= 0 else None,
            "slots": len(self.masters),
            "sessions": [{"session": s.id, "device_id": s.device_id, "slot": s.slot, "model": s.hello.model,
                          "proven": s.proven, "accepted": s.accepted, "rejected": s.rejected,
                          "timeout_ms": round(s.timeout_s * 1000)}
                         for s in list(self.sessions.values())],
            "accepted": rx["accepted"], "received": rx["received"], "hellos": self.hellos,
            "cookies_sent": self.cookies_sent, "sessions_opened": self.sessions_opened,
            "sessions_timed_out": self.sessions_dropped, "sessions_closed": self.sessions_closed,
            "sessions_displaced": self.sessions_displaced, "feedback_sent": self.feedback_sent,
            "send_errors": self.send_errors, "receiver": "thread" if self._thread is not None else "pump",
            "receiver_scheduling": self.scheduling,
            "rate_limited_sources": rx["sources"], "rate_limit_overflow": rx["overflowed"],
            "rejected": counters, "rejected_total": sum(v for k, v in counters.items() if k != "timeout"),
            "superseded": rx["superseded"], "stale_ticks": self.stale_ticks, "kernel_dropped": rx["kernel_dropped"],
            "queue_dropped": rx["queue_dropped"],
            "rcvbuf_bytes": self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) if self.sock.fileno() >= 0 else None,
            "state_age_ms": self.ages.summary(),
        }
