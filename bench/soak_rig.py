"""The live rig of ``pointfence bench soak``: the service as ``pointfence serve`` runs it (UDP
hub with two device slots, hosted Raven II arms in their own process, pre-rendered synthetic
camera, haptic loop thread, authenticated control API), the simulated devices and the
attackers in processes of their own (``soak_devices``), and the handles the fault injections
use (``soak_faults``). Its recording streams to a ``.pfrec`` file (S8), which the judgement
reads afterwards.
"""
from __future__ import annotations

import json
import math
import multiprocessing
import os
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

from pointfence.service.sources.base import DepthSource

from .soak_devices import devices_main, flood_main

#: SCHED_FIFO priority of the soak's equipment where the OS allows it: the simulated arms' process
#: and the devices' thread. They stand for hardware with controllers of its own; on the two cores
#: they share with the service and with whatever else the machine runs, at normal priority they
#: waited for a core for tens of milliseconds (a robot's watchdog fault, a device's session lost)
#: and the soak judged the machine's load instead of the service. Above the service's frame
#: threads and receivers ([service] frames_rt_priority, 50), whose work a flood or a build can
#: stretch over a whole core (below them, a forged flood starved the arms into a watchdog fault,
#: judged against the attack), and below its loop (80)
EQUIPMENT_RT_PRIORITY = 60


class StallableSource(DepthSource):
    """A camera source whose ``read`` blocks while ``stalled`` is set (a stalled camera driver);
    otherwise it is the wrapped source (its frames, pace and scene)."""

    def __init__(self, inner: DepthSource):
        super().__init__(inner.camera, inner.rate_hz, inner.realtime)
        self._inner = inner
        self.scene = getattr(inner, "scene", None)
        self.stalled = threading.Event()

    def read(self, timeout=None):
        while self.stalled.is_set():
            time.sleep(0.005)
        return self._inner.read(timeout)

    def _frame(self, seq: int):   # not used: read() is the wrapped source's own
        raise NotImplementedError("StallableSource reads through its wrapped source")

    def _close(self) -> None:
        self._inner.close()


