"""Attacks on the links into the haptic loop (issue 18, items 6, 7, 9): replayed handshakes, a
forged-datagram flood, spoofed ITP packets. Loopback only; waits are bounded, no timings asserted."""
import hmac
import logging
import os
import socket
import threading
import time

import pytest

from pointfence.clients import Client
from pointfence.clients import protocol as P
from pointfence.service.itp import ItpReceiver, pack_itp
from pointfence.service.udp_cookies import CookieJar
from pointfence.service.udp_server import UdpHub

KEY = bytes(range(7, 39))
DEV = 42


class Device:
    """A genuine device speaking the protocol by hand on its own socket (its datagrams can be
    captured and replayed from the same address)."""

    def __init__(self, hub):
        self.hub = hub
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(2.0)
        self.sent = []

    def send(self, data):
        self.sent.append(data)
        self.sock.sendto(data, self.hub.address)
        self.hub.pump()

    def recv(self):
        data = self.sock.recv(2048)
        h = P.parse_header(data)
        P.verify(data, KEY)
        return h, P.DECODERS[h.type].decode(data)

    def handshake(self):
        """HELLO, COOKIE, HELLO with the cookie, WELCOME; returns (session id, session key)."""
        self.flush()
        hello = P.Hello(os.urandom(16))
        opened = self.hub.sessions_opened
        self.send(hello.encode(KEY, DEV, 1))
        h, ck = self.recv()
        assert h.type == P.COOKIE and ck.client_nonce == hello.nonce and self.hub.sessions_opened == opened
        hello.cookie = ck.cookie
        self.send(hello.encode(KEY, DEV, 2))
        h, w = self.recv()
        assert h.type == P.WELCOME, P.ERROR_NAMES.get(getattr(w, "error", 0))
        return h.session, P.session_key(KEY, hello.nonce, w.server_nonce, DEV, h.session)

    def flush(self):
        """Drop what earlier exchanges left in the socket (answers to replays, BYE)."""
        self.sock.setblocking(False)
        try:
            while True:
                self.sock.recv(2048)
        except BlockingIOError:
            pass
        finally:
            self.sock.settimeout(2.0)

    def prove(self, sid, skey, seq=1):
        self.send(P.State(1, 0, (0.01, 0.0, 0.0)).encode(skey, DEV, sid, seq))

    def close(self):
        self.sock.close()


def no_answer(dev):
    dev.sock.settimeout(0.05)
    try:
        data = dev.sock.recv(2048)
    except socket.timeout:
        return True
    finally:
        dev.sock.settimeout(2.0)
    return P.parse_header(data).type != P.WELCOME


def genuine_connects_and_drives(hub, dev):
    sid, skey = dev.handshake()
    dev.prove(sid, skey)
    m = hub.masters[hub.sessions[sid].slot]
    m.poll(1.0)
    assert m.ok and m.position[0] == 0.01
    return sid, skey


def test_captured_hello_replayed_after_a_restart_opens_nothing():
    hub = UdpHub(KEY, 1, receiver=False)
    dev = Device(hub)
    try:
        sid, skey = dev.handshake()
        dev.prove(sid, skey)
        capture = list(dev.sent)                  # HELLO, HELLO with cookie, STATE
        port = hub.address[1]
        hub.close()
        hub = UdpHub(KEY, 1, host="127.0.0.1", port=port, receiver=False)   # the restarted service
        dev.hub = hub
        for d in capture[:2]:
            dev.sock.sendto(d, hub.address)
        hub.pump()
        assert not hub.sessions and hub.sessions_opened == 0
        assert hub.counters["cookie"] == 1        # the old cookie is worthless after the restart
        genuine_connects_and_drives(hub, dev)     # and the genuine device is not locked out
    finally:
        dev.close()
        hub.close()


