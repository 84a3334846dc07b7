"""Non-blocking UDP calls that keep the interpreter lock (Linux, 64-bit; elsewhere the socket's own).

Python's ``socket`` methods hand the interpreter lock over around every system call, even a
non-blocking one that takes microseconds. In a process whose haptic loop keeps the lock for a
whole tick (``loop.py``: a 5 ms switch interval while a tick runs), that hand-over is costly on
both sides:

* a send (the UDP hub's answers to handshakes and its BYEs; its tick's FEEDBACK went this way
  until the hub's C receiver took it over): the sender hands the lock to whichever thread wants
  it and waits to get it back, up to that thread's switch interval;
* a Python receiver's reads (``rx_stamps.StampedReader``, the ITP adapter's): each read of a
  queued datagram hands the lock to the waiting tick, and the receiver waits for the tick to end
  before it reads the next one. On two loaded cores the UDP hub's Python receiver read about one
  datagram per tick gap, fell behind two 1 kHz devices, and the kernel dropped what its receive
  buffer could not hold: the samples the ticks used were tens of milliseconds old and the
  sessions timed out (arms held, S9). (The hub's STATEs are now read by a C thread that never
  takes the lock: ``udp_native``.)

Here the same calls go through the C library loaded as ``ctypes.PyDLL``, whose calls keep the
lock, with ``MSG_DONTWAIT``: they never block, so keeping the lock costs no other thread more
than the call itself. Only the receiver's wait for data (``poll``) still hands the lock over,
as it must. IPv4 only (the service's UDP endpoints are IPv4); an IPv6 socket, or a platform
without these, uses the socket's own methods.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import errno
import socket
import struct
import sys

MSG_DONTWAIT = getattr(socket, "MSG_DONTWAIT", 0x40)
MSG_NOSIGNAL = getattr(socket, "MSG_NOSIGNAL", 0x4000)
_CMSG_HDR = struct.Struct("@Qii")        # cmsghdr: cmsg_len (size_t), cmsg_level, cmsg_type
_ADDR_CACHE_MAX = 1024                   # distinct peers whose sockaddr / tuple are kept


class _IoVec(ctypes.Structure):
    _fields_ = [("iov_base", ctypes.c_void_p), ("iov_len", ctypes.c_size_t)]


class _MsgHdr(ctypes.Structure):
    _fields_ = [("msg_name", ctypes.c_void_p), ("msg_namelen", ctypes.c_uint32),
                ("msg_iov", ctypes.POINTER(_IoVec)), ("msg_iovlen", ctypes.c_size_t),
                ("msg_control", ctypes.c_void_p), ("msg_controllen", ctypes.c_size_t), ("msg_flags", ctypes.c_int)]


def _load():
    """libc's ``sendto`` and ``recvmsg`` as calls that keep the lock, or None where unsupported."""
    if not sys.platform.startswith("linux") or ctypes.sizeof(ctypes.c_void_p) != 8:
        return None
    try:
        lc = ctypes.PyDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError:
        return None
    sendto, recvmsg = lc.sendto, lc.recvmsg
    sendto.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_void_p, ctypes.c_uint32]
    sendto.restype = ctypes.c_ssize_t
    recvmsg.argtypes = [ctypes.c_int, ctypes.POINTER(_MsgHdr), ctypes.c_int]
    recvmsg.restype = ctypes.c_ssize_t
    return sendto, recvmsg


_CALLS = _load()


def available(sock: socket.socket) -> bool:
    """Whether ``sock`` (a UDP socket) gets the lock-keeping calls here."""
    return _CALLS is not None and sock.family == socket.AF_INET and sock.type == socket.SOCK_DGRAM


