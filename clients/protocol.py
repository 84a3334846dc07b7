"""The pointfence wire protocol, version 2 (``clients/PROTOCOL.md`` is the normative text).

Every datagram is ``header (24 B) | payload | tag (16 B)``, little-endian, of a fixed size per
message type; the tag is HMAC-SHA256 truncated to 16 bytes over everything before it. HELLO,
WELCOME, REJECT and COOKIE are keyed with the pre-shared key (PSK); STATE, FEEDBACK and BYE
with the session key ``HMAC-SHA256(PSK, "pointfence v2 session" | client nonce | server nonce |
device id | session id)``. A session opens only after a stateless server challenge: the first
HELLO of a handshake is answered with a COOKIE, and only a HELLO that repeats that cookie (valid
for ``COOKIE_VALID_S``) gets a WELCOME; a captured HELLO replayed later opens nothing.

This module is pure codec: ``encode_*`` build exact bytes, ``parse_header`` checks size, magic,
version and type without a key, ``verify`` checks the tag in constant time, ``decode_*`` unpack
and validate the values. Every failure raises :class:`ProtocolError` with an error ``code``
(the ``E_*`` constants, shared with the C SDK and carried in FEEDBACK/REJECT messages).
"""
from __future__ import annotations

import hmac
import math
import struct
from dataclasses import dataclass, field
from typing import Tuple

from pointfence.kernels.errors import PointfenceError

from .keyfile import check_key, load_key, parse_key_text  # noqa: F401  (the protocol's key rules)

VERSION = 2
MAGIC = b"PF"
TAG_LEN = 16
HEADER = struct.Struct("<2sBBIIQI")         # magic, version, type, device id, session id, seq, reserved (0)
HEADER_LEN = HEADER.size                    # 24
MAX_DATAGRAM = 2048                         # receive buffer: anything longer is "oversized" anyway

# message types
HELLO, WELCOME, REJECT, STATE, FEEDBACK, BYE, COOKIE = 1, 2, 3, 4, 5, 6, 7
TYPE_NAMES = {HELLO: "HELLO", WELCOME: "WELCOME", REJECT: "REJECT", STATE: "STATE", FEEDBACK: "FEEDBACK", BYE: "BYE",
              COOKIE: "COOKIE"}
COOKIE_LEN = 24             # opaque to clients: echoed verbatim in the second HELLO

# payload layouts (after the header, before the tag)
P_HELLO = struct.Struct("<16sd3d3ddHHI16s24s")         # nonce, max_force, ws_min, ws_max, rate, timeout_ms, caps, rsv, model,
#                                                        cookie (zeros in the first HELLO of a handshake)
P_WELCOME = struct.Struct("<16s16sHHIddQ")             # client nonce, server nonce, slot, timeout_ms, rsv, rate, max_force, t_service_ns
P_REJECT = struct.Struct("<16sHHI")                    # client nonce, error, rsv, rsv
P_STATE = struct.Struct("<QQ3d3d4ddIHH")               # t_client, t_echo, pos, inc, quat wxyz, grasp, buttons, flags, rsv
P_FEEDBACK = struct.Struct("<QQQQQ3d3d3dBBBBIHHII")    # tick, t_tick, t_sent, echo_seq, echo_t_client, force, proxy, robot,
#                                                        contact, fixture, robot_mode, link, hold, error, slot, rejected, rsv
P_BYE = struct.Struct("<HHI")                          # reason, rsv, rsv
P_COOKIE = struct.Struct("<16s24s")                    # client nonce (echo), cookie
PAYLOADS = {HELLO: P_HELLO, WELCOME: P_WELCOME, REJECT: P_REJECT, STATE: P_STATE, FEEDBACK: P_FEEDBACK, BYE: P_BYE,
            COOKIE: P_COOKIE}
SIZES = {t: HEADER_LEN + p.size + TAG_LEN for t, p in PAYLOADS.items()}
#: messages keyed with the PSK (the others with the session key)
PSK_TYPES = (HELLO, WELCOME, REJECT, COOKIE)

