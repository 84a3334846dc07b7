"""Wire protocol v2: the test vectors (Python side; the C SDK runs the same files under ctest),
layout, keys, replay window."""
import hashlib
import hmac
import json
import struct
from pathlib import Path

import pytest

from pointfence.clients import protocol as P
from pointfence.clients import vectors_gen

VEC = Path(__file__).resolve().parents[1] / "clients" / "vectors"


def load(name):
    return json.loads((VEC / name).read_text())


def test_vector_files_are_exactly_what_the_generator_writes():
    for name, doc in vectors_gen.generate().items():
        assert json.loads(json.dumps(doc)) == load(name), f"{name} is stale: run python -m pointfence.clients.vectors_gen"


def test_sizes_are_fixed_and_documented():
    assert P.HEADER_LEN == 24 and P.TAG_LEN == 16
    assert P.SIZES == {P.HELLO: 168, P.WELCOME: 104, P.REJECT: 64, P.STATE: 152, P.FEEDBACK: 172, P.BYE: 48,
                       P.COOKIE: 80}
    assert load("messages.json")["sizes"] == {P.TYPE_NAMES[t]: n for t, n in P.SIZES.items()}
    doc = (Path(__file__).resolve().parents[1] / "clients" / "PROTOCOL.md").read_text()
    for t, n in P.SIZES.items():
        assert f"{P.TYPE_NAMES[t]}" in doc and str(n) in doc


def test_rfc4231_hmac_values():
    cases = load("hmac_sha256.json")["cases"]
    assert cases[0]["mac_hex"] == "b0344c61d8db38535ca8afceaf0bf12b881dc200c9833da726e9376c2e32cff7"
    assert cases[1]["mac_hex"] == "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
    for c in cases:
        assert hmac.new(bytes.fromhex(c["key_hex"]), bytes.fromhex(c["data_hex"]), hashlib.sha256).hexdigest() == c["mac_hex"]


def test_session_keys():
    for c in load("session_keys.json")["cases"]:
        k = P.session_key(bytes.fromhex(c["psk_hex"]), bytes.fromhex(c["client_nonce_hex"]),
                          bytes.fromhex(c["server_nonce_hex"]), c["device_id"], c["session"])
        assert k.hex() == c["session_key_hex"]


def _from_fields(v):
    f = v["fields"]
    typ = v["type"]
    if typ == "HELLO":
        return P.Hello(bytes.fromhex(f["nonce_hex"]), f["max_force"], tuple(f["workspace_min"]), tuple(f["workspace_max"]),
                       f["rate_hz"], f["timeout_ms"], f["caps"], f["model"], bytes.fromhex(f["cookie_hex"]))
    if typ == "COOKIE":
        return P.Cookie(bytes.fromhex(f["client_nonce_hex"]), bytes.fromhex(f["cookie_hex"]))
    if typ == "WELCOME":
        return P.Welcome(bytes.fromhex(f["client_nonce_hex"]), bytes.fromhex(f["server_nonce_hex"]), f["slot"],
                         f["timeout_ms"], f["rate_hz"], f["max_force"], f["t_service_ns"])
    if typ == "REJECT":
        return P.Reject(bytes.fromhex(f["client_nonce_hex"]), f["error"])
    if typ == "STATE":
        return P.State(f["t_client_ns"], f["t_echo_ns"], tuple(f["position"]), tuple(f["increment"]),
                       tuple(f["orientation"]), f["grasp"], f["buttons"], f["flags"])
    if typ == "FEEDBACK":
        return P.Feedback(f["tick"], f["t_tick_ns"], f["t_sent_ns"], f["echo_seq"], f["echo_t_client_ns"],
                          tuple(f["force"]), tuple(f["proxy"]), tuple(f["robot"]), f["contact"], f["fixture"],
                          f["robot_mode"], f["link"], f["hold"], f["error"], f["slot"], f["rejected"])
    return P.Bye(f["reason"])