class Sender:
    """``send(addr, data)``: one datagram (bytes, or a bytearray sent as it is at the call) from
    ``sock`` to ``addr`` (host, port), never blocking, keeping the interpreter lock. Returns False
    where the kernel refused it (full send buffer, an unreachable peer): the caller counts it, as
    it counts a socket ``OSError``."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.held = available(sock)
        self._sockaddr: dict = {}        # (host, port) -> packed sockaddr_in (a ctypes buffer)
        self._bufs = _Buffers()

    def send(self, addr, data) -> bool:
        kind = type(data)
        if not self.held or (kind is not bytes and kind is not bytearray):
            try:
                self.sock.sendto(data, addr)
                return True
            except OSError:
                return False
        sa = self._sockaddr.get(addr)
        if sa is None:
            if len(self._sockaddr) >= _ADDR_CACHE_MAX:
                self._sockaddr.clear()
            try:
                packed = struct.pack("=H", socket.AF_INET) + struct.pack("!H", addr[1]) + socket.inet_aton(addr[0])
            except (OSError, TypeError, IndexError, struct.error):
                return False
            sa = self._sockaddr[addr] = ctypes.create_string_buffer(packed + bytes(8), 16)
        fd = self.sock.fileno()
        if fd < 0:
            return False
        ptr = data if kind is bytes else self._bufs.address(data)
        return _CALLS[0](fd, ptr, len(data), MSG_DONTWAIT | MSG_NOSIGNAL, sa, 16) >= 0


class _Buffers:
    """The addresses of the bytearrays handed to the calls, each found once: the ctypes view kept
    here exports the buffer, so it cannot be resized (moved) while it is known."""

    def __init__(self):
        self._known: dict = {}           # id(buf) -> (buf, its ctypes view, address)

    def address(self, buf: bytearray) -> int:
        got = self._known.get(id(buf))
        if got is None or got[0] is not buf or len(got[1]) != len(buf):
            if len(self._known) >= _ADDR_CACHE_MAX:
                self._known.clear()
            view = (ctypes.c_char * len(buf)).from_buffer(buf)
            got = self._known[id(buf)] = (buf, view, ctypes.addressof(view))
        return got[2]


class Receiver:
    """``read(buf)``: one waiting datagram into the bytearray ``buf``, keeping the interpreter
    lock: ``(nbytes, (host, port), control)`` with ``control`` a list of ``(level, type, data)``
    as ``socket.recvmsg_into`` gives its ancillary data, or None when nothing waits or the socket
    is closed. Errors the socket reports for earlier sends (ICMP port unreachable) are skipped,
    as ``recvmsg_into`` callers skip them. A datagram longer than ``buf`` is cut to it (nbytes is
    what was kept), as ``recvmsg_into`` does."""

    def __init__(self, sock: socket.socket, control_bytes: int = 64):
        self.sock = sock
        self.held = available(sock)
        self._name = bytearray(16)
        self._ctrl = bytearray(control_bytes)
        self._iov = _IoVec()
        self._hdr = _MsgHdr()
        self._name_c = (ctypes.c_char * 16).from_buffer(self._name)
        self._ctrl_c = (ctypes.c_char * control_bytes).from_buffer(self._ctrl)
        self._hdr.msg_name = ctypes.addressof(self._name_c)
        self._hdr.msg_iov = ctypes.pointer(self._iov)
        self._hdr.msg_iovlen = 1
        self._hdr.msg_control = ctypes.addressof(self._ctrl_c)
        self._hdr_ref = ctypes.byref(self._hdr)
        self._bufs = _Buffers()
        self._peers: dict = {}           # packed port + address -> (host, port)

    def read(self, buf: bytearray):
        base, size = self._bufs.address(buf), len(buf)
        hdr, iov, recvmsg = self._hdr, self._iov, _CALLS[1]
        while True:
            fd = self.sock.fileno()
            if fd < 0:
                return None
            iov.iov_base, iov.iov_len = base, size
            hdr.msg_namelen, hdr.msg_controllen, hdr.msg_flags = 16, len(self._ctrl), 0
            n = recvmsg(fd, self._hdr_ref, MSG_DONTWAIT)
            if n >= 0:
                break
            err = ctypes.get_errno()
            if err in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBADF, errno.ENOTSOCK):
                return None
            # EINTR, ECONNREFUSED (an earlier send's ICMP error) and the like: read on
        key = bytes(self._name[2:8])
        peer = self._peers.get(key)
        if peer is None:
            if len(self._peers) >= _ADDR_CACHE_MAX:
                self._peers.clear()
            port, ip = struct.unpack("!H4s", key)
            peer = self._peers[key] = (socket.inet_ntoa(ip), port)
        return n, peer, self._control(hdr.msg_controllen)

    def _control(self, length: int) -> list:
        out, ctrl, off = [], self._ctrl, 0
        end = min(length, len(ctrl))
        while off + _CMSG_HDR.size <= end:
            clen, level, kind = _CMSG_HDR.unpack_from(ctrl, off)
            if clen < _CMSG_HDR.size:
                break
            out.append((level, kind, bytes(ctrl[off + _CMSG_HDR.size:min(off + clen, end)])))
            off += (clen + 7) & ~7
        return out


__all__ = ["Sender", "Receiver", "available"]
