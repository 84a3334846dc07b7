"""The control API under attack (SAFETY.md S4, S6, S7; issue 18 items 4 and 9): requests without
the run's token or with a wrong one are refused, counted and change nothing; values that lower
protection stay bounded; clearing faults needs every arm decoupled; the token file is private;
malformed, deeply nested, slow and too many requests cannot hold a handler; a taken port fails
`serve` instead of moving it."""
import argparse
import json
import os
import socket
import stat
import time

import pytest

from pointfence.kernels.errors import InputError
from pointfence.service import ctl, ctl_auth
from pointfence.service.control_api import ControlServer

from control_rig import Running
from service_cases import needs_opencl

pytestmark = needs_opencl


@pytest.fixture
def rig(tmp_path):
    r = Running(tmp_path / "rig")
    yield r
    r.close()


def state(rig):
    """Everything a control request could change."""
    svc = rig.svc
    return (svc.architecture, svc.haptics_on, svc.teleop_on, svc.pipeline, svc.pipeline.params, svc.last_error,
            rig.loop.error, rig.controller.reconfigurations)


CHANGES = [
    ("POST", "/architecture", {"architecture": "I"}),
    ("POST", "/haptics", {"engaged": False}),
    ("POST", "/teleop", {"engaged": False}),
    ("POST", "/radius", {"radius": 0.001}),
    ("POST", "/selection", {"kind": "box", "min": [-0.01, -0.01, 0.0], "max": [0.01, 0.01, 0.01]}),
    ("POST", "/clear-faults", {}),
    ("GET", "/status", None),
    ("GET", "/metrics", None),
    ("GET", "/config", None),
    ("GET", "/nothing", None),
]


def test_requests_without_or_with_a_wrong_token_are_refused_and_change_nothing(rig):
    rig.wait_ticks(20)
    rig.svc.last_error = "injected fault"             # what clear-faults would forget
    before = state(rig)
    tok = rig.server.token
    wrong = [f"Bearer {tok[:-1]}{'0' if tok[-1] != '0' else '1'}",    # one digit off
             f"Bearer {ctl_auth.new_token()}", f"Bearer {tok.upper()}", tok, f"Basic {tok}", f"Bearer {tok} x",
             "Bearer ", f"Bearer {tok[:32]}", f"Bearer {tok}{tok}", "Bearer \u00e9"]
    n401 = n403 = 0
    for method, path, body in CHANGES:
        status, reply = rig.raw(method, path, body, auth=False)
        assert status == 401 and reply["ok"] is False and "Authorization: Bearer" in reply["error"], (path, reply)
        n401 += 1
        for header in wrong:
            status, reply = rig.raw(method, path, body, auth=header)
            assert status in (401, 403) and reply["ok"] is False, (path, header, status, reply)
            n401 += status == 401
            n403 += status == 403
    rig.wait_ticks(50)
    assert state(rig) == before
    assert rig.controller.requests == 0                # none reached a route
    c = rig.client.metrics()["control"]                # the operator sees them counted
    assert c["rejected"]["unauthenticated"] == n401 and c["rejected"]["wrong_token"] == n403
    assert c["rejected_total"] == n401 + n403 == len(CHANGES) * (1 + len(wrong))
    assert rig.client.status()["control"]["rejected"]["wrong_token"] == n403
    # the authenticated operator may still change everything while running
    assert rig.client.set_architecture("I")["architecture"] == "I"
    assert rig.raw("POST", "/architecture", {"architecture": "II"}, auth=f"bearer {tok}")[0] == 200   # RFC 7235
    assert rig.client.engage("haptics", False)["haptics"] is False


def test_token_file_is_private_and_goes_with_the_run(rig):
    p = rig.server.token_file
    assert p == ctl_auth.default_token_path(rig.server.address[1])
    assert stat.S_IMODE(os.stat(p).st_mode) == 0o600 and os.stat(p).st_uid == os.geteuid()
    assert stat.S_IMODE(os.stat(p.parent).st_mode) == 0o700
    assert ctl_auth.read_token(p) == rig.server.token and len(rig.server.token) == 64
    srv2 = ControlServer(rig.controller, "127.0.0.1", 0).start()
    try:
        assert srv2.token != rig.server.token and srv2.token_file != p
    finally:
        srv2.close()
    assert not srv2.token_file.exists() and p.exists()