# capability bits (HELLO caps)
CAP_FORCE = 1 << 0          # displays 3-DOF force
CAP_ORIENTATION = 1 << 1    # reports orientation
CAP_GRASP = 1 << 2          # reports a grasp (gripper) value
CAP_CLUTCH = 1 << 3         # has a clutch (foot pedal or button)
CAP_MASK = 0xF

# STATE flags
F_CLUTCH = 1 << 0           # pedal pressed: the master drives its robot
F_ORIENTATION = 1 << 1      # the quaternion is valid
F_GRASP = 1 << 2            # the grasp value is valid
FLAG_MASK = 0x7

# FEEDBACK fixture bits
FX_HAPTICS = 1 << 0         # haptic rendering engaged
FX_TELEOP = 1 << 1          # teleoperation engaged
FX_COUPLED = 1 << 2         # this master drives its robot on this tick
FX_FIXTURE = 1 << 3         # forbidden-region mode (0: plain haptic rendering)
# FEEDBACK robot_mode
ROBOT_IDEAL, ROBOT_ENABLED, ROBOT_HOLDING, ROBOT_FAULT = 0, 1, 2, 3
# FEEDBACK contact (the proxy state)
CONTACT_FREE, CONTACT_CONTACT, CONTACT_ENTRENCHED = 0, 1, 2

# error codes
E_OK = 0
E_MALFORMED = 1        # bad magic, unknown type, reserved bits or fields not zero
E_VERSION = 2          # protocol version not supported
E_TRUNCATED = 3        # shorter than its type's size
E_OVERSIZED = 4        # longer than its type's size
E_AUTH = 5             # tag does not verify (wrong key, forged or corrupted)
E_REPLAY = 6           # sequence already received (inside the window)
E_STALE = 7            # sequence older than the window, or older than the newest state
E_NO_SESSION = 8       # unknown or expired session
E_NON_FINITE = 9       # NaN or infinity in a value
E_WORKSPACE = 10       # position outside the declared workspace, increment or quaternion implausible
E_FULL = 11            # no free master slot
E_BUSY = 12            # the device id already has a live session
E_TIMEOUT = 13         # the session was dropped after silence
E_CAPABILITY = 14      # HELLO values out of range
E_DIRECTION = 15       # a message type the receiver never accepts (e.g. FEEDBACK sent to the service)
E_COOKIE = 16          # HELLO cookie invalid or expired (answered with a fresh COOKIE)
ERROR_NAMES = {
    E_OK: "ok", E_MALFORMED: "malformed", E_VERSION: "version", E_TRUNCATED: "truncated",
    E_OVERSIZED: "oversized", E_AUTH: "auth", E_REPLAY: "replay", E_STALE: "stale",
    E_NO_SESSION: "no_session", E_NON_FINITE: "non_finite", E_WORKSPACE: "workspace", E_FULL: "full",
    E_BUSY: "busy", E_TIMEOUT: "timeout", E_CAPABILITY: "capability", E_DIRECTION: "direction", E_COOKIE: "cookie",
}

# limits the receivers enforce
WINDOW = 64                     # replay window, sequences
DEFAULT_TIMEOUT_MS = 50
MAX_TIMEOUT_MS = 1000
MAX_FORCE_N = 1000.0
MAX_EXTENT_M = 10.0             # |workspace coordinate| bound
MAX_RATE_HZ = 10000.0
WORKSPACE_MARGIN_M = 0.001      # positions may exceed the declared workspace by this much
QUAT_TOL = 1e-3                 # | |q| - 1 | bound for a valid orientation
SESSION_LABEL = b"pointfence v2 session"
COOKIE_VALID_S = 2.0            # a HELLO's cookie opens a session only this long after it was issued
PROOF_S = 0.5                   # a session that has sent no valid STATE this long after WELCOME holds nothing


class ProtocolError(PointfenceError, ValueError):
    """A datagram was rejected; ``code`` is one of the ``E_*`` constants."""

    def __init__(self, code: int, message: str = ""):
        self.code = int(code)
        super().__init__(f"{ERROR_NAMES.get(self.code, self.code)}: {message}" if message else ERROR_NAMES.get(self.code, str(code)))


