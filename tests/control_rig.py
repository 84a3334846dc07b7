"""A running Service with its control API for the control-API tests: the haptic loop runs in its
own thread on the simulated clock (FakeClock), frames arrive at their timestamps, requests go
over HTTP on loopback with the run's token."""
import json
import time
import urllib.error
import urllib.request

from pointfence.service.app import Service
from pointfence.service.clock import FakeClock
from pointfence.service.control_api import Controller, ControlServer
from pointfence.service.ctl import ControlClient
from pointfence.service.frames import SimFrames
from pointfence.service.loop import HapticLoop

from service_cases import POINT_MASS, balloon_config, push


class Running:
    """Service + SimFrames + a HapticLoop thread on a FakeClock + the control API on port 0
    (its token in the default place, ``ctl_auth.default_token_path(port)``, as `serve` does)."""

    def __init__(self, tmp_path, arch="III", extra="", record=60000, mode_line=None, start=True, master=None):
        tmp_path.mkdir(parents=True, exist_ok=True)
        cfg = balloon_config(tmp_path, arch=arch, robot=POINT_MASS, extra=extra)
        if mode_line is not None:
            from dataclasses import replace

            cfg = replace(cfg, mode=mode_line)
        self.cfg = cfg
        self.svc = Service(cfg, [master if master is not None else push(t_start=0.1, t_end=2.0, hold=100.0)], record=record)
        self.sources = cfg.open_sources()
        fe = SimFrames(self.svc.pipeline, self.sources, cfg.service.stale_s, cfg.service.max_frame_age_s)
        self.svc.attach_frames(fe)
        fe.poll(0.0)
        self.loop = HapticLoop(self.svc, FakeClock(), 1000, cfg.service.max_lateness_s, switch_interval_s=None)
        self.controller = Controller(self.svc, self.loop, extras={"clients": lambda: {"slots": 1, "sessions": []}},
                                     apply_timeout=5.0)
        self.server = ControlServer(self.controller, "127.0.0.1", 0).start()
        self.client = ControlClient("127.0.0.1", self.server.address[1], timeout=30, token=self.server.token)
        if start:
            self.loop.start()

    def raw(self, method, path, body=None, ctype="application/json", auth=True):
        """(status, JSON) of a request made by hand (for malformed requests); ``auth``: True:
        the run's token; False: no Authorization header; a str: that header."""
        req = urllib.request.Request(self.server.url + path, method=method,
                                     data=body if isinstance(body, bytes) else (None if body is None else json.dumps(body).encode()))
        if ctype:
            req.add_header("Content-Type", ctype)
        if auth is True:
            req.add_header("Authorization", f"Bearer {self.server.token}")
        elif auth:
            req.add_header("Authorization", auth)
        try:
            with urllib.request.urlopen(req, timeout=30) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as e:
            return e.code, json.loads(e.read())

    def wait_ticks(self, n):
        k = self.loop.ticks + n
        end = time.monotonic() + 60
        while self.loop.ticks < k and time.monotonic() < end:
            time.sleep(0.005)
        assert self.loop.ticks >= k

    def close(self):
        self.server.close()
        self.loop.stop()
        for s in self.sources:
            s.close()
