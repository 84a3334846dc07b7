"""The Python client SDK: a haptic device as a master of a pointfence service.

Two ways to use it::

    from pointfence.clients import Client, Command

    with Client("127.0.0.1", 47800, key, device_id=7, max_force=3.3,
                workspace=((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1))) as c:
        c.connect()
        # 1. your own loop: send a sample, read the force
        c.send_state(device.position(), clutch=device.pedal())
        fb = c.poll()                  # newest FEEDBACK (or None); c.force is zero when stale
        device.set_force(c.force)

        # 2. libfranka style: one callback per tick, the SDK keeps the timing contract
        def tick(t):                   # t: Tick (index, time, period, force, feedback, ...)
            device.set_force(t.force)
            return Command(device.position(), clutch=device.pedal())   # finished=True ends
        c.control(tick)

``control`` runs the callback once per tick at the device rate, phase-locked to the service's
ticks so that each sample arrives just before the tick that uses it (``lead_us`` ahead). It
raises :class:`TimingError` when the callback (or the process) breaks the timing contract
(``late_limit`` consecutive ticks later than a period), :class:`LinkLost` when the service is
silent for longer than the session timeout (the force is zero from then on), and passes the
callback's own exceptions through after closing the session. Forces are in the master frame, N;
positions in the master frame, m.
"""
from __future__ import annotations

import os
import socket
import struct
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from pointfence.kernels.errors import PointfenceError

_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)   # Linux; == SCM_TIMESTAMPNS
_TIMESPEC = struct.Struct("@qq")
_ANC_SIZE = socket.CMSG_SPACE(16) if hasattr(socket, "CMSG_SPACE") else 64


def realtime_minus_perf_ns() -> int:
    """CLOCK_REALTIME minus ``time.perf_counter_ns`` (ns), read between two perf_counter readings; the
    narrowest of a few tries. A thread preempted between two plain reads would get an offset
    wrong by the preemption, and one such early arrival time would spoil the minimum transit the
    phase lock keeps (the device loop then sends its samples far too early)."""
    best_w, best = None, 0
    for _ in range(4):
        m0 = time.perf_counter_ns()
        r = time.time_ns()
        m1 = time.perf_counter_ns()
        if best_w is None or m1 - m0 < best_w:
            best_w, best = m1 - m0, r - (m0 + m1) // 2
        if best_w < 20_000:
            break
    return best

from . import protocol as P

RING = 4096


class ClientError(PointfenceError, RuntimeError):
    """Base class of the client SDK's errors."""


class Rejected(ClientError):
    """The service refused the HELLO (``code``: busy, full, capability, ...)."""

    def __init__(self, code: int):
        self.code = code
        super().__init__(f"the service refused the session: {P.ERROR_NAMES.get(code, code)}")


class LinkLost(ClientError):
    """No feedback for longer than the session timeout: the force is zero, the robot holds."""


class TimingError(ClientError):
    """The per-tick timing contract was broken (callback or process too slow)."""


@dataclass
class Command:
    """What a control callback returns: the device's sample for this tick."""

    position: Sequence[float]
    clutch: bool = True
    orientation: Optional[Sequence[float]] = None     # w, x, y, z
    grasp: Optional[float] = None
    buttons: int = 0
    finished: bool = False


@dataclass
class Tick:
    """What a control callback receives."""

    index: int                       # tick number since control() started
    time: float                      # s since control() started
    period: float                    # s since the previous tick started
    force: np.ndarray                # N, master frame (zero when no fresh feedback)
    feedback: Optional[P.Feedback]   # newest FEEDBACK (None before the first)
    fresh: bool                      # feedback within the session timeout


@dataclass
class LinkStats:
    sent: int = 0
    echoed: int = 0
    feedback: int = 0
    rejected_in: int = 0             # datagrams this client dropped (bad tag, replay, ...)
    rtt_us: list = field(default_factory=list)
    #: per answered state: its send -> the deadline of the service tick that answered it (us, on
    #: this client's clock); about ``lead_us`` when the state made the tick it was sent for
    answer_lead_us: list = field(default_factory=list)