def test_captured_hello_replayed_after_5000_other_hellos_and_after_expiry_opens_nothing():
    clock = {"ns": 0}
    hub = UdpHub(KEY, 2, receiver=False)
    hub.cookies = CookieJar(clock_ns=lambda: clock["ns"])
    dev = Device(hub)
    try:
        sid, skey = dev.handshake()
        dev.prove(sid, skey, 1)
        hello1, hello2 = dev.sent[0], dev.sent[1]
        dev.send(P.Bye().encode(skey, DEV, sid, 2))          # the genuine session ends
        assert not hub.sessions
        # 5,000 other handshakes (other devices, other addresses), complete ones included
        for i in range(5000):
            h = P.Hello(os.urandom(16))
            addr = ("127.0.0.1", 20000 + i % 30000)
            assert hub.handle(h.encode(KEY, 1000 + i, 1), addr) == P.E_OK
            h.cookie = hub.cookies.issue(addr, 1000 + i, h.nonce)
            hub.handle(h.encode(KEY, 1000 + i, 2), addr)
        for s in list(hub.sessions.values()):               # end them (BYE) so that slots are free
            hub.handle(P.Bye().encode(s.key, s.device_id, s.id, 1), s.addr)
        opened = hub.sessions_opened
        replays = hub.counters["replay"]
        dev.send(hello2)                                     # inside the cookie's validity
        assert not hub.sessions and hub.sessions_opened == opened and hub.counters["replay"] == replays + 1
        assert no_answer(dev)
        clock["ns"] += int((P.COOKIE_VALID_S + 1) * 1e9)      # after the cookie's validity
        dev.send(hello1)
        dev.send(hello2)
        assert not hub.sessions and hub.sessions_opened == opened and hub.counters["cookie"] == 1
        genuine_connects_and_drives(hub, dev)
    finally:
        dev.close()
        hub.close()


def test_replayed_second_hello_cannot_take_the_slot_of_a_live_device():
    hub = UdpHub(KEY, 1, receiver=False)
    dev = Device(hub)
    try:
        sid, skey = genuine_connects_and_drives(hub, dev)
        dev.send(dev.sent[1])                     # the second HELLO again, from the genuine address
        assert list(hub.sessions) == [sid] and hub.counters["replay"] == 1
        assert hub.masters[0].session is hub.sessions[sid]
    finally:
        dev.close()
        hub.close()


def test_a_session_that_never_proves_its_key_holds_nothing():
    hub = UdpHub(KEY, 1, receiver=False)
    dev = Device(hub)
    other = Device(hub)
    try:
        sid, _ = dev.handshake()                  # no STATE follows
        sid2, skey2 = dev.handshake()             # the same device again: not "busy"
        assert list(hub.sessions) == [sid2] and hub.sessions_displaced == 1
        # another device finds the only slot taken by an unproven session: full at first ...
        hello = P.Hello(os.urandom(16))
        other.send(hello.encode(KEY, 7, 1))
        _, ck = other.recv()
        hello.cookie = ck.cookie
        other.send(hello.encode(KEY, 7, 2))
        h, r = other.recv()
        assert h.type == P.REJECT and r.error == P.E_FULL
        # ... and gets the slot once that session has held it PROOF_S without proving its key
        hub.sessions[sid2].t_open -= P.PROOF_S + 0.1
        hello = P.Hello(os.urandom(16))
        other.send(hello.encode(KEY, 7, 1))
        _, ck = other.recv()
        hello.cookie = ck.cookie
        other.send(hello.encode(KEY, 7, 2))
        h, w = other.recv()
        assert h.type == P.WELCOME and sid2 not in hub.sessions
    finally:
        dev.close()
        other.close()
        hub.close()


class _Ticker:
    """Plays the haptic loop: polls every master each ~1 ms and counts the HMACs computed inside poll."""

    def __init__(self, hub):
        self.hub = hub
        self.local = threading.local()
        self.hmacs_in_poll = 0
        self.hmacs_elsewhere = 0
        self.stop = threading.Event()
        self.th = threading.Thread(target=self.run, daemon=True)

    def digest(self, real):
        def counted(*a, **k):
            if getattr(self.local, "in_poll", False):
                self.hmacs_in_poll += 1
            else:
                self.hmacs_elsewhere += 1
            return real(*a, **k)
        return counted

    def run(self):
        t0 = time.monotonic()
        while not self.stop.is_set():
            t = time.monotonic() - t0
            for m in self.hub.masters:
                self.local.in_poll = True
                try:
                    m.poll(t)
                finally:
                    self.local.in_poll = False
                if m.ok:
                    m.send_force(-100.0 * m.position)
            time.sleep(0.001)


FLOODER = """
import socket, sys, time
host, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
forged = bytes.fromhex(sys.stdin.readline().strip())
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
sent = 0
while sent < n:
    for _ in range(20):                  # ~20,000 datagrams/s: 20 x a 1 kHz device, 5 x the per-source limit
        try:
            s.sendto(forged, (host, port))
        except OSError:
            pass
    sent += 20
    time.sleep(0.001)
print(sent)
"""