def test_run_dir_and_token_file_that_others_could_reach_are_refused(tmp_path, monkeypatch):
    base = tmp_path / "xdg"
    base.mkdir()
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(base))
    d = ctl_auth.run_dir(create=True)
    assert d == base / "pointfence" and stat.S_IMODE(os.stat(d).st_mode) == 0o700
    d.chmod(0o755)
    with pytest.raises(InputError, match="mode 0755; expected 0700"):
        ctl_auth.default_token_path(47801)
    d.rmdir()
    d.symlink_to(tmp_path)
    with pytest.raises(InputError, match="not a plain directory"):
        ctl_auth.run_dir()
    d.unlink()
    if os.geteuid() == 0:                          # as root the test can hand the directory to another user
        d.mkdir(0o700)
        os.chown(d, 12345, -1)
        with pytest.raises(InputError, match="belongs to uid 12345"):
            ctl_auth.run_dir()
        d.rmdir()
    f = ctl_auth.write_token(tmp_path / "t.token", ctl_auth.new_token())
    f.chmod(0o644)
    with pytest.raises(InputError, match="mode 0644: other users may have read it"):
        ctl_auth.read_token(f)
    f.chmod(0o600)
    f.write_text("0" * 10 + "\n")
    with pytest.raises(InputError, match="not a pointfence control token"):
        ctl_auth.read_token(f)
    with pytest.raises(InputError, match="no control token for the control API on port 5 at"):
        ctl_auth.read_token(tmp_path / "missing", 5)


def test_ctl_says_what_to_do_without_the_right_token(rig, tmp_path, capsys):
    port = str(rig.server.address[1])
    rig.wait_ticks(5)
    before = state(rig)
    bad = ctl_auth.write_token(tmp_path / "other.token", ctl_auth.new_token())
    assert ctl.main(["--port", port, "--token-file", str(bad), "disengage", "haptics"]) == 1
    err = capsys.readouterr().err
    assert "wrong control token" in err and "HTTP 403" in err and "--token-file" in err
    assert ctl.main(["--port", port, "--token-file", str(tmp_path / "none"), "disengage", "haptics"]) == 1
    err = capsys.readouterr().err
    assert "no control token" in err and "is `pointfence serve` running" in err
    assert state(rig) == before
    assert ctl.main(["--port", port, "disengage", "haptics"]) == 0 and rig.svc.haptics_on is False  # default file