# --- keys ---------------------------------------------------------------------------------------
def session_key(psk: bytes, client_nonce: bytes, server_nonce: bytes, device_id: int, session_id: int) -> bytes:
    """The 32-byte key of one session (STATE, FEEDBACK and BYE are tagged with it)."""
    msg = SESSION_LABEL + bytes(client_nonce) + bytes(server_nonce) + struct.pack("<II", device_id, session_id)
    return hmac.digest(psk, msg, "sha256")


def tag(key: bytes, body) -> bytes:
    return hmac.digest(key, body, "sha256")[:TAG_LEN]


# --- header --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Header:
    type: int
    device_id: int
    session: int
    seq: int


def parse_header(buf) -> Header:
    """Size, magic, version and type checks (no key needed); raises ProtocolError."""
    n = len(buf)
    if n < HEADER_LEN + TAG_LEN:
        raise ProtocolError(E_TRUNCATED, f"{n} bytes, below the smallest message ({HEADER_LEN + TAG_LEN})")
    magic, version, typ, dev, sess, seq, rsv = HEADER.unpack_from(buf, 0)
    if magic != MAGIC:
        raise ProtocolError(E_MALFORMED, "bad magic")
    if version != VERSION:
        raise ProtocolError(E_VERSION, f"version {version}, expected {VERSION}")
    size = SIZES.get(typ)
    if size is None:
        raise ProtocolError(E_MALFORMED, f"unknown message type {typ}")
    if n < size:
        raise ProtocolError(E_TRUNCATED, f"{TYPE_NAMES[typ]} of {n} bytes, expected {size}")
    if n > size:
        raise ProtocolError(E_OVERSIZED, f"{TYPE_NAMES[typ]} of {n} bytes, expected {size}")
    if rsv:
        raise ProtocolError(E_MALFORMED, "header reserved field set")
    return Header(typ, dev, sess, seq)


def verify(buf, key: bytes) -> None:
    """Constant-time check of the trailing tag; raises ProtocolError(E_AUTH)."""
    mv = memoryview(buf)
    if not hmac.compare_digest(hmac.digest(key, mv[:-TAG_LEN], "sha256")[:TAG_LEN], bytes(mv[-TAG_LEN:])):
        raise ProtocolError(E_AUTH, "tag does not verify")


def _seal(key: bytes, head: bytes, payload: bytes) -> bytes:
    body = head + payload
    return body + tag(key, body)


def _head(typ: int, device_id: int, session: int, seq: int) -> bytes:
    return HEADER.pack(MAGIC, VERSION, typ, device_id & 0xFFFFFFFF, session & 0xFFFFFFFF, seq & 0xFFFFFFFFFFFFFFFF, 0)


def _finite(values, what: str) -> None:
    for v in values:
        if not math.isfinite(v):
            raise ProtocolError(E_NON_FINITE, f"{what} is not finite")


