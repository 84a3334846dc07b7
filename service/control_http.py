"""The control API's HTTP server: loopback only, a bearer token on every request, and bounded
work per client (standard library only; the routes and their logic are ``control_api.Controller``).

Every request, reads included, must carry ``Authorization: Bearer <token>`` (``ctl_auth``):
reads run in the haptic tick (``Service.call_between_ticks``), and no other local user may load
the 1 kHz loop or learn the robot's positions. A request without it is refused with 401, one
with a wrong token with 403, before its body is read; both change nothing and are counted
(``control.rejected`` in /status, /metrics and serve's final status).

Limits, so that no client can hold a handler: one request per connection (HTTP/1.0); the whole
request (line, headers, body) must arrive within ``read_timeout`` s of the connection (a client
that trickles bytes or sends less body than its Content-Length is cut then); a body of at most
``MAX_BODY`` bytes nested at most ``MAX_JSON_DEPTH`` deep (checked before parsing; NaN and
Infinity are not JSON here); at most ``max_handlers`` connections are handled at once (more:
503 at once, no thread). Replies are written with a ``write_timeout``.
"""
from __future__ import annotations

import io
import ipaddress
import json
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Optional

from pointfence.kernels.errors import InputError

from . import ctl_auth

DEFAULT_CONTROL_PORT = 47801
MAX_BODY = 64 * 1024
#: deepest nesting of arrays/objects a body may have (the routes need 2)
MAX_JSON_DEPTH = 8


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def json_depth_exceeds(raw: bytes, limit: int) -> bool:
    """True if ``raw`` nests arrays/objects deeper than ``limit`` (a linear scan that skips
    strings; no recursion, whatever the input)."""
    depth = 0
    in_str = esc = False
    for c in raw:
        if in_str:
            if esc:
                esc = False
            elif c == 92:           # backslash
                esc = True
            elif c == 34:           # quote
                in_str = False
        elif c == 34:
            in_str = True
        elif c == 91 or c == 123:   # [ {
            depth += 1
            if depth > limit:
                return True
        elif c == 93 or c == 125:   # ] }
            depth -= 1
    return False


def _no_constant(name: str):
    raise ValueError(f"{name} is not a JSON number; send finite numbers only")


def parse_body(raw: bytes):
    """The JSON value of a request body; ``ValueError`` with a message for the caller."""
    if json_depth_exceeds(raw, MAX_JSON_DEPTH):
        raise ValueError(f"body nests arrays/objects deeper than {MAX_JSON_DEPTH} levels")
    try:
        return json.loads(raw.decode("utf-8"), parse_constant=_no_constant)
    except UnicodeDecodeError as e:
        raise ValueError(f"body is not UTF-8: {e}") from None
    except RecursionError:
        raise ValueError("body nests too deeply") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"body is not valid JSON: {e}") from None


class _DeadlineReader(io.RawIOBase):
    """The connection's input, cut at ``deadline`` (time.monotonic()): every receive waits at
    most until then, so trickled bytes cannot stretch a request past it."""

    def __init__(self, sock, deadline: float, on_timeout):
        self.sock, self.deadline, self.on_timeout = sock, deadline, on_timeout

    def readable(self) -> bool:
        return True

    def readinto(self, b) -> int:
        left = self.deadline - time.monotonic()
        try:
            if left <= 0:
                raise TimeoutError("request not received in time")
            self.sock.settimeout(left)
            return self.sock.recv_into(b)
        except TimeoutError:
            self.on_timeout()
            raise


class _Handler(BaseHTTPRequestHandler):
    server_version = "pointfence-control/1"
    protocol_version = "HTTP/1.0"
    controller = None               # these four are set on the subclass made per server
    auth: ctl_auth.BearerCheck = None
    read_timeout = 2.0
    write_timeout = 2.0

    def setup(self):
        super().setup()
        timed_out = []

        def on_timeout():
            if not timed_out:
                timed_out.append(True)
                self.controller.count_rejected("timeout")

        self.rfile.close()          # the plain reader setup() made (the socket stays open)
        self.rfile = io.BufferedReader(_DeadlineReader(self.connection, time.monotonic() + self.read_timeout,
                                                       on_timeout))

    def log_message(self, fmt, *args):   # no per-request logging to stderr
        pass

    def _reply(self, status: int, obj: dict, headers: Optional[dict] = None) -> None:
        data = (json.dumps(obj) + "\n").encode()
        self.connection.settimeout(self.write_timeout)
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-store")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(data)

    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").strip()
        if host.startswith("["):
            name = host[: host.find("]") + 1] if "]" in host else host
        else:
            name = host.rsplit(":", 1)[0] if host.count(":") == 1 else host
        return is_loopback(name)

    def _admitted(self) -> bool:
        """Host and token checks; False: refused and answered."""
        if not self._host_ok():
            self.controller.count_rejected("host")
            self._reply(403, {"ok": False, "error": "Host header is not a loopback name"})
            return False
        denied = self.auth.check(self.headers.get("Authorization"))
        if denied is not None:
            status, message = denied
            self.controller.count_rejected("unauthenticated" if status == 401 else "wrong_token")
            self._reply(status, {"ok": False, "error": message},
                        {"WWW-Authenticate": 'Bearer realm="pointfence"'} if status == 401 else None)
            return False
        return True

    def do_GET(self):
        if self._admitted():
            self._reply(*self.controller.handle("GET", self.path))

    def _refuse_body(self, status: int, message: str) -> None:
        self.controller.count_rejected("bad_body")
        self._reply(status, {"ok": False, "error": message})

    def do_POST(self):
        if not self._admitted():
            return
        ctype = (self.headers.get("Content-Type") or "").split(";", 1)[0].strip().lower()
        if ctype != "application/json":
            return self._refuse_body(415, f"Content-Type {ctype or 'missing'}; expected application/json")
        try:
            n = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            n = -1
        if not 0 <= n <= MAX_BODY:
            return self._refuse_body(413 if n > MAX_BODY else 400, f"body of {n} bytes; expected 0..{MAX_BODY}")
        raw = self.rfile.read(n) if n else b"{}"
        if len(raw) < n:
            return self._refuse_body(400, f"body ended after {len(raw)} of its {n} bytes (Content-Length)")
        try:
            body = parse_body(raw)
        except ValueError as e:
            return self._refuse_body(400, str(e))
        self._reply(*self.controller.handle("POST", self.path, body))

    def do_PUT(self):
        if self._admitted():
            self._reply(405, {"ok": False, "error": "use GET or POST"})

    do_DELETE = do_PATCH = do_PUT