def test_values_that_lower_protection_stay_bounded(rig):
    """S6/S7: radius 0, negative, NaN, inf, huge, strings; empty, flat, far or NaN boxes; empty
    colour ranges; nested junk; a selection that protects nothing: refused, naming the value,
    nothing changed."""
    rig.wait_ticks(20)
    before = state(rig)
    cases = [
        ({"radius": 0}, "radius = 0 m; expected 0 < radius <= 0.1"),
        ({"radius": 0.0}, "expected 0 < radius"),
        ({"radius": -1}, "radius = -1 m"),
        ({"radius": 1e308}, "radius = 1e+308 m"),
        ({"radius": 10 ** 400}, "expected a finite number"),
        ({"radius": "0.01"}, "radius = '0.01'; expected a number"),
        ({"radius": [0.01]}, "radius = [0.01]"),
        ({"radius": {"a": [[[[1]]]]}}, "expected a number"),
        ({"radius": None}, "radius = None"),
        ({"radius": True}, "radius = True"),
        ({}, "radius: missing"),
        ({"radius": 0.01, "radius_max": 1e308}, "radius_max = 1e+308"),
        ({"radius": 0.01, "radius_max": 0}, "radius_max = 0 m"),
        ({"radius": 0.01, "r": 1}, "unknown key"),
    ]
    for body, text in cases:
        status, reply = rig.raw("POST", "/radius", body)
        assert status == 400 and text in reply["error"], (body, status, reply)
    for raw, text in ((b'{"radius": NaN}', "NaN is not a JSON number"),
                      (b'{"radius": Infinity}', "Infinity is not a JSON number"),
                      (b'{"radius": -Infinity}', "-Infinity is not a JSON number"),
                      (b'{"radius": 1e400}', "radius = inf; expected a finite number")):
        status, reply = rig.raw("POST", "/radius", raw)
        assert status == 400 and text in reply["error"], (raw, status, reply)
    box = {"kind": "box", "min": [-0.05, -0.05, 0.0], "max": [0.05, 0.05, 0.2]}
    sel_cases = [
        ({**box, "min": [0.06, -0.05, 0.0]}, "expected min < max"),                    # min > max
        ({**box, "min": [-0.05, -0.05, 0.2]}, "expected min < max"),                   # flat
        ({**box, "min": [1.0, 1.0, 1.0], "max": [2.0, 2.0, 2.0]}, "outside the workspace"),
        ({**box, "max": [0.05, 0.05, 1e308]}, "selection box max[2] = 1e+308"),
        ({**box, "max": [0.05, 0.05, "x"]}, "selection box max[2] = 'x'"),
        ({**box, "max": [0.05, 0.05, [[0.1]]]}, "selection box max[2] = [[0.1]]"),
        ({**box, "max": [0.05, 0.05]}, "expected [x, y, z]"),
        ({"kind": "color", "lo": [200, 0, 0], "hi": [100, 90, 90]}, "expected lo <= hi"),
        ({"kind": "color", "lo": [0, 0, 0.5], "hi": [255, 90, 90]}, "0..255"),
        ({"kind": ["box"]}, "selection kind = ['box']"),
    ]
    for body, text in sel_cases:
        status, reply = rig.raw("POST", "/selection", body)
        assert status == 400 and text in reply["error"], (body, status, reply)
    status, reply = rig.raw("POST", "/selection", b'{"kind": "box", "min": [NaN, 0, 0], "max": [1, 1, 1]}')
    assert status == 400 and "NaN is not a JSON number" in reply["error"]
    # inside the workspace, but no point of the scene there: the fixture would vanish
    status, reply = rig.raw("POST", "/selection", {"kind": "box", "min": [0.2, 0.2, 0.2], "max": [0.24, 0.24, 0.24]})
    assert status == 409 and "no point of the current frames is protected" in reply["error"], reply
    status, reply = rig.raw("POST", "/selection", {"kind": "color", "lo": [0, 250, 0], "hi": [5, 255, 5]})
    assert status == 409 and "fixture would vanish" in reply["error"], reply
    rig.wait_ticks(20)
    assert state(rig) == before and rig.svc.pipeline.params.radius.r_base == pytest.approx(0.02)
    assert rig.client.metrics()["control"]["refused"] == len(cases) + len(sel_cases) + 3
    assert rig.client.metrics()["control"]["rejected"]["bad_body"] == 4     # the NaN / Infinity bodies


def test_clear_faults_needs_every_arm_decoupled(rig):
    rig.wait_ticks(50)
    assert rig.client.status()["coupled"] == [True]          # the scripted master's pedal is down
    rig.svc.last_error = "injected fault"
    status, reply = rig.raw("POST", "/clear-faults", {})
    assert status == 409 and "arm(s) 0 coupled" in reply["error"] and "release the pedal" in reply["error"]
    rig.wait_ticks(10)
    assert rig.svc.last_error == "injected fault"             # nothing was cleared
    status, reply = rig.raw("POST", "/clear-faults", {"force": True})
    assert status == 400 and "unknown key" in reply["error"]
    rig.client.engage("teleop", False)                         # decoupled: now it may
    rig.wait_ticks(5)
    assert rig.client.status()["coupled"] == [False]
    assert rig.client.post("/clear-faults", {})["ok"] and rig.svc.last_error is None