# --- messages ------------------------------------------------------------------------------------
@dataclass
class Hello:
    """Client -> service, PSK-tagged: device capabilities, a fresh 16-byte nonce and the cookie
    (``COOKIE_LEN`` zero bytes in the first HELLO of a handshake; the service's COOKIE in the second)."""

    nonce: bytes
    max_force: float = 3.3
    workspace_min: Tuple[float, float, float] = (-0.1, -0.1, -0.1)
    workspace_max: Tuple[float, float, float] = (0.1, 0.1, 0.1)
    rate_hz: float = 1000.0
    timeout_ms: int = DEFAULT_TIMEOUT_MS
    caps: int = CAP_FORCE | CAP_CLUTCH
    model: str = ""
    cookie: bytes = bytes(COOKIE_LEN)

    def encode(self, psk: bytes, device_id: int, seq: int = 0) -> bytes:
        model = self.model.encode("ascii")[:16]
        return _seal(psk, _head(HELLO, device_id, 0, seq),
                     P_HELLO.pack(bytes(self.nonce), self.max_force, *self.workspace_min, *self.workspace_max,
                                  self.rate_hz, self.timeout_ms, self.caps, 0, model, bytes(self.cookie)))

    @classmethod
    def decode(cls, buf) -> "Hello":
        v = P_HELLO.unpack_from(buf, HEADER_LEN)
        nonce, fmax, wmin, wmax, rate, tmo, caps, rsv, model = v[0], v[1], v[2:5], v[5:8], v[8], v[9], v[10], v[11], v[12]
        cookie = v[13]
        _finite((fmax, *wmin, *wmax, rate), "HELLO value")
        if rsv or caps & ~CAP_MASK:
            raise ProtocolError(E_MALFORMED, "HELLO reserved bits set")
        m = model.rstrip(b"\0")
        if b"\0" in m or any(c < 0x20 or c > 0x7E for c in m):
            raise ProtocolError(E_MALFORMED, "HELLO model is not NUL-padded printable ASCII")
        if not 0 < fmax <= MAX_FORCE_N:
            raise ProtocolError(E_CAPABILITY, f"max_force {fmax} N outside (0, {MAX_FORCE_N}]")
        if not all(-MAX_EXTENT_M <= a < b <= MAX_EXTENT_M for a, b in zip(wmin, wmax)):
            raise ProtocolError(E_CAPABILITY, f"workspace {wmin}..{wmax} m empty or beyond {MAX_EXTENT_M} m")
        if not 1.0 <= rate <= MAX_RATE_HZ:
            raise ProtocolError(E_CAPABILITY, f"rate {rate} Hz outside [1, {MAX_RATE_HZ}]")
        if tmo > MAX_TIMEOUT_MS:
            raise ProtocolError(E_CAPABILITY, f"timeout {tmo} ms above {MAX_TIMEOUT_MS}")
        return cls(bytes(nonce), fmax, tuple(wmin), tuple(wmax), rate, tmo, caps, m.decode("ascii"), bytes(cookie))

    @property
    def has_cookie(self) -> bool:
        """True for the second HELLO of a handshake (a cookie is present)."""
        return any(self.cookie)


@dataclass
class Welcome:
    """Service -> client, PSK-tagged: the session (id in the header), slot and link parameters."""

    client_nonce: bytes
    server_nonce: bytes
    slot: int
    timeout_ms: int
    rate_hz: float
    max_force: float
    t_service_ns: int

    def encode(self, psk: bytes, device_id: int, session: int, seq: int = 0) -> bytes:
        return _seal(psk, _head(WELCOME, device_id, session, seq),
                     P_WELCOME.pack(self.client_nonce, self.server_nonce, self.slot, self.timeout_ms, 0,
                                    self.rate_hz, self.max_force, self.t_service_ns & 0xFFFFFFFFFFFFFFFF))

    @classmethod
    def decode(cls, buf) -> "Welcome":
        cn, sn, slot, tmo, rsv, rate, fmax, tns = P_WELCOME.unpack_from(buf, HEADER_LEN)
        _finite((rate, fmax), "WELCOME value")
        if rsv:
            raise ProtocolError(E_MALFORMED, "WELCOME reserved field set")
        if not (1 <= tmo <= MAX_TIMEOUT_MS and 1.0 <= rate <= MAX_RATE_HZ and 0 <= fmax <= MAX_FORCE_N):
            raise ProtocolError(E_CAPABILITY, "WELCOME values out of range")
        return cls(bytes(cn), bytes(sn), slot, tmo, rate, fmax, tns)


@dataclass
class Reject:
    """Service -> client, PSK-tagged: why a HELLO was refused."""

    client_nonce: bytes
    error: int

    def encode(self, psk: bytes, device_id: int, seq: int = 0) -> bytes:
        return _seal(psk, _head(REJECT, device_id, 0, seq), P_REJECT.pack(self.client_nonce, self.error, 0, 0))

    @classmethod
    def decode(cls, buf) -> "Reject":
        cn, err, r1, r2 = P_REJECT.unpack_from(buf, HEADER_LEN)
        if r1 or r2:
            raise ProtocolError(E_MALFORMED, "REJECT reserved field set")
        return cls(bytes(cn), err)


