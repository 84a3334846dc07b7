"""Writes the protocol test vectors in ``clients/vectors/*.json`` (deterministic: fixed keys and
nonces). Both SDKs must reproduce every ``bytes_hex`` byte for byte and every expected error.

    python -m pointfence.clients.vectors_gen [OUT_DIR]      # default: clients/vectors beside this file

Files: ``sha256.json`` and ``hmac_sha256.json`` (FIPS 180 / RFC 4231 cases, computed here with
hashlib), ``session_keys.json``, ``messages.json`` (fields -> exact bytes, one per message type
and edge cases), ``rejects.json`` (datagrams -> the error code the receiver must give) and
``replay.json`` (sequence streams -> accept / replay / stale) and ``keyfiles.json`` (key file
contents and modes -> the key, or the class of refusal: ``mode``, ``format``, ``zero``).
"""
from __future__ import annotations

import hashlib
import hmac
import json
import struct
import sys
from pathlib import Path

from . import protocol as P

PSK = bytes(range(0x20, 0x40))                      # 32 bytes 20 21 ... 3f
CLIENT_NONCE = bytes.fromhex("00112233445566778899aabbccddeeff")
SERVER_NONCE = bytes.fromhex("f0e1d2c3b4a5968778695a4b3c2d1e0f")
DEVICE, SESSION = 0x01020304, 0xA1B2C3D4
WS = ((-0.08, -0.06, -0.05), (0.08, 0.06, 0.07))
COOKIE = bytes.fromhex("0807060504030201") + bytes(range(0xC0, 0xD0))   # opaque to clients: any 24 bytes


def _hex(b) -> str:
    return bytes(b).hex()


def sha256_vectors():
    msgs = [b"", b"abc", b"abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq",
            b"abcdefghbcdefghicdefghijdefghijkefghijklfghijklmghijklmnhijklmnoijklmnopjklmnopqklmnopqrlmnopqrsmnopqrstnopqrstu",
            bytes(range(256)) * 4 + b"x" * 55, b"a" * 55, b"a" * 56, b"a" * 63, b"a" * 64, b"a" * 65]
    return [{"message_hex": _hex(m), "digest_hex": hashlib.sha256(m).hexdigest()} for m in msgs]


def hmac_vectors():
    cases = [  # RFC 4231 test cases 1, 2, 3, 4, 6, 7
        (b"\x0b" * 20, b"Hi There"),
        (b"Jefe", b"what do ya want for nothing?"),
        (b"\xaa" * 20, b"\xdd" * 50),
        (bytes(range(1, 26)), b"\xcd" * 50),
        (b"\xaa" * 131, b"Test Using Larger Than Block-Size Key - Hash Key First"),
        (b"\xaa" * 131, b"This is a test using a larger than block-size key and a larger than block-size data. "
                        b"The key needs to be hashed before being used by the HMAC algorithm."),
        (PSK, b"pointfence"),
    ]
    return [{"key_hex": _hex(k), "data_hex": _hex(d), "mac_hex": hmac.new(k, d, hashlib.sha256).hexdigest()}
            for k, d in cases]


def session_key_vectors():
    out = []
    for psk, cn, sn, dev, sid in [(PSK, CLIENT_NONCE, SERVER_NONCE, DEVICE, SESSION),
                                  (b"\x00" * 16, b"\x00" * 16, b"\xff" * 16, 0, 1),
                                  (bytes(range(64)), SERVER_NONCE, CLIENT_NONCE, 0xFFFFFFFF, 0xFFFFFFFF)]:
        out.append({"psk_hex": _hex(psk), "client_nonce_hex": _hex(cn), "server_nonce_hex": _hex(sn),
                    "device_id": dev, "session": sid, "session_key_hex": _hex(P.session_key(psk, cn, sn, dev, sid))})
    return out


def _skey():
    return P.session_key(PSK, CLIENT_NONCE, SERVER_NONCE, DEVICE, SESSION)