# --- the HTTP layer: bodies, slow clients, too many clients ------------------------------------------
@pytest.fixture
def tight(rig, tmp_path):
    """A second server on the rig's controller: read_timeout 1 s, 2 handlers at once."""
    srv = ControlServer(rig.controller, "127.0.0.1", 0, token_file=tmp_path / "tight.token", read_timeout=1.0,
                        max_handlers=2).start()
    yield srv
    srv.close()


def _request(srv, body: bytes, auth=True, length=None) -> bytes:
    head = (f"POST /radius HTTP/1.0\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
            f"Content-Length: {len(body) if length is None else length}\r\n"
            + (f"Authorization: Bearer {srv.token}\r\n" if auth else "") + "\r\n").encode()
    return head + body


def _talk(srv, data: bytes, timeout=30.0) -> tuple:
    """(HTTP status or None if the server closed without a reply, reply text)."""
    with socket.create_connection(srv.address, timeout=timeout) as s:
        try:
            s.sendall(data)
            s.shutdown(socket.SHUT_WR)
        except OSError:             # the server may answer (503 busy) and close before the request is all sent
            pass
        out = b""
        while True:
            try:
                chunk = s.recv(65536)
            except ConnectionResetError:
                break
            if not chunk:
                break
            out += chunk
    if not out:
        return None, ""
    return int(out.split(b" ", 2)[1]), out.decode("utf-8", "replace")


def _talk_when_free(srv, data: bytes) -> tuple:
    """``_talk``, again while the two-handler server answers 503 busy (a handler of the request
    before may still be closing its socket on a loaded machine; busy is tested on its own)."""
    end = time.monotonic() + 10.0
    while True:
        status, reply = _talk(srv, data)
        if status != 503 or "busy" not in reply or time.monotonic() > end:
            return status, reply
        time.sleep(0.05)


def test_deeply_nested_or_malformed_bodies_are_400(rig, tight):
    rig.wait_ticks(5)
    before = state(rig)
    for body, text in ((b'{"radius": ' + b"[" * 30000 + b"]" * 30000 + b"}", "deeper than 8"),
                       (b"[" * 50000, "deeper than 8"),
                       (b'{"a": [[[[[[[[[1]]]]]]]]]}', "deeper than 8"),
                       (b'{"radius": "\\"[[[[[[[[[[[[[[[[[["}', "radius = '\\\"[[[[["),    # brackets in a string
                       (b'{"radius": 0.01', "not valid JSON"),
                       (b'\xff\xfe', "not UTF-8"),
                       (b'{"radius": ' + b"9" * 5000 + b"}", "digits")):
        status, reply = _talk_when_free(tight, _request(tight, body))
        assert status == 400 and text in reply, (body[:40], status, reply[-300:])
    status, reply = _talk_when_free(tight, _request(tight, b'{"radius": 0.01}', length=200))   # shorter than announced
    assert status == 400 and "body ended after 16 of its 200 bytes" in reply
    status, reply = _talk_when_free(tight, _request(tight, b"{}", length=10 ** 9))
    assert status == 413
    assert state(rig) == before


def _cut_within(sock, limit: float) -> float:
    """Seconds until the server closes ``sock`` (fails the test beyond ``limit``)."""
    t0 = time.monotonic()
    sock.settimeout(limit)
    try:
        while sock.recv(4096):
            pass
    except (ConnectionResetError, BrokenPipeError):
        pass
    except socket.timeout:
        pytest.fail(f"the server kept a slow client for more than {limit} s")
    return time.monotonic() - t0