class Client:
    """One haptic device's link to the service (see the module docstring).

    Args:
        host, port: the service (``pointfence serve``).
        key: the pre-shared key (bytes) or a key file path.
        device_id: this device's id (unique among the service's clients).
        max_force: the device's force limit, N.
        workspace: ((min x, y, z), (max x, y, z)) of the device, master frame, m.
        rate_hz: the rate this client sends at.
        timeout_ms: session timeout asked for (the service may lower it).
        caps: capability bits (``protocol.CAP_*``).
        model: device model, ASCII, up to 16 characters.
    """

    def __init__(self, host: str, port: int, key, device_id: int, *, max_force: float = 3.3,
                 workspace=((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1)), rate_hz: float = 1000.0,
                 timeout_ms: int = P.DEFAULT_TIMEOUT_MS, caps: int = P.CAP_FORCE | P.CAP_CLUTCH, model: str = "python"):
        self.psk = P.check_key(key) if isinstance(key, (bytes, bytearray)) else P.load_key(key)
        self.addr = (socket.gethostbyname(host), int(port))
        self.device_id = int(device_id)
        self.hello = P.Hello(b"", float(max_force), tuple(workspace[0]), tuple(workspace[1]), float(rate_hz),
                             int(timeout_ms), int(caps), model)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(self.addr)        # only the service's datagrams arrive
        self.sock.setblocking(False)
        self._buf = bytearray(P.MAX_DATAGRAM)
        self._view = memoryview(self._buf)
        # kernel receive timestamps (Linux SO_TIMESTAMPNS): a FEEDBACK's arrival time is when it
        # reached this host, not when the device loop got round to reading it (once per tick)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            self._kernel_stamps = sys.platform.startswith("linux")
        except OSError:
            self._kernel_stamps = False
        self.session = 0
        self.key = b""
        self.welcome: Optional[P.Welcome] = None
        self.window = P.ReplayWindow()
        self.seq = 0
        self._prev = None
        self.feedback: Optional[P.Feedback] = None
        self.force = np.zeros(3)
        self.last_rx_ns = 0
        self.timeout_ns = int(timeout_ms) * 1_000_000
        self._sent_ns = np.zeros(RING, np.int64)
        self._sent_seq = np.zeros(RING, np.int64)
        self._echo = 0
        self._off_ns = None                 # min(recv - sent): clock offset + shortest transit
        self.scheduling = "normal"          # of the thread in control() (see its rt_priority)
        self.last_datagram = b""
        #: the HELLOs of the latest handshake as sent (a captured handshake, for attack tests)
        self.hellos_sent: list = []
        self.stats = LinkStats()

    # --- session ------------------------------------------------------------------------------------
    def connect(self, timeout: float = 5.0, retry: float = 0.1) -> P.Welcome:
        """Handshake: HELLO (fresh nonce), the service's COOKIE, HELLO again with the cookie, then
        WELCOME or REJECT; restarted with a fresh nonce every ``retry`` s, until ``timeout`` s."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.hello_send()
            w = self.hello_wait(min(retry, max(0.0, end - time.monotonic())))
            if w is not None:
                return w
        raise ClientError(f"no answer from the service at {self.addr[0]}:{self.addr[1]} within {timeout} s "
                          "(is `pointfence serve` running there, with the same key and protocol version "
                          f"{P.VERSION}?)")

    def hello_send(self) -> bytes:
        """Start a handshake: send a HELLO with a fresh nonce and no cookie; returns the nonce."""
        self._nonce = os.urandom(16)
        self.hellos_sent = []
        self.hello.nonce = self._nonce
        self.hello.cookie = bytes(P.COOKIE_LEN)
        self._send_hello()
        return self._nonce

    def _send_hello(self) -> None:
        self._hellos = getattr(self, "_hellos", 0) + 1
        data = self.hello.encode(self.psk, self.device_id, self._hellos)
        self.hellos_sent.append(data)
        try:
            self.sock.send(data)
        except OSError:
            pass

    def hello_wait(self, timeout: float) -> Optional[P.Welcome]:
        """Wait up to ``timeout`` s for the answer to the current handshake: a COOKIE for its
        nonce is answered at once (the HELLO again, with the cookie) and waiting goes on; returns
        the WELCOME (session set up), None (no answer yet), or raises :class:`Rejected`."""
        nonce = self._nonce
        until = time.monotonic() + timeout
        while True:
            data = self._recv_wait(until - time.monotonic())
            if data is not None:
                try:
                    h = P.parse_header(data)
                    if h.type not in (P.WELCOME, P.REJECT, P.COOKIE) or h.device_id != self.device_id:
                        raise P.ProtocolError(P.E_DIRECTION)
                    P.verify(data, self.psk)
                    if h.type == P.COOKIE:
                        ck = P.Cookie.decode(data)
                        if ck.client_nonce != nonce:
                            raise P.ProtocolError(P.E_STALE)
                        self.hello.cookie = ck.cookie
                        self._send_hello()
                        continue
                    if h.type == P.REJECT:
                        r = P.Reject.decode(data)
                        if r.client_nonce == nonce:
                            raise Rejected(r.error)
                        raise P.ProtocolError(P.E_STALE)
                    w = P.Welcome.decode(data)
                    if w.client_nonce != nonce:
                        raise P.ProtocolError(P.E_STALE)
                except P.ProtocolError:
                    self.stats.rejected_in += 1
                else:
                    self._start_session(h.session, nonce, w)
                    return w
            if time.monotonic() >= until:
                return None

    def _start_session(self, session: int, nonce: bytes, w: P.Welcome) -> None:
        self.session = session
        self.key = P.session_key(self.psk, nonce, w.server_nonce, self.device_id, session)
        self.welcome = w
        self.timeout_ns = w.timeout_ms * 1_000_000
        self.window = P.ReplayWindow()
        self.seq = 0
        self._prev = None
        self.feedback = None
        self._echo = 0
        self._off_ns = None
        self.force[:] = 0.0
        self.last_rx_ns = time.perf_counter_ns()

    def _recv_wait(self, timeout: float):
        if timeout <= 0:
            try:
                n = self.sock.recv_into(self._buf)
                return bytes(self._view[:n])
            except OSError:
                return None
        self.sock.settimeout(timeout)
        try:
            n = self.sock.recv_into(self._buf)
            return bytes(self._view[:n])
        except OSError:      # timeout, would block, ICMP refused
            return None
        finally:
            self.sock.setblocking(False)

    @property
    def connected(self) -> bool:
        return self.session != 0

    def close(self) -> None:
        """End the session (BYE) and close the socket; the force is zero."""
        if self.session:
            try:
                self.seq += 1
                self.sock.send(P.Bye(P.E_OK).encode(self.key, self.device_id, self.session, self.seq))
            except OSError:
                pass
            self.session = 0
        self.force[:] = 0.0
        self.sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # --- samples and forces --------------------------------------------------------------------------
    def send_state(self, position, *, clutch: bool = True, orientation=None, grasp=None, buttons: int = 0,
                   now_ns: Optional[int] = None) -> int:
        """Send one sample (master frame, m); returns its sequence number. Increments are computed
        from the previous sample (zero for the first)."""
        if not self.session:
            raise ClientError("not connected: call connect() first")
        pos = (float(position[0]), float(position[1]), float(position[2]))
        prev = self._prev if self._prev is not None else pos
        inc = (pos[0] - prev[0], pos[1] - prev[1], pos[2] - prev[2])
        self._prev = pos
        flags = (P.F_CLUTCH if clutch else 0) | (P.F_ORIENTATION if orientation is not None else 0) | \
                (P.F_GRASP if grasp is not None else 0)
        fb = self.feedback
        self.seq += 1
        t = time.perf_counter_ns() if now_ns is None else now_ns
        st = P.State(t, fb.t_sent_ns if fb is not None else 0, pos, inc,
                     tuple(orientation) if orientation is not None else (1.0, 0.0, 0.0, 0.0),
                     float(grasp) if grasp is not None else 0.0, int(buttons), flags)
        data = st.encode(self.key, self.device_id, self.session, self.seq)
        i = self.seq & (RING - 1)
        self._sent_ns[i] = t
        self._sent_seq[i] = self.seq
        try:
            self.sock.send(data)
        except OSError:          # ICMP unreachable from an earlier datagram; UDP is lossy anyway
            pass
        self.last_datagram = data
        self.stats.sent += 1
        return self.seq

    def poll(self) -> Optional[P.Feedback]:
        """Read every waiting FEEDBACK (never blocks); returns the newest new one, or None.
        Keeps ``force`` (zeroed once feedback is older than the timeout)."""
        newest = None
        stamps = self._kernel_stamps
        rt_minus_mono = None
        while True:
            try:
                if stamps:
                    n, anc, _, _ = self.sock.recvmsg_into([self._buf], _ANC_SIZE)
                else:
                    n = self.sock.recv_into(self._buf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                continue
            now = time.perf_counter_ns()
            if stamps:
                for level, kind, raw in anc:
                    if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(raw) >= 16:
                        sec, nsec = _TIMESPEC.unpack_from(raw)
                        # the stamp is CLOCK_REALTIME: move it to this process's monotonic clock
                        if rt_minus_mono is None:
                            rt_minus_mono = realtime_minus_perf_ns()
                        now = min(now, sec * 1_000_000_000 + nsec - rt_minus_mono)
            fb = self._accept(self._view[:n], now)
            if fb is not None:
                newest = fb
        if time.perf_counter_ns() - self.last_rx_ns > self.timeout_ns:
            self.force[:] = 0.0
        return newest

    def _accept(self, data, now: int) -> Optional[P.Feedback]:
        try:
            h = P.parse_header(data)
            if h.session != self.session or h.device_id != self.device_id or not self.session:
                raise P.ProtocolError(P.E_NO_SESSION)
            if h.type == P.BYE:
                P.verify(data, self.key)
                self.window.check(h.seq)
                self.window.commit(h.seq)
                self.session = 0
                self.force[:] = 0.0
                raise LinkLost("the service ended the session")
            if h.type != P.FEEDBACK:
                raise P.ProtocolError(P.E_DIRECTION)
            P.verify(data, self.key)
            self.window.check(h.seq)
            if not self.window.commit(h.seq):
                raise P.ProtocolError(P.E_STALE)
            fb = P.Feedback.decode(data)
        except P.ProtocolError:
            self.stats.rejected_in += 1
            return None
        self.feedback = fb
        self.last_rx_ns = now
        self.force[:] = fb.force
        self.stats.feedback += 1
        off = now - fb.t_sent_ns
        if self._off_ns is None or off < self._off_ns:
            self._off_ns = off
        if fb.echo_seq > self._echo:
            self._echo = fb.echo_seq
            i = fb.echo_seq & (RING - 1)
            if self._sent_seq[i] == fb.echo_seq:
                self.stats.echoed += 1
                sent = int(self._sent_ns[i])
                self.stats.rtt_us.append((now - sent) / 1000.0)
                self.stats.answer_lead_us.append((fb.t_tick_ns + self._off_ns - sent) / 1000.0)
        return fb

    @property
    def fresh(self) -> bool:
        return self.feedback is not None and time.perf_counter_ns() - self.last_rx_ns <= self.timeout_ns

    def next_service_tick_ns(self, after_ns: int) -> Optional[int]:
        """The first service tick deadline after ``after_ns`` in this client's clock (estimated from
        the feedback's tick deadlines and the smallest observed send-to-receive delay)."""
        fb = self.feedback
        if fb is None or self._off_ns is None or self.welcome is None:
            return None
        P_ns = 1e9 / self.welcome.rate_hz
        g0 = fb.t_tick_ns + self._off_ns
        k = int(np.ceil((after_ns - g0) / P_ns))
        return int(g0 + k * P_ns)

    # --- libfranka-style control loop ----------------------------------------------------------------
    def control(self, callback: Callable[[Tick], Command], *, rate_hz: Optional[float] = None,
                duration: Optional[float] = None, lead_us: float = 250.0, late_limit: int = 20,
                spin_us: float = 300.0, rt_priority: int = 0) -> int:
        """Run ``callback`` once per tick until it returns ``Command(..., finished=True)`` or
        ``duration`` s pass; returns the number of ticks. See the module docstring for the errors.

        ``rt_priority`` (1-99): run the calling thread SCHED_FIFO at that priority for the loop's
        duration, where the OS allows it (as libfranka's ``RealtimeConfig``; refused: normal
        priority, noted in ``scheduling``); a device thread that an ordinary process can preempt
        sends late and its samples miss the service's tick."""
        if not self.session:
            raise ClientError("not connected: call connect() first")
        if int(late_limit) < 1:
            raise ClientError(f"late_limit {late_limit}: the number of consecutive overrun ticks allowed "
                              "must be at least 1")
        saved = self._enter_realtime(int(rt_priority))
        try:
            return self._control(callback, rate_hz, duration, lead_us, late_limit, spin_us)
        finally:
            if saved is not None:
                try:
                    os.sched_setscheduler(0, *saved)
                except OSError:
                    pass

    def _enter_realtime(self, priority: int):
        """SCHED_FIFO ``priority`` for the calling thread; returns what to restore (None: unchanged)."""
        self.scheduling = "normal"
        if priority <= 0:
            return None
        try:
            saved = (os.sched_getscheduler(0), os.sched_getparam(0))
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (AttributeError, OSError) as e:
            self.scheduling = f"normal (SCHED_FIFO refused: {e})"
            return None
        self.scheduling = f"SCHED_FIFO {priority}"
        return saved

    def _control(self, callback, rate_hz, duration, lead_us, late_limit, spin_us) -> int:
        rate = float(rate_hz or self.hello.rate_hz)
        period = int(1e9 / rate)
        lead = int(lead_us * 1000)
        spin = int(spin_us * 1000)
        pc = time.perf_counter_ns
        t0 = pc()
        deadline = t0
        prev_start = t0
        k = 0
        late_run = 0
        end = None if duration is None else t0 + int(duration * 1e9)
        try:
            while True:
                rest = deadline - pc() - spin
                if rest > 0:
                    time.sleep(rest / 1e9)
                while pc() < deadline:
                    pass
                start = pc()
                self.poll()
                fresh = self.fresh
                if self.feedback is not None and not fresh:
                    raise LinkLost(f"no feedback for {(start - self.last_rx_ns) / 1e6:.1f} ms "
                                   f"(timeout {self.timeout_ns / 1e6:.0f} ms): force zeroed, the robot holds")
                if self.feedback is None and start - self.last_rx_ns > max(self.timeout_ns, 200_000_000):
                    raise LinkLost("the service never answered a sample: force zero")
                tick = Tick(k, (start - t0) / 1e9, (start - prev_start) / 1e9, self.force.copy(), self.feedback, fresh)
                cmd = callback(tick)
                if not isinstance(cmd, Command):
                    raise ClientError(f"control callback returned {type(cmd).__name__}; expected a Command")
                self.send_state(cmd.position, clutch=cmd.clutch, orientation=cmd.orientation, grasp=cmd.grasp,
                                buttons=cmd.buttons)
                k += 1
                if cmd.finished or (end is not None and pc() >= end):
                    return k
                done = pc()
                # lateness: this tick ended after the next one was due
                if done - deadline > period:
                    late_run += 1
                    if late_run >= late_limit:
                        raise TimingError(f"{late_run} consecutive ticks overran the {period / 1e3:.0f} us period "
                                          f"(last: callback {(done - start) / 1e3:.0f} us, woke "
                                          f"{(start - deadline) / 1e3:.0f} us late)")
                else:
                    late_run = 0
                prev_start = start
                nxt = deadline + period
                g = self.next_service_tick_ns(nxt - period // 2 + lead)
                if g is not None and self.welcome is not None and abs(self.welcome.rate_hz - rate) < 1e-6:
                    nxt = g - lead               # phase lock: arrive just before the service tick
                deadline = max(nxt, done) if nxt - done < -period else nxt
        except BaseException:
            self.force[:] = 0.0          # whatever went wrong, the device displays no force
            raise
