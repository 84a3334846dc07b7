"""Per-source rate limiting of datagrams, before any authentication work (token buckets).

Each source address has a token bucket (``rate`` datagrams/s, ``burst`` deep); a datagram from a
source whose bucket is empty is dropped before its tag is computed, so a flood from one address
costs one dictionary look-up a datagram and does not starve the other sources. The table is
bounded (``max_sources``): a new source takes the place of one idle for ``idle_s``, and beyond
that every further new source shares one overflow bucket (a flood from many spoofed addresses
then competes only with itself, never with the sources already known).

``poll_loop`` is the receiver thread's body that the UDP hub and the ITP adapter share.
"""
from __future__ import annotations

import collections
import select


class SourceLimiter:
    """Token buckets per source address (see the module docstring).

    Args:
        rate: datagrams per second a source may send on average.
        burst: datagrams a source may send at once (bucket depth).
        max_sources: sources with a bucket of their own at most.
        idle_s: a source silent this long may give its bucket to a new one, s.
    """

    def __init__(self, rate: float = 4000.0, burst: float = 400.0, max_sources: int = 1024, idle_s: float = 10.0):
        if not (rate > 0 and burst >= 1 and max_sources >= 1 and idle_s > 0):
            raise ValueError(f"rate {rate}/s, burst {burst}, max_sources {max_sources}, idle_s {idle_s}: "
                             "expected positive values (burst >= 1)")
        self.rate, self.burst, self.max_sources, self.idle_s = float(rate), float(burst), int(max_sources), float(idle_s)
        self._buckets = collections.OrderedDict()    # addr -> [tokens, last time s], least recent first
        self._overflow = [self.burst, None]
        self.overflowed = 0                          # datagrams that went to the overflow bucket

    def allow(self, addr, now: float) -> bool:
        """Take a token for one datagram from ``addr`` at time ``now`` (s); False: drop it."""
        b = self._buckets.get(addr)
        if b is None:
            b = self._new(addr, now)
        else:
            self._buckets.move_to_end(addr)
        tokens = b[0] if b[1] is None else min(self.burst, b[0] + (now - b[1]) * self.rate)
        b[1] = now
        if tokens < 1.0:
            b[0] = tokens
            return False
        b[0] = tokens - 1.0
        return True

    def _new(self, addr, now: float):
        d = self._buckets
        if len(d) >= self.max_sources:
            oldest = next(iter(d))
            if now - d[oldest][1] <= self.idle_s:
                self.overflowed += 1
                return self._overflow
            del d[oldest]
        b = [self.burst, None]
        d[addr] = b
        return b

    def __len__(self) -> int:
        return len(self._buckets)


def poll_loop(sock, stop, pump, timeout_ms: int = 50) -> None:
    """A receiver thread's body (UDP hub, ITP adapter): wait for ``sock`` to be readable and call
    ``pump()`` until ``stop`` (a threading.Event) is set or the socket is closed."""
    poller = select.poll()
    poller.register(sock, select.POLLIN)
    while not stop.is_set() and sock.fileno() >= 0:
        try:
            ready = poller.poll(timeout_ms)
        except OSError:
            return
        if ready:
            pump()
