"""`pointfence ctl`: talk to a running `pointfence serve` through its local control API.

    pointfence ctl status | metrics | config
    pointfence ctl set-architecture III
    pointfence ctl engage haptics|teleop        pointfence ctl disengage haptics|teleop
    pointfence ctl radius 0.015 [--radius-max 0.03]
    pointfence ctl select box --min -0.05 -0.05 0 --max 0.05 0.05 0.2
    pointfence ctl select color --lo 150 0 0 --hi 255 90 90
    pointfence ctl select all | mask
    pointfence ctl clear-faults

The service listens on 127.0.0.1:47801 by default (``pointfence serve --control-port``); use
``--port`` / ``--host`` or ``$POINTFENCE_CONTROL``, e.g. ``127.0.0.1:47801``. Every request
carries the run's token (``ctl_auth.py``), read from ``--token-file``, ``$POINTFENCE_CONTROL_TOKEN``
or where `serve` writes it for that port (``$XDG_RUNTIME_DIR/pointfence/control-<port>.token``);
only the user who runs the service can read it. The reply is printed as JSON; a refused
command prints the service's reason and exits with status 1.
"""
from __future__ import annotations

import http.client
import json
import os
import sys
from typing import Optional

from pointfence.kernels.errors import InputError, PointfenceError

from . import ctl_auth
from .control_http import DEFAULT_CONTROL_PORT


class ControlRefused(PointfenceError):
    """The service answered with an error status."""

    def __init__(self, status: int, message: str):
        super().__init__(f"{message} (HTTP {status})")
        self.status = status