def message_vectors():
    skey = _skey()
    v = []

    def add(name, typ, key_name, key, seq, session, fields, data):
        v.append({"name": name, "type": P.TYPE_NAMES[typ], "key": key_name, "key_hex": _hex(key), "device_id": DEVICE,
                  "session": session, "seq": seq, "fields": fields, "size": len(data), "bytes_hex": _hex(data)})

    def hello_fields(h):
        return {"nonce_hex": _hex(h.nonce), "max_force": h.max_force, "workspace_min": list(h.workspace_min),
                "workspace_max": list(h.workspace_max), "rate_hz": h.rate_hz, "timeout_ms": h.timeout_ms,
                "caps": h.caps, "model": h.model, "cookie_hex": _hex(h.cookie)}

    hello = P.Hello(CLIENT_NONCE, 3.3, WS[0], WS[1], 1000.0, 50, P.CAP_FORCE | P.CAP_CLUTCH | P.CAP_GRASP, "Touch")
    add("hello", P.HELLO, "psk", PSK, 1, 0, hello_fields(hello), hello.encode(PSK, DEVICE, 1))
    h2 = P.Hello(SERVER_NONCE, 12.0, (-0.2, -0.2, -0.2), (0.2, 0.2, 0.2), 4000.0, 20, P.CAP_MASK, "sigma.7 lefthand")
    add("hello-all-caps", P.HELLO, "psk", PSK, 0xFFFFFFFFFFFFFFFF, 0, hello_fields(h2),
        h2.encode(PSK, DEVICE, 0xFFFFFFFFFFFFFFFF))
    ck = P.Cookie(CLIENT_NONCE, COOKIE)
    add("cookie", P.COOKIE, "psk", PSK, 0, 0, {"client_nonce_hex": _hex(ck.client_nonce), "cookie_hex": _hex(ck.cookie)},
        ck.encode(PSK, DEVICE, 0))
    h3 = P.Hello(CLIENT_NONCE, 3.3, WS[0], WS[1], 1000.0, 50, P.CAP_FORCE | P.CAP_CLUTCH | P.CAP_GRASP, "Touch",
                 COOKIE)
    add("hello-with-cookie", P.HELLO, "psk", PSK, 2, 0, hello_fields(h3), h3.encode(PSK, DEVICE, 2))
    w = P.Welcome(CLIENT_NONCE, SERVER_NONCE, 1, 50, 1000.0, 3.3, 123456789012345)
    add("welcome", P.WELCOME, "psk", PSK, 0, SESSION,
        {"client_nonce_hex": _hex(w.client_nonce), "server_nonce_hex": _hex(w.server_nonce), "slot": w.slot,
         "timeout_ms": w.timeout_ms, "rate_hz": w.rate_hz, "max_force": w.max_force, "t_service_ns": w.t_service_ns},
        w.encode(PSK, DEVICE, SESSION, 0))
    r = P.Reject(CLIENT_NONCE, P.E_BUSY)
    add("reject-busy", P.REJECT, "psk", PSK, 0, 0, {"client_nonce_hex": _hex(r.client_nonce), "error": r.error},
        r.encode(PSK, DEVICE, 0))
    states = [
        ("state", 1, P.State(1_000_000_000, 999_000_000, (0.01, -0.02, 0.03), (1e-5, -2e-5, 0.0),
                             (1.0, 0.0, 0.0, 0.0), 0.0, 0, P.F_CLUTCH)),
        ("state-orientation-grasp", 2, P.State(1_001_000_000, 1_000_500_000, (-0.0123456789, 0.0456, -0.049),
                                               (-1.5e-6, 2.5e-7, -3.125e-3), (0.5, 0.5, -0.5, 0.5), 0.7853981633974483,
                                               0xFFFFFFFF, P.F_CLUTCH | P.F_ORIENTATION | P.F_GRASP)),
        ("state-pedal-up", 0x0123456789ABCDEF, P.State(18446744073709551615, 0, (-0.0, 5e-324, 0.07),
                                                       (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 0.0, 5, 0)),
    ]
    for name, seq, s in states:
        add(name, P.STATE, "session", skey, seq, SESSION,
            {"t_client_ns": s.t_client_ns, "t_echo_ns": s.t_echo_ns, "position": list(s.position),
             "increment": list(s.increment), "orientation": list(s.orientation), "grasp": s.grasp,
             "buttons": s.buttons, "flags": s.flags}, s.encode(skey, DEVICE, SESSION, seq))
    fb = P.Feedback(1234, 5_000_000_000, 5_000_120_000, 1, 1_000_000_000, (0.5, -1.25, 3.3), (0.01, -0.02, 0.14),
                    (0.0101, -0.0199, 0.1405), P.CONTACT_CONTACT, P.FX_HAPTICS | P.FX_TELEOP | P.FX_COUPLED | P.FX_FIXTURE,
                    P.ROBOT_ENABLED, 0, 0, P.E_OK, 1, 0)
    fb2 = P.Feedback(99, 7, 8, 0x0123456789ABCDEF, 0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
                     P.CONTACT_ENTRENCHED, 0, P.ROBOT_HOLDING, 0, 8 | 2, P.E_WORKSPACE, 65535, 4294967295)
    for name, seq, f in (("feedback", 1, fb), ("feedback-holding", 77, fb2)):
        add(name, P.FEEDBACK, "session", skey, seq, SESSION,
            {"tick": f.tick, "t_tick_ns": f.t_tick_ns, "t_sent_ns": f.t_sent_ns, "echo_seq": f.echo_seq,
             "echo_t_client_ns": f.echo_t_client_ns, "force": list(f.force), "proxy": list(f.proxy),
             "robot": list(f.robot), "contact": f.contact, "fixture": f.fixture, "robot_mode": f.robot_mode,
             "link": f.link, "hold": f.hold, "error": f.error, "slot": f.slot, "rejected": f.rejected},
            f.encode(skey, DEVICE, SESSION, seq))
    b = P.Bye(P.E_OK)
    add("bye", P.BYE, "session", skey, 9, SESSION, {"reason": b.reason}, b.encode(skey, DEVICE, SESSION, 9))
    return v


def _retag(data: bytearray, key: bytes) -> bytes:
    data[-P.TAG_LEN:] = P.tag(key, bytes(data[:-P.TAG_LEN]))
    return bytes(data)


def reject_vectors():
    """Datagrams a receiver must refuse, with the error it must give (checks run in the order:
    size/magic/version/type, tag, values; see PROTOCOL.md)."""
    skey = _skey()
    good = P.State(1, 0, (0.01, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), 0.0, 0, P.F_CLUTCH)
    base = bytearray(good.encode(skey, DEVICE, SESSION, 5))
    hello = bytearray(P.Hello(CLIENT_NONCE, 3.3, WS[0], WS[1], 1000.0, 50, 9, "Touch").encode(PSK, DEVICE, 1))
    out = []

    def add(name, data, key, code, workspace=True):
        out.append({"name": name, "bytes_hex": _hex(data), "key_hex": _hex(key), "workspace_min": list(WS[0]),
                    "workspace_max": list(WS[1]), "use_workspace": workspace, "error": P.ERROR_NAMES[code],
                    "code": code})

    add("empty", b"", skey, P.E_TRUNCATED)
    add("header-only", base[:P.HEADER_LEN], skey, P.E_TRUNCATED)
    add("state-truncated", base[:-1], skey, P.E_TRUNCATED)
    add("state-oversized", bytes(base) + b"\0", skey, P.E_OVERSIZED)
    m = bytearray(base); m[0] = ord("X")
    add("bad-magic", m, skey, P.E_MALFORMED)
    m = bytearray(base); m[2] = 1
    add("version-1", _retag(m, skey), skey, P.E_VERSION)
    m = bytearray(base); m[3] = 9
    add("unknown-type", m, skey, P.E_MALFORMED)
    m = bytearray(base); m[-1] ^= 1
    add("tag-bit-flip", m, skey, P.E_AUTH)
    m = bytearray(base); m[40] ^= 0x80
    add("payload-bit-flip", m, skey, P.E_AUTH)
    add("wrong-key", bytes(base), PSK, P.E_AUTH)
    m = bytearray(base); m[-P.TAG_LEN:] = b"\0" * P.TAG_LEN
    add("zero-tag", m, skey, P.E_AUTH)
    off = P.HEADER_LEN + 16       # position x
    m = bytearray(base); m[off:off + 8] = struct.pack("<d", float("nan"))
    add("nan-position-authentic", _retag(m, skey), skey, P.E_NON_FINITE)
    m = bytearray(base); m[off + 8:off + 16] = struct.pack("<d", float("inf"))
    add("inf-position-authentic", _retag(m, skey), skey, P.E_NON_FINITE)
    m = bytearray(base); m[off + 16:off + 24] = struct.pack("<d", 0.5)
    add("outside-workspace-authentic", _retag(m, skey), skey, P.E_WORKSPACE)
    m = bytearray(base); m[off:off + 8] = struct.pack("<d", 11.0)
    add("beyond-10m-no-workspace", _retag(m, skey), skey, P.E_WORKSPACE, workspace=False)
    q = P.HEADER_LEN + 64         # quaternion w
    m = bytearray(base); m[q:q + 8] = struct.pack("<d", 0.9)
    m[P.HEADER_LEN + 108:P.HEADER_LEN + 110] = struct.pack("<H", P.F_CLUTCH | P.F_ORIENTATION)
    add("non-unit-quaternion-authentic", _retag(m, skey), skey, P.E_WORKSPACE)
    m = bytearray(base); m[P.HEADER_LEN + 108:P.HEADER_LEN + 110] = struct.pack("<H", 0x80)
    add("unknown-flag-authentic", _retag(m, skey), skey, P.E_MALFORMED)
    m = bytearray(base); m[P.HEADER_LEN + 110:P.HEADER_LEN + 112] = struct.pack("<H", 1)
    add("reserved-set-authentic", _retag(m, skey), skey, P.E_MALFORMED)
    add("hello-wrong-key", hello, skey, P.E_AUTH)
    m = bytearray(hello); m[P.HEADER_LEN + 16:P.HEADER_LEN + 24] = struct.pack("<d", -1.0)
    add("hello-negative-force", _retag(m, PSK), PSK, P.E_CAPABILITY)
    m = bytearray(hello); m[P.HEADER_LEN + 24:P.HEADER_LEN + 32] = struct.pack("<d", 0.5)
    add("hello-empty-workspace", _retag(m, PSK), PSK, P.E_CAPABILITY)
    m = bytearray(hello); m[P.HEADER_LEN + 24:P.HEADER_LEN + 32] = struct.pack("<d", float("nan"))
    add("hello-nan-workspace", _retag(m, PSK), PSK, P.E_NON_FINITE)
    m = bytearray(hello); m[P.HEADER_LEN + 82:P.HEADER_LEN + 84] = struct.pack("<H", 0x10)
    add("hello-unknown-cap", _retag(m, PSK), PSK, P.E_MALFORMED)
    m = bytearray(hello); m[P.HEADER_LEN + 88] = 7
    add("hello-model-control-char", _retag(m, PSK), PSK, P.E_MALFORMED)
    add("cookie-of-zeros", P.Cookie(CLIENT_NONCE, bytes(P.COOKIE_LEN)).encode(PSK, DEVICE, 0), PSK, P.E_MALFORMED)
    m = bytearray(P.Cookie(CLIENT_NONCE, COOKIE).encode(PSK, DEVICE, 0)); m[P.HEADER_LEN + 20] ^= 1
    add("cookie-bit-flip", m, PSK, P.E_AUTH)
    return out


def keyfile_vectors():
    """Key file contents (hex of the file's bytes) and mode -> accepted key, or the refusal class.
    Both loaders (``keyfile.load_key``, C ``pf_load_key``) must agree on every case."""
    k = PSK.hex()
    cases = [
        ("hex-newline", (k + "\n").encode(), 0o600, "ok"),
        ("hex-no-newline", k.encode(), 0o600, "ok"),
        ("hex-crlf", (k + "\r\n").encode(), 0o600, "ok"),
        ("hex-upper", (k.upper() + "\n").encode(), 0o600, "ok"),
        ("owner-read-only", (k + "\n").encode(), 0o400, "ok"),
        ("16-bytes", (k[:32] + "\n").encode(), 0o600, "ok"),
        ("64-bytes", (k * 2 + "\n").encode(), 0o600, "ok"),
        ("15-bytes", (k[:30] + "\n").encode(), 0o600, "format"),
        ("65-bytes", (k * 2 + "ab\n").encode(), 0o600, "format"),
        ("odd-digits", (k[:-1] + "\n").encode(), 0o600, "format"),
        ("two-newlines", (k + "\n\n").encode(), 0o600, "format"),
        ("trailing-space", (k + " \n").encode(), 0o600, "format"),
        ("leading-space", (" " + k + "\n").encode(), 0o600, "format"),
        ("trailing-junk", (k + " junk\n").encode(), 0o600, "format"),
        ("second-line", (k + "\n# my key\n").encode(), 0o600, "format"),
        ("lone-cr", (k + "\r").encode(), 0o600, "format"),
        ("nul-after", (k + "\0").encode(), 0o600, "format"),
        ("0x-prefix", ("0x" + k + "\n").encode(), 0o600, "format"),
        ("raw-bytes", PSK, 0o600, "format"),
        ("empty", b"", 0o600, "format"),
        ("newline-only", b"\n", 0o600, "format"),
        ("all-zero", ("00" * 32 + "\n").encode(), 0o600, "zero"),
        ("all-zero-16", ("0" * 32).encode(), 0o600, "zero"),
        ("mode-644", (k + "\n").encode(), 0o644, "mode"),
        ("mode-640", (k + "\n").encode(), 0o640, "mode"),
        ("mode-604", (k + "\n").encode(), 0o604, "mode"),
        ("mode-620", (k + "\n").encode(), 0o620, "mode"),
    ]
    out = []
    for name, data, mode, result in cases:
        key = bytes.fromhex(data.decode().strip()) if result == "ok" else b""
        out.append({"name": name, "content_hex": _hex(data), "mode": mode, "result": result, "key_hex": _hex(key)})
    return out


def replay_vectors():
    streams = [
        [1, 2, 3, 3, 2, 4],
        [10, 5, 5, 70, 6, 7, 10, 71, 69, 200, 137, 136],
        [0, 1, 0],
        [18446744073709551615, 18446744073709551614, 18446744073709551615],
        [100, 37, 36, 99, 99],
    ]
    out = []
    for s in streams:
        w = P.ReplayWindow()
        res = []
        for q in s:
            try:
                w.check(q)
                res.append("new" if w.commit(q) else "late")
            except P.ProtocolError as e:
                res.append(P.ERROR_NAMES[e.code])
        out.append({"window": P.WINDOW, "sequence": s, "result": res})
    return out


def generate() -> dict:
    return {
        "sha256.json": {"cases": sha256_vectors()},
        "hmac_sha256.json": {"cases": hmac_vectors()},
        "session_keys.json": {"label_hex": _hex(P.SESSION_LABEL), "cases": session_key_vectors()},
        "messages.json": {"protocol_version": P.VERSION, "sizes": {P.TYPE_NAMES[t]: n for t, n in P.SIZES.items()},
                          "vectors": message_vectors()},
        "rejects.json": {"error_codes": {name: code for code, name in P.ERROR_NAMES.items()}, "vectors": reject_vectors()},
        "replay.json": {"streams": replay_vectors()},
        "keyfiles.json": {"cases": keyfile_vectors()},
    }


def write(out_dir) -> list:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = []
    for name, doc in generate().items():
        (out / name).write_text(json.dumps(doc, indent=1) + "\n")
        names.append(str(out / name))
    return names


if __name__ == "__main__":
    target = sys.argv[1] if len(sys.argv) > 1 else Path(__file__).resolve().parent / "vectors"
    for n in write(target):
        print(n)