def test_a_forged_flood_from_one_source_neither_starves_a_client_nor_costs_the_tick_hmacs(monkeypatch):
    import subprocess
    import sys

    hub = UdpHub(KEY, 2, timeout_ms=1000)       # generous: a loaded test machine may stall a thread for tens of ms
    ticker = _Ticker(hub)
    monkeypatch.setattr(hmac, "digest", ticker.digest(hmac.digest))
    ticker.th.start()
    proc = None
    try:
        c = Client(*hub.address, KEY, 3, timeout_ms=1000)
        c.connect(timeout=10)
        forged = P.State(1, 0, (0.09, 0.09, 0.09)).encode(bytes([9]) * 32, 3, c.session, 10**9)
        proc = subprocess.Popen([sys.executable, "-c", FLOODER, hub.address[0], str(hub.address[1]), "50000"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        proc.stdin.write(forged.hex() + "\n")
        proc.stdin.close()
        sent = 0
        end = time.monotonic() + 60
        while proc.poll() is None and time.monotonic() < end:
            c.send_state((0.0, 0.0, -0.01))
            sent += 1
            time.sleep(0.002)
        flooded = int(proc.stdout.read().strip() or 0)
        live = hub.sessions.get(c.session)
        assert flooded == 50000 and sent > 100
        assert live is not None and hub.sessions_dropped == 0, "the genuine session timed out under the flood"
        assert live.accepted >= sent // 2, (live.accepted, sent, hub.status())
        assert hub.counters["rate_limited"] > 0
        assert hub.counters["auth"] < flooded // 2           # most forgeries were dropped before their HMAC
        assert ticker.hmacs_in_poll == 0 and ticker.hmacs_elsewhere > 0
        c.close()
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        ticker.stop.set()
        ticker.th.join(2)
        hub.close()


# --- ITP ---------------------------------------------------------------------------------------------
Q = [[0, 0, 0, 1], [0, 0, 0, 1]]
GENUINE = ("127.0.0.1", 40001)
OTHER = ("127.0.0.1", 40002)


def test_itp_spoofed_sequence_jump_does_not_lock_out_the_genuine_master():
    r = ItpReceiver("127.0.0.1", 0, receiver=False)
    try:
        arm = r.arm_master(0)
        for s in (10, 11, 12):
            assert r.handle(pack_itp(s, [[1, 0, 0], [0, 0, 0]], Q), 0.001 * s, GENUINE)
        # one spoofed packet (even from the genuine address) numbered last + 2^31 - 1
        assert not r.handle(pack_itp(12 + 2**31 - 1, [[0, 0, 0], [0, 0, 0]], Q), 0.013, GENUINE)
        assert r.counters["jump"] == 1
        for s in range(13, 20):                                   # the genuine master goes on
            assert r.handle(pack_itp(s, [[1, 0, 0], [0, 0, 0]], Q), 0.001 * s, GENUINE)
        arm.poll(0.02)                                            # the tick copies the newest sample
        assert arm.position[0] == pytest.approx(10e-6)
    finally:
        r.close()


def test_itp_locks_to_the_first_source_until_silence():
    r = ItpReceiver("127.0.0.1", 0, lock_timeout_s=0.5, receiver=False)
    try:
        r.arm_master(0)
        assert r.handle(pack_itp(1, [[1, 0, 0], [0, 0, 0]], Q), 0.0, GENUINE)
        assert not r.handle(pack_itp(2, [[500, 0, 0], [0, 0, 0]], Q), 0.001, OTHER)
        assert r.counters["source"] == 1 and r.status()["locked_to"] == list(GENUINE)
        assert r.handle(pack_itp(2, [[1, 0, 0], [0, 0, 0]], Q), 0.002, GENUINE)
        assert not r.handle(pack_itp(3, [[1, 0, 0], [0, 0, 0]], Q), 0.4, OTHER)
        # the genuine master is silent longer than the lock timeout: another may take the link
        assert r.handle(pack_itp(900, [[1, 0, 0], [0, 0, 0]], Q), 0.6, OTHER)
        assert not r.handle(pack_itp(3, [[1, 0, 0], [0, 0, 0]], Q), 0.601, GENUINE)
    finally:
        r.close()


def test_itp_warns_loudly_when_bound_beyond_loopback(caplog):
    with caplog.at_level(logging.WARNING, logger="pointfence.itp"):
        r = ItpReceiver("0.0.0.0", 0)
    try:
        assert r.status()["exposed"] is True and "UNAUTHENTICATED" in r.status()["warning"]
        assert any("UNAUTHENTICATED" in rec.getMessage() for rec in caplog.records)
    finally:
        r.close()
    r = ItpReceiver("127.0.0.1", 0)
    try:
        assert r.status()["exposed"] is False and r.status()["warning"] is None
    finally:
        r.close()


def test_source_limiter_buckets_are_per_source_and_the_table_is_bounded():
    from pointfence.service.udp_ratelimit import SourceLimiter

    lim = SourceLimiter(rate=100.0, burst=10.0, max_sources=4, idle_s=5.0)
    a, b = ("10.0.0.1", 1), ("10.0.0.2", 1)
    assert sum(lim.allow(a, 0.0) for _ in range(50)) == 10        # a's burst, then dropped
    assert all(lim.allow(b, 0.0) for _ in range(10))              # b is untouched by a's flood
    assert lim.allow(a, 0.1)                                       # refilled at 100/s
    for i in range(100):                                           # many spoofed sources: one shared bucket
        lim.allow(("10.1.0.%d" % i, 1), 0.2)
    assert len(lim) == 4 and lim.overflowed > 0
    assert lim.allow(b, 0.3)                                       # known sources keep their buckets


def test_a_cookie_is_bound_to_its_address():
    hub = UdpHub(KEY, 1, receiver=False)
    try:
        h = P.Hello(os.urandom(16))
        h.cookie = hub.cookies.issue(("127.0.0.1", 5000), DEV, h.nonce)
        assert hub.handle(h.encode(KEY, DEV, 2), ("127.0.0.1", 5001)) == P.E_COOKIE
        assert not hub.sessions
        assert hub.handle(h.encode(KEY, DEV, 2), ("127.0.0.1", 5000)) == P.E_OK and len(hub.sessions) == 1
    finally:
        hub.close()


def test_replayed_states_cost_no_mac_and_handshake_floods_are_cut_per_source(monkeypatch):
    """A replay flood of a live session's own STATEs is rejected before any MAC: from another
    address as naming no session of it, from the device's own (spoofed) on the anti-replay window
    (RFC 4303 3.4.3), and a flood of HELLOs from one source is cut to HELLO_RATE before
    their MACs; the genuine device keeps its session throughout. (Before: every replayed STATE
    cost a MAC, every HELLO two and an answer, and such a flood dropped the live sessions.)"""
    from pointfence.service import udp_server

    hub = UdpHub(KEY, 1, "127.0.0.1", 0, receiver=False)
    dev, attacker = Device(hub), Device(hub)
    try:
        sid, skey = genuine_connects_and_drives(hub, dev)
        for seq in range(2, 12):
            dev.prove(sid, skey, seq)
        macs = {"n": 0}
        real = P.verify

        def counting(buf, key):
            macs["n"] += 1
            return real(buf, key)

        monkeypatch.setattr(P, "verify", counting)
        captured = list(dev.sent)
        before = dict(hub.counters)
        for _ in range(10):
            for data in captured[-10:]:                 # this session's STATEs, replayed
                attacker.send(data)                     # from another address: no session of that address
                dev.send(data)                          # spoofing the device's own: the anti-replay window
        assert macs["n"] == 0
        d = {k: hub.counters[k] - before[k] for k in ("no_session", "stale", "replay")}
        assert d["no_session"] == 100 and d["stale"] + d["replay"] == 100, d
        hellos = [d for d in captured if P.parse_header(d).type == P.HELLO]
        for _ in range(100):                            # the captured handshake, again and again
            for data in hellos:
                attacker.send(data)
        assert macs["n"] <= udp_server.HELLO_BURST + 2   # the rest cut before their MAC
        assert hub.counters["rate_limited"] - before["rate_limited"] >= 180
        dev.prove(sid, skey, 12)                         # the genuine session is untouched
        m = hub.masters[hub.sessions[sid].slot]
        m.poll(2.0)
        assert m.ok and hub.sessions[sid].accepted == 12
    finally:
        dev.close()
        attacker.close()
        hub.close()

