"""Datagrams with the time the kernel received them (the ITP adapter's receiver; the UDP hub's
C receiver reads the same stamps from a socket set up by ``stamp_socket``).

A datagram that waited in a socket's receive queue is as old as its arrival says, not as its
read says: a receiver starved of CPU reads seconds-old master samples as if they were new.
``StampedReader`` reads with ``recvmsg_into`` and the socket's ``SO_TIMESTAMPNS`` stamps (Linux:
``CLOCK_REALTIME`` when the datagram reached the socket), moved onto ``time.perf_counter_ns``'s
clock, the one the haptic tick reads (ns). Where the platform gives no stamps, the read time
stands in (a backlog in the kernel's queue is then not seen). It also counts the datagrams the
kernel dropped because the receive buffer was full (``SO_RXQ_OVFL``, Linux).

The receive buffer is sized for a few tens of milliseconds of traffic, not seconds
(``RCVBUF_BYTES``): under a flood the kernel drops what does not fit (the genuine devices send
again a period later, and only their newest sample matters), rather than queueing a backlog
that the receiver would later hand to the tick in order.
"""
from __future__ import annotations

import socket
import struct
import sys
import time

from pointfence.clients.client import realtime_minus_perf_ns

from .held_io import Receiver

#: the receive buffer asked for (Linux doubles it for its bookkeeping): 64 KiB hold about 150
#: STATE datagrams on loopback (about 830 bytes of kernel memory each): 75 ms of two 1 kHz
#: devices, or 8 ms of a 20,000 datagram/s flood
RCVBUF_BYTES = 64 << 10
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)    # Linux; == SCM_TIMESTAMPNS
SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)          # Linux: datagrams dropped so far (u32)
_TIMESPEC = struct.Struct("@qq")
_U32 = struct.Struct("@I")
_ANC = (socket.CMSG_SPACE(16) + socket.CMSG_SPACE(4)) if hasattr(socket, "CMSG_SPACE") else 64


def stamp_socket(sock: socket.socket, rcvbuf_bytes: int = RCVBUF_BYTES) -> bool:
    """Make ``sock`` non-blocking with a receive buffer of ``rcvbuf_bytes`` (asked; the kernel may
    round or cap it) and, on Linux, each datagram's arrival stamp (``SO_TIMESTAMPNS``) and the
    count of datagrams dropped for want of buffer (``SO_RXQ_OVFL``); whether stamps are on."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, int(rcvbuf_bytes))
    except OSError:
        pass
    sock.setblocking(False)
    if not sys.platform.startswith("linux"):
        return False
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    except OSError:
        return False
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
    except OSError:
        pass
    return True


class StampedReader:
    """Non-blocking reads of ``sock`` with each datagram's arrival time.

    Args:
        sock: a bound UDP socket (set non-blocking here).
        rcvbuf_bytes: the receive buffer to ask for (bytes; the kernel may round or cap it).
    """

    def __init__(self, sock: socket.socket, rcvbuf_bytes: int = RCVBUF_BYTES):
        self.sock = sock
        self.stamps = stamp_socket(sock, rcvbuf_bytes)
        #: datagrams the kernel dropped for want of receive buffer (since the socket opened)
        self.dropped = 0
        #: reads that keep the interpreter lock (``held_io``): a starved receiver is not made to
        #: wait for the haptic tick between two queued datagrams; None: the socket's own reads
        self._held = Receiver(sock, _ANC) if self.stamps else None
        if self._held is not None and not self._held.held:
            self._held = None
        self._off = 0
        self.begin()

    @property
    def rcvbuf(self) -> int:
        """The receive buffer the kernel granted (bytes, its bookkeeping included)."""
        return self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

    def begin(self) -> None:
        """Before a drain: read again the clock offset that moves the kernel's stamps onto
        perf_counter's clock (the realtime clock may have been stepped or slewed)."""
        if self.stamps:
            self._off = realtime_minus_perf_ns()

    def read(self, buf):
        """One datagram into ``buf``: ``(nbytes, address, arrival ns on perf_counter's clock)``,
        or None when nothing waits (or the socket is closed). Errors a UDP socket reports for
        earlier sends (ICMP port unreachable) are skipped."""
        sock = self.sock
        while True:
            try:
                if not self.stamps:
                    n, addr = sock.recvfrom_into(buf)
                    return n, addr, time.perf_counter_ns()
                if self._held is not None:
                    got = self._held.read(buf)
                    if got is None:
                        return None
                    n, addr, anc = got
                else:
                    n, anc, _, addr = sock.recvmsg_into((buf,), _ANC)
            except (BlockingIOError, InterruptedError):
                return None
            except OSError:
                if sock.fileno() < 0:
                    return None
                continue
            t = 0
            for level, kind, raw in anc:
                if level == socket.SOL_SOCKET:
                    if kind == SO_TIMESTAMPNS and len(raw) >= 16:
                        sec, nsec = _TIMESPEC.unpack_from(raw)
                        t = sec * 1_000_000_000 + nsec - self._off
                    elif kind == SO_RXQ_OVFL and len(raw) >= 4:
                        self.dropped = _U32.unpack_from(raw)[0]
            now = time.perf_counter_ns()
            return n, addr, (t if 0 < t < now else now)