def test_message_vectors_byte_for_byte_and_back():
    vs = load("messages.json")["vectors"]
    assert {v["type"] for v in vs} == set(P.TYPE_NAMES.values())
    for v in vs:
        key = bytes.fromhex(v["key_hex"])
        msg = _from_fields(v)
        if v["type"] in ("HELLO", "REJECT", "COOKIE"):
            data = msg.encode(key, v["device_id"], v["seq"])
        elif v["type"] == "WELCOME":
            data = msg.encode(key, v["device_id"], v["session"], v["seq"])
        else:
            data = msg.encode(key, v["device_id"], v["session"], v["seq"])
        assert data.hex() == v["bytes_hex"], v["name"]
        h, back = P.decode(bytes.fromhex(v["bytes_hex"]), key)
        assert (h.device_id, h.session, h.seq) == (v["device_id"], v["session"], v["seq"])
        assert back == msg, v["name"]


def test_state_layout_by_hand():
    """The STATE vector rebuilt from the spec's table with struct and hmac alone."""
    v = next(x for x in load("messages.json")["vectors"] if x["name"] == "state-orientation-grasp")
    f = v["fields"]
    head = b"PF" + bytes([2, 4]) + struct.pack("<IIQI", v["device_id"], v["session"], v["seq"], 0)
    body = struct.pack("<QQ", f["t_client_ns"], f["t_echo_ns"])
    body += struct.pack("<3d3d4dd", *f["position"], *f["increment"], *f["orientation"], f["grasp"])
    body += struct.pack("<IHH", f["buttons"], f["flags"], 0)
    data = head + body
    data += hmac.new(bytes.fromhex(v["key_hex"]), data, hashlib.sha256).digest()[:16]
    assert data.hex() == v["bytes_hex"]


def test_reject_vectors_give_their_error():
    for v in load("rejects.json")["vectors"]:
        ws = (v["workspace_min"], v["workspace_max"]) if v["use_workspace"] else None
        with pytest.raises(P.ProtocolError) as e:
            P.decode(bytes.fromhex(v["bytes_hex"]), bytes.fromhex(v["key_hex"]), ws)
        assert e.value.code == v["code"], v["name"]


def test_replay_window_streams():
    for s in load("replay.json")["streams"]:
        w = P.ReplayWindow(s["window"])
        got = []
        for q in s["sequence"]:
            try:
                w.check(q)
                got.append("new" if w.commit(q) else "late")
            except P.ProtocolError as e:
                got.append(P.ERROR_NAMES[e.code])
        assert got == s["result"]


def test_keys_and_key_files(tmp_path):
    with pytest.raises(Exception, match="16 to 64 bytes"):
        P.check_key(b"short")
    with pytest.raises(Exception, match="all zero"):
        P.check_key(bytes(32))
    with pytest.raises(Exception, match="not found"):
        P.load_key(tmp_path / "missing")


#: what each refusal class of keyfiles.json must say (the user's next step)
KEY_ERRORS = {"mode": r"mode 0\d+.*chmod 600 .*--new-key", "format": r"hex digit|empty|longer than",
              "zero": r"all zero.*--new-key"}


def test_key_file_table_shared_with_the_c_sdk(tmp_path):
    """clients/vectors/keyfiles.json: contents and mode -> key or refusal (the C ctest runs it too)."""
    cases = load("keyfiles.json")["cases"]
    assert {c["result"] for c in cases} == {"ok", "mode", "format", "zero"}
    for i, c in enumerate(cases):
        p = tmp_path / f"k{i}"
        p.write_bytes(bytes.fromhex(c["content_hex"]))
        p.chmod(c["mode"])
        if c["result"] == "ok":
            assert P.load_key(p).hex() == c["key_hex"], c["name"]
        else:
            with pytest.raises(P.PointfenceError, match=KEY_ERRORS[c["result"]]) as e:
                P.load_key(p)
            assert str(p) in str(e.value), c["name"]


def test_key_file_that_is_not_a_regular_file(tmp_path):
    with pytest.raises(P.PointfenceError, match="not a regular file"):
        P.load_key(tmp_path)
