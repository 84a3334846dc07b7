"""Stateless HELLO cookies: the service's challenge before any session exists (PROTOCOL.md 6.1).

The first HELLO of a handshake carries no cookie; the service answers it with a COOKIE and keeps
nothing. The client repeats its HELLO (same nonce) with that cookie; only then a session opens.
A cookie is ``t_issue (u64, ms of this process's monotonic clock) | MAC (16 bytes)`` with
``MAC = HMAC-SHA256(secret, "pointfence v2 cookie" | t_issue | client address | device id |
client nonce)``, where ``secret`` is 32 random bytes drawn when the service starts. So a cookie

* is valid ``valid_s`` after its issue only (a captured second HELLO replayed later opens
  nothing, and a restart, with a new secret, invalidates every cookie at once),
* is bound to the address it was sent to (a replay from another address fails), and
* opens at most one session: the nonces of the second HELLOs accepted are kept until their
  cookies expire (``consume``), so a replay inside the validity is refused as ``replay``.

That table holds only nonces of *authentic* second HELLOs (PSK-tagged, with a cookie this
service issued) and forgets each one when its cookie expires; at ``max_used`` entries further
handshakes are refused (``full``) until entries expire: it fails closed, never by forgetting.
"""
from __future__ import annotations

import collections
import hmac
import os
import struct
import time

from pointfence.clients import protocol as P

LABEL = b"pointfence v2 cookie"
_T = struct.Struct("<Q")
_DEV = struct.Struct("<I")


def _addr_bytes(addr) -> bytes:
    return f"{addr[0]}:{addr[1]}".encode("ascii", "replace")


class CookieJar:
    """Issues and checks HELLO cookies (see the module docstring).

    Args:
        valid_s: validity of a cookie after its issue, s.
        max_used: nonces of accepted second HELLOs kept at most (their cookies still valid).
        clock_ns: monotonic clock, ns (tests pass a fake one).
    """

    def __init__(self, valid_s: float = P.COOKIE_VALID_S, max_used: int = 65536, clock_ns=time.monotonic_ns):
        self._secret = os.urandom(32)
        self.valid_ms = int(round(valid_s * 1000))
        self.max_used = int(max_used)
        self._clock = clock_ns
        self._t0 = clock_ns()
        self._used = {}                              # nonce -> expiry, ms
        self._order = collections.deque()            # (expiry ms, nonce), insertion order

    def now_ms(self) -> int:
        return (self._clock() - self._t0) // 1_000_000

    def _mac(self, t_ms: int, addr, device_id: int, nonce: bytes) -> bytes:
        msg = LABEL + _T.pack(t_ms) + _addr_bytes(addr) + _DEV.pack(device_id & 0xFFFFFFFF) + bytes(nonce)
        return hmac.digest(self._secret, msg, "sha256")[:P.COOKIE_LEN - _T.size]

    def issue(self, addr, device_id: int, nonce: bytes) -> bytes:
        """A fresh cookie for this address, device id and client nonce."""
        t = self.now_ms()
        return _T.pack(t) + self._mac(t, addr, device_id, nonce)

    def check(self, cookie: bytes, addr, device_id: int, nonce: bytes) -> int:
        """Raise ProtocolError(E_COOKIE) unless ``cookie`` is one of ours, for these values, and
        not expired; returns its issue time, ms."""
        t = _T.unpack_from(cookie, 0)[0]
        now = self.now_ms()
        if not hmac.compare_digest(self._mac(t, addr, device_id, nonce), bytes(cookie[_T.size:])):
            raise P.ProtocolError(P.E_COOKIE, "cookie not issued by this service for this address, device and nonce")
        if not 0 <= now - t <= self.valid_ms:
            raise P.ProtocolError(P.E_COOKIE, f"cookie issued {now - t} ms ago (valid {self.valid_ms} ms)")
        return t

    def consume(self, nonce: bytes, t_issue_ms: int) -> None:
        """Record the nonce of an accepted second HELLO; ProtocolError(E_REPLAY) if it was used
        already, (E_FULL) if the table is full of unexpired entries."""
        now = self.now_ms()
        order, used = self._order, self._used
        while order and order[0][0] < now:
            exp, n = order.popleft()
            if used.get(n) == exp:
                del used[n]
        if nonce in used:
            raise P.ProtocolError(P.E_REPLAY, "HELLO nonce already opened a session")
        if len(used) >= self.max_used:
            raise P.ProtocolError(P.E_FULL, f"{len(used)} handshakes within {self.valid_ms} ms; try again later")
        exp = t_issue_ms + self.valid_ms
        used[nonce] = exp
        order.append((exp, nonce))

    def __len__(self) -> int:
        return len(self._used)