@dataclass
class Cookie:
    """Service -> client, PSK-tagged: the stateless challenge answering a HELLO without a valid
    cookie. The client repeats its HELLO (same nonce) with ``cookie`` in it."""

    client_nonce: bytes
    cookie: bytes

    def encode(self, psk: bytes, device_id: int, seq: int = 0) -> bytes:
        return _seal(psk, _head(COOKIE, device_id, 0, seq), P_COOKIE.pack(bytes(self.client_nonce), bytes(self.cookie)))

    @classmethod
    def decode(cls, buf) -> "Cookie":
        cn, ck = P_COOKIE.unpack_from(buf, HEADER_LEN)
        if not any(ck):
            raise ProtocolError(E_MALFORMED, "COOKIE of zero bytes")
        return cls(bytes(cn), bytes(ck))


@dataclass
class State:
    """Client -> service, session-tagged: one master sample (master frame, SI units)."""

    t_client_ns: int = 0
    t_echo_ns: int = 0
    position: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    increment: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation: Tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)   # w, x, y, z
    grasp: float = 0.0
    buttons: int = 0
    flags: int = F_CLUTCH

    @property
    def clutch(self) -> bool:
        return bool(self.flags & F_CLUTCH)

    def encode(self, skey: bytes, device_id: int, session: int, seq: int) -> bytes:
        return _seal(skey, _head(STATE, device_id, session, seq),
                     P_STATE.pack(self.t_client_ns & 0xFFFFFFFFFFFFFFFF, self.t_echo_ns & 0xFFFFFFFFFFFFFFFF,
                                  *self.position, *self.increment, *self.orientation, self.grasp,
                                  self.buttons & 0xFFFFFFFF, self.flags, 0))

    @classmethod
    def decode(cls, buf, workspace=None) -> "State":
        """Unpack and check the values; ``workspace`` = (min (3,), max (3,)) declared at HELLO."""
        v = P_STATE.unpack_from(buf, HEADER_LEN)
        pos, inc, quat = v[2:5], v[5:8], v[8:12]
        grasp, buttons, flags, rsv = v[12], v[13], v[14], v[15]
        if rsv or flags & ~FLAG_MASK:
            raise ProtocolError(E_MALFORMED, "STATE reserved bits set")
        _finite(v[2:13], "STATE value")
        check_state_values(pos, inc, quat, flags, workspace)
        return cls(v[0], v[1], pos, inc, quat, grasp, buttons, flags)


def check_state_values(pos, inc, quat, flags, workspace) -> None:
    """Workspace and plausibility checks of a (finite) master sample; raises E_WORKSPACE."""
    if workspace is not None:
        lo, hi = workspace
        m = WORKSPACE_MARGIN_M
        for i in range(3):
            if not lo[i] - m <= pos[i] <= hi[i] + m:
                raise ProtocolError(E_WORKSPACE, f"position[{i}] = {pos[i]} m outside [{lo[i]}, {hi[i]}] m")
            if abs(inc[i]) > hi[i] - lo[i] + 2 * m:
                raise ProtocolError(E_WORKSPACE, f"increment[{i}] = {inc[i]} m larger than the workspace")
    else:
        for i in range(3):
            if abs(pos[i]) > MAX_EXTENT_M or abs(inc[i]) > 2 * MAX_EXTENT_M:
                raise ProtocolError(E_WORKSPACE, f"position or increment beyond {MAX_EXTENT_M} m")
    if flags & F_ORIENTATION:
        n = math.sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3])
        if abs(n - 1.0) > QUAT_TOL:
            raise ProtocolError(E_WORKSPACE, f"orientation quaternion of norm {n}, expected 1")