def test_slow_clients_are_cut(rig, tight):
    """read_timeout 1 s: headers sent byte by byte, a body shorter than its Content-Length, a
    client that sends nothing: each is dropped within 5 s."""
    rig.wait_ticks(5)
    data = _request(tight, b'{"radius": 0.001}')
    s = socket.create_connection(tight.address, timeout=30)
    t0 = time.monotonic()
    try:
        for i in range(len(data)):                 # 0.1 s a byte: each wait is short, the request long
            if time.monotonic() - t0 > 6.0:
                pytest.fail("the server kept reading a slow-loris client for more than 6 s")
            try:
                s.sendall(data[i:i + 1])
            except (BrokenPipeError, ConnectionResetError):
                break
            s.settimeout(0.1)
            try:
                if s.recv(4096) == b"":
                    break                          # closed by the server
            except socket.timeout:
                pass
            except ConnectionResetError:
                break
        assert time.monotonic() - t0 < 5.0
    finally:
        s.close()
    s = socket.create_connection(tight.address, timeout=30)
    s.sendall(_request(tight, b'{"radius"', length=17))           # 8 of 17 body bytes, then silence
    assert _cut_within(s, 5.0) < 5.0
    s.close()
    s = socket.create_connection(tight.address, timeout=30)        # connects, sends nothing
    assert _cut_within(s, 5.0) < 5.0
    s.close()
    assert rig.svc.pipeline.params.radius.r_base == pytest.approx(0.02)
    assert rig.controller.rejected["timeout"] == 3


def test_handler_threads_are_bounded(rig, tight):
    rig.wait_ticks(5)
    idle = [socket.create_connection(tight.address, timeout=30) for _ in range(2)]    # hold both handlers
    time.sleep(0.2)
    status, reply = _talk(tight, _request(tight, b'{"radius": 0.001}'), timeout=5.0)
    assert status == 503 and "busy" in reply
    assert rig.controller.rejected["busy"] >= 1
    for s in idle:                                  # cut at read_timeout; then the operator gets through
        assert _cut_within(s, 5.0) < 5.0
        s.close()
    end = time.monotonic() + 10
    while True:
        status, reply = _talk(tight, b"GET /config HTTP/1.0\r\nHost: 127.0.0.1\r\n"
                                     + f"Authorization: Bearer {tight.token}\r\n\r\n".encode())
        if status == 200 or time.monotonic() > end:
            break
        time.sleep(0.05)
    assert status == 200 and json.loads(reply.split("\r\n\r\n", 1)[1])["ok"]


# --- ports --------------------------------------------------------------------------------------------
def test_a_taken_control_port_is_an_error_not_a_move(rig):
    port = rig.server.address[1]
    with pytest.raises(InputError, match=f"cannot listen on 127.0.0.1:{port}.*--control-port"):
        ControlServer(rig.controller, "127.0.0.1", port)


def _serve_args(tmp_path, *extra):
    from pointfence.bench.e2e import LIGHT_SCENE
    from pointfence.service import serve

    key = tmp_path / "pf.key"
    if not key.exists():
        serve.new_key(key)
    scene = tmp_path / "scene.toml"
    scene.write_text(LIGHT_SCENE)
    p = argparse.ArgumentParser()
    serve.add_arguments(p)
    return serve, p.parse_args(["--key-file", str(key), "--config", str(scene), "--status-every", "0",
                                "--duration", "0.5", *extra])


def test_serve_fails_when_its_ports_are_taken(tmp_path, monkeypatch):
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    tcp.bind(("127.0.0.1", 0))
    tcp.listen(1)
    try:
        serve, args = _serve_args(tmp_path, "--port", str(udp.getsockname()[1]))
        with pytest.raises(InputError, match=f"udp://127.0.0.1:{udp.getsockname()[1]}.*--port"):
            serve.run(args)
        # the default control port taken (here: the module's default pointed at a port in use)
        monkeypatch.setattr(serve, "DEFAULT_CONTROL_PORT", tcp.getsockname()[1])
        serve, args = _serve_args(tmp_path, "--port", "0", "--ready-file", str(tmp_path / "ready.json"))
        with pytest.raises(InputError, match=f"127.0.0.1:{tcp.getsockname()[1]}.*--control-port"):
            serve.run(args)
        assert not (tmp_path / "ready.json").exists()
    finally:
        udp.close()
        tcp.close()