class SoakRig:
    """Everything running (``start``), handles for the injections, ``stop`` -> the recording."""

    def __init__(self, cfg, workdir: Path, backend=None, device=None, prerender: int = 30):
        from pointfence.service.canned import live_sources
        from pointfence.service.control_api import Controller, ControlServer
        from pointfence.service.ctl import ControlClient
        from pointfence.service.runner import LiveRun
        from pointfence.service.udp_server import UdpHub

        self.cfg = cfg
        self.workdir = Path(workdir)
        self.record_path = self.workdir / "soak.pfrec"
        self.psk = os.urandom(32)
        max_force = cfg.haptics.max_force if cfg.haptics is not None else 10.0
        self.hub = UdpHub(self.psk, 2, "127.0.0.1", 0, 50, cfg.service.rate_hz, max_force)
        self.sources = [StallableSource(s) for s in live_sources(cfg, prerender)]
        self.run = LiveRun(cfg, list(self.hub.masters), backend=backend, device=device, sources=self.sources,
                           record_path=self.record_path, robot_rt_priority=EQUIPMENT_RT_PRIORITY)
        self.svc = self.run.service
        self.hub.attach(self.svc)
        self.max_age = cfg.service.max_frame_age_s
        self.radius = cfg.pipeline.radius.r_base
        self.controller = Controller(self.svc, self.run.loop, extras={"clients": self.hub.status})
        self.control = ControlServer(self.controller, "127.0.0.1", 0, token_file=self.workdir / "control.token")
        self.ctl = None
        self._ControlClient = ControlClient
        ctx = multiprocessing.get_context("spawn")
        self._ctx = ctx
        self._conn, child = ctx.Pipe()
        self._devices = ctx.Process(target=devices_main, args=(child, "127.0.0.1", self.hub.address[1], self.psk, 2,
                                                                EQUIPMENT_RT_PRIORITY),
                                    name="soak-devices", daemon=True)
        self._lock = threading.Lock()

    # --- running -------------------------------------------------------------------------------------
    def start(self) -> None:
        self.control.start()
        self.ctl = self._ControlClient("127.0.0.1", self.control.address[1], timeout=30, token=self.control.token)
        self.run.start()
        self.run.wait_ticks(10)
        self._devices.start()
        if not self._conn.poll(60) or self._conn.recv()[0] != "started":
            raise RuntimeError("bench soak: the device process did not start")
        self.run.mark()

    def stop(self) -> dict:
        """Stop the devices and the service; returns the devices' link statistics."""
        out = {}
        try:
            with self._lock:
                self._conn.send(("stop",))
                if self._conn.poll(15):
                    out = {"devices": self._conn.recv()[1]}
        finally:
            self._devices.join(timeout=10)
            if self._devices.is_alive():
                self._devices.kill()
            self.control.close()
            self.run.stop()
            self.hub.close()
        return out

    # --- handles for the injections ------------------------------------------------------------------
    def tick(self) -> int:
        """The loop's current tick number."""
        return int(self.run.loop.k)

    def tick_at(self, t: float) -> int:
        """The last tick due at or before time ``t`` (the loop's clock, s): the first that can
        have seen what happened at ``t``, if it started late."""
        loop = self.run.loop
        return int(math.floor((t - loop.t0) / loop.period + 1e-9))

    def now(self) -> float:
        return self.run.clock.now()

    @staticmethod
    def sleep(seconds: float) -> None:
        time.sleep(seconds)

    def in_tick(self, fn) -> int:
        """Run ``fn(service)`` between two ticks; returns the number of the tick it ran before."""
        done, out = threading.Event(), {}

        def call(svc):
            out["k"] = int(self.run.loop.k)
            fn(svc)
            done.set()

        self.svc.call_between_ticks(call)
        if not done.wait(5.0):
            raise RuntimeError("bench soak: the haptic loop ran no tick within 5 s")
        return out["k"]

    def devices(self, *cmd):
        with self._lock:
            self._conn.send(tuple(cmd))
            return self._conn.recv()

    def stall_cameras(self, on: bool) -> None:
        for s in self.sources:
            (s.stalled.set if on else s.stalled.clear)()

    def flood(self, kind: str, seconds: float, rate_hz: float = 10000.0) -> int:
        """A flood from a process of its own: ``"forged"`` STATE-shaped forgeries or ``"replay"``
        of device 0's captured datagrams and handshake; returns the number sent."""
        sent, hellos = self.devices("capture", 0)
        pool = (sent + hellos * 50) if kind == "replay" else sent[-1:]
        conn, child = self._ctx.Pipe()
        p = self._ctx.Process(target=flood_main, args=(child, "127.0.0.1", self.hub.address[1], kind, seconds, rate_hz,
                                                       pool), daemon=True)
        p.start()
        n = conn.recv() if conn.poll(seconds + 60) else 0
        p.join(timeout=5)
        return int(n)

    def raw_control(self, method: str, path: str, body, auth) -> int:
        """HTTP status of a control request; ``auth``: True (the run's token), False (none) or a
        header value."""
        req = urllib.request.Request(self.control.url + path, method=method, data=json.dumps(body).encode())
        req.add_header("Content-Type", "application/json")
        if auth is True:
            req.add_header("Authorization", f"Bearer {self.control.token}")
        elif auth:
            req.add_header("Authorization", auth)
        try:
            with urllib.request.urlopen(req, timeout=30) as r:
                return r.status
        except urllib.error.HTTPError as e:
            return e.code

    def scheduling(self) -> dict:
        """How the OS schedules the threads that feed or watch the tick (each's own report)."""
        loop = self.run.loop
        return {"loop": loop.scheduling, "frames": self.run.frames.scheduling,
                "udp_receiver": self.hub.scheduling,
                "watchdog": loop.watchdog.scheduling if loop.watchdog is not None else None}

    def robot_notes(self) -> str:
        """Why each hosted arm cannot be enabled now, if it cannot (for a failure's message)."""
        host = self.run.robot_host
        if host is None:
            return "robots in the loop"
        return "robot host: " + "; ".join(f"arm {b}: {host.ready(b) or 'ready'}" for b in range(host.n))

    def pedals(self, down: bool, timeout: float = 10.0) -> float:
        """Every device's pedal ``down`` (True) or up, and wait until the service's tick read it
        (the command is repeated every second); returns the seconds it took (inf: never). Reads
        the tick's pedals (``Service.pedal``), not ``status()``: a status every 20 ms would take
        the interpreter lock from the loop for the soak's own bookkeeping."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            self.devices("pedal", down)
            end = time.monotonic() + 1.0
            while time.monotonic() < end:
                if bool((self.svc.pedal == down).all()):
                    return time.monotonic() - t0
                time.sleep(0.02)
        return float("inf")

    def steady(self, timeout: float) -> bool:
        """Wait until every arm is coupled and nothing holds (True), or ``timeout`` s. Reads the
        last tick's hold mask, coupling and latched faults (``Service.hold_mask``,
        ``coupled``, ``latched``: what ``status()`` names), not the whole status."""
        svc, end = self.svc, time.monotonic() + timeout
        while time.monotonic() < end:
            if not svc.hold_mask and bool(svc.coupled.all()) and not svc.latched:
                return True
            time.sleep(0.05)
        return False