class ControlClient:
    """A minimal client of the control API (``control_api``): ``get(path)``, ``post(path, body)``.

    ``token``: the run's control token (``ctl_auth.read_token``); None: read it from
    ``token_file``, else from where `serve` writes it for ``port`` (at the first request)."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_CONTROL_PORT, timeout: float = 10.0,
                 token: Optional[str] = None, token_file=None):
        self.host, self.port, self.timeout = host, int(port), float(timeout)
        self.token, self.token_file = token, token_file

    def _authorization(self) -> str:
        if self.token is None:
            path = self.token_file if self.token_file is not None else ctl_auth.default_token_path(self.port)
            self.token = ctl_auth.read_token(path, self.port)
        return f"Bearer {self.token}"

    def request(self, method: str, path: str, body=None) -> tuple:
        """(HTTP status, decoded JSON reply)."""
        conn = http.client.HTTPConnection(self.host, self.port, timeout=self.timeout)
        try:
            headers = {"Accept": "application/json", "Authorization": self._authorization()}
            data = None
            if method == "POST":
                data = json.dumps(body if body is not None else {}).encode()
                headers["Content-Type"] = "application/json"
            try:
                conn.request(method, path, body=data, headers=headers)
                resp = conn.getresponse()
                raw = resp.read()
            except (ConnectionRefusedError, OSError) as e:
                raise InputError(f"no control API at {self.host}:{self.port} ({e}); is `pointfence serve` running, "
                                 "and on which --control-port?") from None
            try:
                return resp.status, json.loads(raw.decode() or "{}")
            except (UnicodeDecodeError, json.JSONDecodeError):
                raise InputError(f"{self.host}:{self.port} answered HTTP {resp.status} with a non-JSON body; "
                                 "is that the pointfence control port?") from None
        finally:
            conn.close()

    def _ok(self, status: int, reply: dict) -> dict:
        if status >= 400 or not reply.get("ok", False):
            msg = reply.get("error", "refused")
            if status in (401, 403):
                msg += (f"; the token used ({self.token_file or 'the default token file for port ' + str(self.port)}) "
                        "is not this service's: pass the file `pointfence serve` names on stderr with --token-file")
            raise ControlRefused(status, msg)
        return reply

    def get(self, path: str) -> dict:
        return self._ok(*self.request("GET", path))

    def post(self, path: str, body=None) -> dict:
        return self._ok(*self.request("POST", path, body))

    # conveniences
    def status(self) -> dict:
        return self.get("/status")

    def metrics(self) -> dict:
        return self.get("/metrics")

    def set_architecture(self, a: str) -> dict:
        return self.post("/architecture", {"architecture": a})

    def engage(self, what: str, on: bool = True) -> dict:
        if what not in ("haptics", "teleop"):
            raise InputError(f"{what!r}; expected haptics or teleop")
        return self.post(f"/{what}", {"engaged": bool(on)})

    def radius(self, r: float, radius_max=None) -> dict:
        body = {"radius": r}
        if radius_max is not None:
            body["radius_max"] = radius_max
        return self.post("/radius", body)

    def select(self, kind: str, **kw) -> dict:
        return self.post("/selection", {"kind": kind, **kw})


def address(args) -> tuple:
    """(host, port) of the control API from ``--host``/``--port``, else ``$POINTFENCE_CONTROL``."""
    host, port = args.host, args.port
    env = os.environ.get("POINTFENCE_CONTROL")
    if env and host is None and port is None:
        h, _, p = env.rpartition(":")
        try:
            return (h or "127.0.0.1"), int(p)
        except ValueError:
            raise InputError(f"$POINTFENCE_CONTROL = {env!r}; expected [HOST:]PORT") from None
    return host or "127.0.0.1", port if port is not None else DEFAULT_CONTROL_PORT


def add_arguments(p):
    p.add_argument("--host", default=None, help="control API host (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help=f"control API port (default {DEFAULT_CONTROL_PORT}, "
                                                          "or $POINTFENCE_CONTROL=[HOST:]PORT)")
    p.add_argument("--timeout", type=float, default=10.0, help="s to wait for the reply (default 10)")
    p.add_argument("--token-file", default=os.environ.get(ctl_auth.TOKEN_ENV),
                   help=f"the service's control token (default ${ctl_auth.TOKEN_ENV}, else the file `pointfence "
                        "serve` writes for the port: $XDG_RUNTIME_DIR/pointfence/control-PORT.token)")
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    sub.add_parser("status", help="architecture, engagement, holds, robots, frames, clients, positions, fixture")
    sub.add_parser("metrics", help="loop timing, misses, degraded reasons, camera staleness, client counts")
    sub.add_parser("config", help="the fixture parameters in use")
    a = sub.add_parser("set-architecture", help="switch the fixture architecture (no jump in force or command)")
    a.add_argument("architecture", help="I, II or III (eqs. 3.1-3.3)")
    for name, what in (("engage", "engage"), ("disengage", "disengage")):
        e = sub.add_parser(name, help=f"{what} haptic rendering or teleoperation")
        e.add_argument("what", choices=("haptics", "teleop"))
    r = sub.add_parser("radius", help="fixture radius r_base, m (new snapshots use it)")
    r.add_argument("radius", type=float)
    r.add_argument("--radius-max", type=float, default=None, help="r_max (adaptive radii); default r_base + the current margin")
    s = sub.add_parser("select", help="which points are protected: all, box, color, mask")
    s.add_argument("kind", choices=("all", "box", "color", "mask"))
    s.add_argument("--min", type=float, nargs=3, metavar=("X", "Y", "Z"), help="box corner (world frame, m)")
    s.add_argument("--max", type=float, nargs=3, metavar=("X", "Y", "Z"), help="box corner (world frame, m)")
    s.add_argument("--lo", type=int, nargs=3, metavar=("R", "G", "B"), help="colour range low (0..255)")
    s.add_argument("--hi", type=int, nargs=3, metavar=("R", "G", "B"), help="colour range high (0..255)")
    sub.add_parser("clear-faults", help="leave the loop's safe mode after an error; re-enable faulted robots "
                                        "(refused while an arm is coupled: release the pedal first)")


def run(args) -> int:
    host, port = address(args)
    c = ControlClient(host, port, args.timeout, token_file=args.token_file)
    act = args.action
    if act in ("status", "metrics", "config"):
        reply = c.get(f"/{act}")
    elif act == "set-architecture":
        reply = c.set_architecture(args.architecture)
    elif act in ("engage", "disengage"):
        reply = c.engage(args.what, act == "engage")
    elif act == "radius":
        reply = c.radius(args.radius, args.radius_max)
    elif act == "select":
        kw = {}
        if args.kind == "box":
            if args.min is None or args.max is None:
                raise InputError("select box needs --min X Y Z and --max X Y Z (world frame, m)")
            kw = {"min": args.min, "max": args.max}
        elif args.kind == "color":
            if args.lo is None or args.hi is None:
                raise InputError("select color needs --lo R G B and --hi R G B (0..255)")
            kw = {"lo": args.lo, "hi": args.hi}
        reply = c.select(args.kind, **kw)
    elif act == "clear-faults":
        reply = c.post("/clear-faults", {})
    else:  # argparse refuses anything else
        raise InputError(f"unknown action {act!r}")
    print(json.dumps(reply, indent=2))
    return 0


def main(argv=None) -> int:
    """``python -m pointfence.service.ctl`` (the same as ``pointfence ctl``)."""
    import sys

    from pointfence.cli import main as pointfence_main

    return pointfence_main(["ctl", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