class _BoundedServer(ThreadingHTTPServer):
    """At most ``max_handlers`` connections handled at once; a connection beyond that gets a
    503 from the accepting thread and is closed (no thread is started for it)."""

    daemon_threads = True
    max_handlers = 8
    controller = None

    def server_activate(self):
        self._slots = threading.BoundedSemaphore(self.max_handlers)
        super().server_activate()

    def process_request(self, request, client_address):
        if not self._slots.acquire(blocking=False):
            self.controller.count_rejected("busy")
            body = b'{"ok": false, "error": "control API busy: too many connections; try again"}\n'
            try:
                request.settimeout(0.1)
                request.sendall(b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                                b"Content-Length: %d\r\n\r\n%s" % (len(body), body))
            except OSError:
                pass
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request, client_address):
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


class ControlServer:
    """``Controller`` behind an HTTP server in its own daemon thread on ``host:port`` (loopback
    only; port 0: any free port, see ``address``). A port in use is an error, never a silent
    move to another port.

    The run's token is written, once the port is bound, to ``token_file`` (default
    ``ctl_auth.default_token_path(port)``) and removed by ``close()``.

    Args:
        read_timeout: s from a connection's start to the end of its request (cut beyond).
        max_handlers: connections handled at once.
    """

    def __init__(self, controller, host: str = "127.0.0.1", port: int = DEFAULT_CONTROL_PORT,
                 token_file=None, read_timeout: float = 2.0, max_handlers: int = 8):
        if not is_loopback(host):
            raise InputError(f"control API address {host!r}: the control API binds to loopback only "
                             "(127.0.0.1, ::1, localhost)")
        if not (0 < read_timeout <= 60) or not (1 <= int(max_handlers) <= 64):
            raise InputError(f"control API read_timeout {read_timeout} s / max_handlers {max_handlers}; "
                             "expected 0 < read_timeout <= 60 and 1 <= max_handlers <= 64")
        self.controller = controller
        self.token = ctl_auth.new_token()
        handler = type("Handler", (_Handler,), {"controller": controller, "auth": ctl_auth.BearerCheck(self.token),
                                                "read_timeout": float(read_timeout),
                                                "write_timeout": float(read_timeout)})
        attrs = {"max_handlers": int(max_handlers), "controller": controller}
        if ":" in host:
            attrs["address_family"] = socket.AF_INET6
        cls = type("Server", (_BoundedServer,), attrs)
        try:
            self.httpd = cls((host, int(port)), handler)
        except OSError as e:
            raise InputError(f"control API: cannot listen on {host}:{port}: {e}; stop what holds that port, or "
                             "choose another with --control-port N (0: any free port, shown on stderr and in "
                             "--ready-file)") from None
        try:
            path = token_file if token_file is not None else ctl_auth.default_token_path(self.address[1], True)
            self.token_file = ctl_auth.write_token(path, self.token)
        except BaseException:
            self.httpd.server_close()
            raise
        self._thread: Optional[threading.Thread] = None

    @property
    def address(self) -> tuple:
        return self.httpd.server_address[:2]

    @property
    def url(self) -> str:
        host, port = self.address
        return f"http://{'[' + host + ']' if ':' in host else host}:{port}"

    def start(self) -> "ControlServer":
        if self._thread is None:
            self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1},
                                            name="pointfence-control-api", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        if self._thread is not None:
            self.httpd.shutdown()
            self._thread.join(timeout=5.0)
            self._thread = None
        self.httpd.server_close()
        ctl_auth.remove_token(self.token_file, self.token)
