"""`pointfence bench fuzz`: random and mutated datagrams thrown at the service's packet handler.

A ``UdpHub`` with one live session (opened by an authentic handshake: HELLO, COOKIE, HELLO with
the cookie) receives ``--packets`` datagrams through ``UdpHub.handle``, the exact code path of
the service's receiver thread (which verifies datagrams outside the haptic tick): uniformly random
bytes (half of them with a valid magic/version/type and an exact message size), and authentic
datagrams (HELLO, STATE, BYE, and FEEDBACK/WELCOME sent the wrong way) mutated by bit flips,
byte overwrites, truncation, extension and sequence changes. Reports the per-reason rejection
counts, datagrams per second, and ``accepted_forgeries``: mutated or random datagrams that were
accepted (must be 0), and ``master_changed``: times the session's published sample (what the
tick copies into the master) or the session table changed on a datagram that was not authentic
(must be 0). No datagram may raise.

The generator (``Fuzzer``) is shared with tests/test_protocol_fuzz.py.
"""
from __future__ import annotations

import random
import struct
import time

from pointfence.clients import protocol as P
from pointfence.service.udp_native import Sample

PSK = bytes(range(100, 132))


class Fuzzer:
    """A hub with one session and a stream of hostile datagrams (see the module docstring)."""

    def __init__(self, seed: int = 0):
        from pointfence.service.udp_server import UdpHub

        self.hub = UdpHub(PSK, 2, port=0, receiver=False)
        self.addr = ("127.0.0.1", 9)
        self.rng = random.Random(seed)
        hello = P.Hello(b"N" * 16, 3.3, (-0.1, -0.1, -0.1), (0.1, 0.1, 0.1), 1000.0, 50, P.CAP_FORCE, "fuzz")
        assert self.hub.handle(hello.encode(PSK, 77, 1), self.addr) == P.E_OK      # answered with a COOKIE
        assert not self.hub.sessions
        hello.cookie = self.hub.cookies.issue(self.addr, 77, hello.nonce)        # the COOKIE's content
        second = hello.encode(PSK, 77, 2)
        assert self.hub.handle(second, self.addr) == P.E_OK
        self.session = next(iter(self.hub.sessions.values()))
        self._sample = Sample()       # the C receiver's copy of the session's sample
        self.master = self.hub.masters[self.session.slot]
        s = self.session
        self.seq = 1
        st = P.State(1, 0, (0.01, 0.02, 0.03), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 0.0, 0, P.F_CLUTCH)
        first = st.encode(s.key, s.device_id, s.id, 1)
        assert self.hub.handle(first, self.addr) == P.E_OK
        self.bases = [
            first,
            P.State(2, 0, (-0.05, 0.0, 0.09), (0.0, 0.0, 0.0), (0.5, 0.5, 0.5, 0.5), 0.3, 3,
                    P.F_CLUTCH | P.F_ORIENTATION | P.F_GRASP).encode(s.key, s.device_id, s.id, 2),
            P.Hello(b"M" * 16, 3.3, (-0.1, -0.1, -0.1), (0.1, 0.1, 0.1), 1000.0, 50, 1, "x").encode(PSK, 78, 1),
            second,                                                          # the session's own second HELLO
            P.Bye(0).encode(s.key, s.device_id, s.id, 3),
            P.Feedback().encode(s.key, s.device_id, s.id, 4),
            P.Welcome(b"N" * 16, b"S" * 16, 0, 50, 1000.0, 3.0, 1).encode(PSK, 77, s.id, 0),
        ]
        self.accepted_forgeries = 0
        self.master_changed = 0
        self.count = 0
        self._mv = memoryview

    def random_datagram(self) -> bytes:
        r = self.rng
        typ = r.randint(1, 7)
        n = P.SIZES[typ] if r.random() < 0.5 else r.randint(0, 300)
        b = bytearray(r.getrandbits(8) for _ in range(n)) if n < 64 else bytearray(r.randbytes(n))
        if n >= P.HEADER_LEN and r.random() < 0.7:
            P.HEADER.pack_into(b, 0, P.MAGIC, P.VERSION, typ, self.session.device_id if r.random() < 0.5 else r.getrandbits(32),
                               self.session.id if r.random() < 0.7 else r.getrandbits(32), r.getrandbits(64), 0)
        return bytes(b)

    def mutated_datagram(self, base: bytes) -> bytes:
        r = self.rng
        b = bytearray(base)
        for _ in range(r.randint(1, 4)):
            op = r.randrange(6)
            if op == 0 and b:
                i = r.randrange(len(b))
                b[i] ^= 1 << r.randrange(8)
            elif op == 1 and b:
                b[r.randrange(len(b))] = r.getrandbits(8)
            elif op == 2 and b:
                del b[r.randrange(len(b)):]
            elif op == 3:
                b += r.randbytes(r.randint(1, 64))
            elif op == 4 and len(b) >= P.HEADER_LEN:
                b[12:20] = r.getrandbits(64).to_bytes(8, "little")          # sequence
            elif op == 5 and len(b) >= P.HEADER_LEN + 24:
                off = P.HEADER_LEN + 8 * r.randrange((len(b) - P.HEADER_LEN - P.TAG_LEN) // 8)
                b[off:off + 8] = r.choice([b"\x00\x00\x00\x00\x00\x00\xf8\x7f", b"\x00\x00\x00\x00\x00\x00\xf0\x7f",
                                           struct.pack("<d", 1e9), r.randbytes(8)])   # NaN, inf, huge, junk
        return bytes(b)

    def one(self) -> int:
        """Throw one datagram; returns its code."""
        r = self.rng
        hub, m = self.hub, self.master
        if r.random() < 0.4:
            data, authentic = self.random_datagram(), False
        else:
            base = r.choice(self.bases)
            data = self.mutated_datagram(base)
            if data == base:          # a mutation that undid itself: make it a real mutation
                data += b"\0"
            authentic = False
        before = self.sample()
        sessions = dict(hub.sessions)
        code = hub.handle(data, self.addr)
        self.count += 1
        if not authentic:
            if code == P.E_OK:
                self.accepted_forgeries += 1
            if self.sample() != before or hub.sessions != sessions or m.session is not self.session:
                self.master_changed += 1
        return code

    def sample(self):
        """The session's published sample (what the tick would copy into the master)."""
        s, c = self.session, self._sample
        n = self.hub.rx.sample(s.slot, s.id, c)
        return (n, tuple(c.pos), c.flags, c.buttons, tuple(c.quat), c.grasp)

    def close(self) -> None:
        self.hub.close()


def add_arguments(p):
    p.add_argument("--packets", type=int, default=1_000_000, help="datagrams to throw (default 1,000,000)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")


def run(args) -> dict:
    fz = Fuzzer(args.seed)
    t0 = time.perf_counter()
    for _ in range(args.packets):
        fz.one()
    dt = time.perf_counter() - t0
    counters = {k: v for k, v in fz.hub.counters.items() if v}
    fz.close()
    return {"packets": fz.count, "seconds": round(dt, 2), "packets_per_s": round(fz.count / dt),
            "accepted_forgeries": fz.accepted_forgeries, "master_changed": fz.master_changed,
            "rejected": counters, "accepted_authentic": fz.hub.accepted - 1}