@dataclass
class Feedback:
    """Service -> client, session-tagged: the force to display and the state behind it."""

    tick: int = 0
    t_tick_ns: int = 0
    t_sent_ns: int = 0
    echo_seq: int = 0
    echo_t_client_ns: int = 0
    force: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    proxy: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    robot: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    contact: int = CONTACT_FREE
    fixture: int = 0
    robot_mode: int = ROBOT_IDEAL
    link: int = 0
    hold: int = 0
    error: int = E_OK
    slot: int = 0
    rejected: int = 0

    def encode(self, skey: bytes, device_id: int, session: int, seq: int) -> bytes:
        return _seal(skey, _head(FEEDBACK, device_id, session, seq), self.pack_payload())

    def pack_payload(self) -> bytes:
        M = 0xFFFFFFFFFFFFFFFF
        return P_FEEDBACK.pack(self.tick & M, self.t_tick_ns & M, self.t_sent_ns & M, self.echo_seq & M,
                               self.echo_t_client_ns & M, *self.force, *self.proxy, *self.robot, self.contact,
                               self.fixture, self.robot_mode, self.link, self.hold & 0xFFFFFFFF, self.error, self.slot,
                               self.rejected & 0xFFFFFFFF, 0)

    @classmethod
    def decode(cls, buf) -> "Feedback":
        v = P_FEEDBACK.unpack_from(buf, HEADER_LEN)
        if v[22]:
            raise ProtocolError(E_MALFORMED, "FEEDBACK reserved field set")
        _finite(v[5:14], "FEEDBACK value")
        return cls(v[0], v[1], v[2], v[3], v[4], v[5:8], v[8:11], v[11:14], v[14], v[15], v[16], v[17], v[18],
                   v[19], v[20], v[21])


@dataclass
class Bye:
    """Either direction, session-tagged: the session ends now (``reason``: an E_* code, 0 normal)."""

    reason: int = E_OK

    def encode(self, skey: bytes, device_id: int, session: int, seq: int) -> bytes:
        return _seal(skey, _head(BYE, device_id, session, seq), P_BYE.pack(self.reason, 0, 0))

    @classmethod
    def decode(cls, buf) -> "Bye":
        reason, r1, r2 = P_BYE.unpack_from(buf, HEADER_LEN)
        if r1 or r2:
            raise ProtocolError(E_MALFORMED, "BYE reserved field set")
        return cls(reason)


DECODERS = {HELLO: Hello, WELCOME: Welcome, REJECT: Reject, STATE: State, FEEDBACK: Feedback, BYE: Bye, COOKIE: Cookie}


def decode(buf, key: bytes, workspace=None):
    """Full check of one datagram with the key of its type: (Header, message). For tests and tools;
    the service and the client pick the key from the header first (PSK or session key)."""
    h = parse_header(buf)
    verify(buf, key)
    cls = DECODERS[h.type]
    msg = cls.decode(buf, workspace) if h.type == STATE else cls.decode(buf)
    return h, msg


# --- replay window -------------------------------------------------------------------------------
@dataclass
class ReplayWindow:
    """Anti-replay over 64-bit sequences (RFC 4303 style, ``size`` <= 64): a sequence is new if it
    is above the highest seen, or inside the window below it and not yet seen. ``check`` raises,
    ``commit`` records (call it only after the tag verified)."""

    size: int = WINDOW
    top: int = 0
    bits: int = 0           # bit i set: sequence top - i seen
    _mask: int = field(default=0, repr=False)

    def __post_init__(self):
        if not 1 <= self.size <= 64:
            raise ValueError("window size must be 1..64")
        self._mask = (1 << self.size) - 1

    def check(self, seq: int) -> None:
        if seq == 0:
            raise ProtocolError(E_STALE, "sequence 0 is never valid in a session")
        if seq > self.top:
            return
        d = self.top - seq
        if d >= self.size:
            raise ProtocolError(E_STALE, f"sequence {seq} older than the window (newest {self.top})")
        if self.bits >> d & 1:
            raise ProtocolError(E_REPLAY, f"sequence {seq} already received")

    def commit(self, seq: int) -> bool:
        """Record ``seq``; True if it is the newest so far."""
        if seq > self.top:
            shift = seq - self.top
            self.bits = ((self.bits << shift) | 1) & self._mask if shift < 64 else 1
            self.top = seq
            return True
        self.bits |= 1 << (self.top - seq)
        return False
