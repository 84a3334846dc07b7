"""The local HTTP JSON control API of `pointfence serve` (standard library only).

An ``http.server`` in its own thread, bound to loopback (127.0.0.1 by default, port
``DEFAULT_CONTROL_PORT``). It never touches the haptic tick's data directly: every read and
every change is a short function handed to ``Service.call_between_ticks``, which the tick thread
runs at the start of its next tick (so a change is applied whole, between two ticks, never
half-way through one); the request waits for it (``apply_timeout``). Reads return what that
tick thread copied out. The one exception is the loop's timing, computed here from the loop's
measurement rings (read-only arrays the tick appends to; a concurrent write changes one sample).

Routes (JSON in, JSON out; errors are ``{"ok": false, "error": "..."}`` with a 4xx/5xx status,
and a refused command changes nothing):

    GET  /status                     architecture, engagement, holds, robots, frames, clients,
                                     the last tick's positions/forces, the fixture parameters
    GET  /metrics                    loop timing (compute/lateness p50/p99/max, misses, overruns),
                                     degraded (hold) reasons, camera ages and staleness, clients
    GET  /config                     the fixture parameters in use (mode, radius, selection, cell)
    GET  /masters                    each master's latest raw sample: position in its own frame
                                     (m; null when invalid), valid, and the tick's number and loop
                                     time (s); read from the tick's published copy, not in a tick
                                     (``pointfence calib master --live`` polls it)
    POST /architecture  {"architecture": "I"|"II"|"III"}
    POST /haptics       {"engaged": true|false}
    POST /teleop        {"engaged": true|false}
    POST /radius        {"radius": 0.015[, "radius_max": R]}
    POST /selection     {"kind": "all"} | {"kind": "box", "min": [x,y,z], "max": [x,y,z]}
                        | {"kind": "color", "lo": [r,g,b], "hi": [r,g,b]} | {"kind": "mask"}
    POST /clear-faults  {}           leave the loop's safe mode, re-enable faulted robots

Radius and selection are parameters of the frame pipeline's snapshots. A change builds a new
pipeline with the new parameters (and, unless the configuration fixes ``[hash] cell_size``, the
cell size they need) off the tick thread, gives it a snapshot of every camera's latest frame,
makes the frame feeder build into it, and then, between two ticks, the tick swaps pipeline and
proxy batch together (the proxies keep their positions). Snapshots before the swap were built
with the old parameters and are queried with them; every snapshot after it with the new ones.
If the tick does not take the swap within ``apply_timeout`` the feeder goes back to the old
pipeline and the request fails (nothing changed). A radius the fixed cell size cannot serve is
refused with a message saying so. Runtime changes are not part of a recording's inputs:
``pointfence replay --recording`` replays the configuration's parameters.

Every request needs the run's bearer token (``control_http``, ``ctl_auth``): only the user who
runs the service can read or change it. POST bodies must be ``Content-Type: application/json``
and the ``Host`` a loopback name (a web page cannot post here: cross-origin JSON needs a CORS
preflight this server never grants).

Values that lower protection stay bounded: a radius in (0, ``MAX_RUNTIME_RADIUS``] m, finite
numbers only, a selection box with min < max on every axis inside +-``MAX_BOX_COORD`` m, a
colour range with lo <= hi, and no radius or selection that leaves the current frames without
a protected point. ``/clear-faults`` is refused (409) while any arm is coupled: release the
pedal first.
"""
from __future__ import annotations

import json
import math
import threading
from typing import Callable, Optional

from pointfence.kernels.errors import ConflictError, InputError, PointfenceError
from pointfence.kernels.params import RadiusModel, Selection

from .control_http import DEFAULT_CONTROL_PORT, ControlServer  # noqa: F401 - the API's server, importable here
from .teleop import ARCHITECTURES, arch_code

#: largest fixture radius (m) the API accepts at runtime (larger: edit the configuration)
MAX_RUNTIME_RADIUS = 0.1
#: largest |coordinate| (m) of a selection box the API accepts
MAX_BOX_COORD = 10.0


#: why the HTTP layer refused a request before any route saw it (``Controller.count_rejected``)
REJECT_REASONS = ("unauthenticated", "wrong_token", "host", "bad_body", "timeout", "busy")


class ControlError(Exception):
    """A refused request: HTTP ``status`` and a message for the caller."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = int(status)
        self.message = message


def _short(v, n: int = 60) -> str:
    """``repr(v)``, cut to ``n`` characters (a refused value is named, never echoed whole)."""
    try:
        r = repr(v)
    except ValueError:   # an int too long to print
        r = f"<{type(v).__name__}>"
    return r if len(r) <= n else r[: n - 3] + "..."


def _number(name: str, v, lo: float, hi: float, lo_open: bool = False, unit: str = "m", hint: str = "") -> float:
    """``v`` as a float in [lo, hi] (or (lo, hi] with ``lo_open``), else a 400 naming it
    (``hint``: appended to the out-of-range message)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ControlError(400, f"{name} = {_short(v)}; expected a number of {unit}")
    try:
        x = float(v)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise ControlError(400, f"{name} = {_short(v)}; expected a finite number of {unit}")
    if x < lo or (lo_open and x <= lo) or x > hi:
        raise ControlError(400, f"{name} = {_short(v)} {unit}; expected {lo:g} {'<' if lo_open else '<='} {name} "
                                f"<= {hi:g} {unit}" + (f" {hint}" if hint else ""))
    return x


class _Pending:
    """One function for the tick thread, with its result; ``cancel()`` and the tick's run are
    mutually exclusive (exactly one of them happens)."""

    def __init__(self, fn: Callable):
        self.fn = fn
        self.done = threading.Event()
        self.result = None
        self.error: Optional[BaseException] = None
        self._lock = threading.Lock()
        self._state = 0   # 0 queued, 1 ran, 2 cancelled

    def __call__(self, service) -> None:   # in the tick thread: never raises
        with self._lock:
            if self._state != 0:
                return
            self._state = 1
        try:
            self.result = self.fn(service)
        except BaseException as e:  # noqa: BLE001 - reported to the requester, never to the tick
            self.error = e
        self.done.set()

    def cancel(self) -> bool:
        with self._lock:
            if self._state == 0:
                self._state = 2
                return True
            return False


def _jsonable(o):
    return json.loads(json.dumps(o, default=lambda v: v.tolist() if hasattr(v, "tolist") else str(v)))


def selection_dict(sel: Selection) -> dict:
    d = {"kind": sel.kind}
    if sel.kind == "box":
        d.update(min=list(sel.box_min), max=list(sel.box_max))
    elif sel.kind == "color":
        d.update(lo=list(sel.color_lo), hi=list(sel.color_hi))
    return d


class Controller:
    """The API's logic, without HTTP: ``handle(method, path, body) -> (status, dict)``.

    Args:
        service: the running ``app.Service``.
        loop: its ``loop.HapticLoop`` (timing, safe-mode state); None: timing unavailable.
        clock: the loop's clock (frame ages); default the loop's.
        extras: name -> callable() returning a JSON-able dict, called in the tick thread for
            /status and /metrics (e.g. ``{"clients": hub.status}``).
        apply_timeout: s to wait for the tick thread to take a request.
    """

    def __init__(self, service, loop=None, clock=None, extras: Optional[dict] = None, apply_timeout: float = 2.0):
        self.service = service
        self.loop = loop
        self.clock = clock if clock is not None else getattr(loop, "clock", None)
        self.extras = dict(extras or {})
        self.apply_timeout = float(apply_timeout)
        self._lock = threading.Lock()      # one change at a time
        self.reconfigurations = 0
        self.requests = 0
        self.refused = 0
        self._count_lock = threading.Lock()
        self.rejected = {k: 0 for k in REJECT_REASONS}

    # --- the tick thread ------------------------------------------------------------------------
    def _in_tick(self, fn: Callable, what: str, leave_safe_mode: bool = False):
        """Run ``fn(service)`` in the tick thread between two ticks and return its result.
        ``leave_safe_mode``: clear the loop's error once ``fn`` is queued, so that ``fn`` runs
        at the start of the first normal tick, before it reads the masters."""
        loop = self.loop
        if loop is not None and loop.error is not None and not leave_safe_mode:
            raise ControlError(503, f"{what}: not applied: the haptic loop is in its safe mode after an error "
                                    f"({loop.error}); POST /clear-faults (pointfence ctl clear-faults) first")
        if loop is not None and not loop.running:
            raise ControlError(503, f"{what}: not applied: the haptic loop is not running")
        p = _Pending(fn)
        self.service.call_between_ticks(p)
        if leave_safe_mode and loop is not None:
            loop.clear_error()   # a flag; the next tick is a normal one again and runs p first
        if not p.done.wait(self.apply_timeout):
            if p.cancel():
                raise ControlError(503, f"{what}: not applied: the haptic loop ran no tick within "
                                        f"{self.apply_timeout:g} s (nothing changed)")
            p.done.wait()
        if p.error is not None:
            if isinstance(p.error, ControlError):
                raise p.error
            if isinstance(p.error, PointfenceError):
                raise ControlError(409, f"{what}: {p.error}")
            raise ControlError(500, f"{what}: {type(p.error).__name__}: {p.error}")
        return p.result

    def _now(self) -> Optional[float]:
        return self.clock.now() if self.clock is not None else None

    def _collect(self, svc) -> dict:
        """In the tick thread: status, the last tick's published values, extras."""
        out = {"status": svc.status(self._now()), "snapshot": svc.snapshot(), "tick": svc.last_tick}
        for name, fn in self.extras.items():
            try:
                out[name] = fn()
            except Exception as e:  # noqa: BLE001
                out[name] = {"error": f"{type(e).__name__}: {e}"}
        return out

    # --- requests -------------------------------------------------------------------------------
    def handle(self, method: str, path: str, body: Optional[dict] = None):
        with self._count_lock:
            self.requests += 1
        route = path.split("?", 1)[0].rstrip("/") or "/"
        try:
            fn = self.ROUTES.get((method, route))
            if fn is None:
                if any(r == route for _, r in self.ROUTES):
                    allowed = sorted(m for m, r in self.ROUTES if r == route)
                    raise ControlError(405, f"{method} {route}: method not allowed; use {', '.join(allowed)}")
                raise ControlError(404, f"no route {method} {route}; routes: " +
                                   ", ".join(f"{m} {r}" for m, r in sorted(self.ROUTES, key=lambda x: x[1])))
            if method == "POST" and not isinstance(body, dict):
                raise ControlError(400, f"POST {route}: expected a JSON object body")
            return 200, {"ok": True, **_jsonable(fn(self, body or {}))}
        except ControlError as e:
            self._count_refused()
            return e.status, {"ok": False, "error": e.message}
        except InputError as e:
            self._count_refused()
            return 400, {"ok": False, "error": str(e)}

    def _count_refused(self) -> None:
        with self._count_lock:
            self.refused += 1

    def get_status(self, _body) -> dict:
        c = self._in_tick(self._collect, "status")
        snap = c["snapshot"]
        arms = [{k: snap[k][b] for k in ("xm", "hip", "proxy", "cmd", "xr", "force")} | {"state": int(snap["state"][b])}
                for b in range(len(snap["state"]))]
        return {**c["status"], "tick": c["tick"], "t": snap["t"], "arms": arms, "fixture": self.fixture_config(),
                **{k: c[k] for k in self.extras}, "control": self.counters()}

    def get_metrics(self, _body) -> dict:
        c = self._in_tick(self._collect, "metrics")
        st = c["status"]
        fr = st.get("frames") or {}
        out = {
            "loop": self.loop.timing().as_dict() if self.loop is not None else None,
            "scheduling": getattr(self.loop, "scheduling", None),
            "loop_error": getattr(self.loop, "error", None), "loop_exceptions": getattr(self.loop, "errors", 0),
            "degraded": bool(st["hold"]) or any(st["arms_holding"]), "hold": st["hold"],
            "arms_holding": st["arms_holding"], "hold_causes": st["hold_causes"],
            "latched_faults": st["latched_faults"], "kernel_errors": st["kernel_errors"],
            "robot_errors": st["robot_errors"], "last_error": st["last_error"], "frame_seq": st["frame_seq"],
            "cameras": {"ages_s": fr.get("ages_s"), "stale": fr.get("stale"), "snapshots": fr.get("snapshots"),
                        "frames": fr.get("frames"), "ingest_errors": fr.get("ingest_errors")},
            "control": self.counters(),
        }
        if "grasper" in st:        # [cable]: the grasper's estimate, misses, alerts and fault
            out["grasper"] = st["grasper"]
        for name in self.extras:
            v = c[name]
            if isinstance(v, dict) and "sessions" in v:   # a UdpHub's status: counts
                out[name] = {"slots": v.get("slots"), "connected": len(v["sessions"]),
                             "accepted": v.get("accepted"), "rejected_total": v.get("rejected_total"),
                             "timed_out": v.get("sessions_timed_out"), "closed": v.get("sessions_closed")}
            else:
                out[name] = v
        return out

    def get_config(self, _body) -> dict:
        return {"fixture": self.fixture_config(), "architecture": self.service.architecture,
                "architectures": list(ARCHITECTURES)}

    def get_masters(self, _body) -> dict:
        m = self.service.master_sample()
        loop = self.loop
        arms = [{"arm": b, "valid": bool(ok), "position": [float(x) for x in pos] if ok and math.isfinite(sum(pos)) else None}
                for b, (pos, ok) in enumerate(zip(m["position"].tolist(), m["valid"].tolist()))]
        return {"tick": int(m["tick"]), "t": float(m["t"]), "masters": arms,
                "loop_running": bool(loop.running) if loop is not None else None,
                "loop_error": loop.error if loop is not None else None}

    def count_rejected(self, reason: str) -> None:
        """Count a request the HTTP layer refused before it reached a route (``REJECT_REASONS``)."""
        with self._count_lock:
            self.rejected[reason] += 1

    def counters(self) -> dict:
        """requests/refused: requests that reached a route and those of them refused;
        rejected: requests refused before that (no or wrong token, foreign Host, bad body,
        timed out, server busy)."""
        with self._count_lock:
            rejected = dict(self.rejected)
        return {"requests": self.requests, "refused": self.refused, "reconfigurations": self.reconfigurations,
                "rejected": rejected, "rejected_total": sum(rejected.values())}

    def fixture_config(self) -> dict:
        svc = self.service
        pp = svc.fixture_params
        r = pp.radius
        return {"mode": svc.cfg.mode, "radius": r.r_base, "radius_max": r.r_max, "adaptive": r.adaptive,
                "k_sigma": r.k_sigma, "selection": selection_dict(pp.selection), "cell_size": pp.cell_size,
                "cell_size_fixed": bool(svc.cfg.cell_size_given)}

    # --- commands -------------------------------------------------------------------------------
    def post_architecture(self, body) -> dict:
        a = body.get("architecture")
        if not isinstance(a, str) or a.upper() not in ARCHITECTURES:
            raise ControlError(400, f"architecture = {_short(a)}; expected one of {', '.join(ARCHITECTURES)} (eqs. 3.1-3.3)")
        code = arch_code(a)

        def apply(svc):
            prev = svc.architecture
            svc.set_architecture(code)   # applied by the next tick: HIP and command stay continuous, arms re-anchor (S1)
            return {"architecture": ARCHITECTURES[code - 1], "previous": prev, "applied_before_tick": svc.last_tick + 1}

        with self._lock:
            return self._in_tick(apply, "set architecture")

    def _engage(self, body, what: str) -> dict:
        on = body.get("engaged")
        if not isinstance(on, bool):
            raise ControlError(400, f"engaged = {_short(on)}; expected true or false")

        def apply(svc):
            prev = svc.haptics_on if what == "haptics" else svc.teleop_on
            (svc.engage_haptics if what == "haptics" else svc.engage_teleop)(on)
            return {what: on, "previous": prev, "applied_before_tick": svc.last_tick + 1}

        with self._lock:
            return self._in_tick(apply, f"{'engage' if on else 'disengage'} {what}")

    def post_haptics(self, body) -> dict:
        return self._engage(body, "haptics")

    def post_teleop(self, body) -> dict:
        return self._engage(body, "teleop")

    @staticmethod
    def _refuse_if_coupled(status: dict) -> None:
        arms = [b for b, (c, p) in enumerate(zip(status["coupled"], status["pedal"])) if c or (p and status["teleop"])]
        if arms:
            raise ControlError(409, f"clear faults: refused: arm(s) {', '.join(map(str, arms))} coupled (pedal down, "
                                    "teleoperation on); clearing faults needs every arm decoupled: release the "
                                    "pedal, then clear faults (nothing changed)")

    def post_clear_faults(self, body) -> dict:
        if body:
            raise ControlError(400, f"clear-faults: unknown key(s) {_short(sorted(body))}; expected an empty object")
        with self._lock:
            was = self.loop.error if self.loop is not None else None
            # first on the last tick's published pedals (safe ticks read them too), so that a
            # refused request does not take the loop out of its safe mode; then again in the tick
            self._refuse_if_coupled(self.service.status())

            def apply(svc):   # coupled: as published by the last tick (a safe tick decouples every arm)
                self._refuse_if_coupled(svc.status())
                svc.clear_faults()   # refuses (InputError -> 409) while an arm is coupled, too
                return {}

            return {**self._in_tick(apply, "clear faults", leave_safe_mode=True), "cleared_loop_error": was}

    def post_radius(self, body) -> dict:
        extra = set(body) - {"radius", "radius_max"}
        if extra:
            raise ControlError(400, f"radius: unknown key(s) {_short(sorted(extra))}; expected radius, radius_max")
        if "radius" not in body:
            raise ControlError(400, "radius: missing; expected {\"radius\": metres}, e.g. 0.015")
        lim = "(the control API's limit; set larger radii in the configuration and restart)"
        r = _number("radius", body["radius"], 0.0, MAX_RUNTIME_RADIUS, lo_open=True, hint=lim)
        cur = self.service.fixture_params.radius
        margin = cur.r_max - cur.r_base
        rmax = body.get("radius_max")
        if rmax is None:
            rmax = r + margin if cur.adaptive else r
        else:
            rmax = _number("radius_max", rmax, 0.0, MAX_RUNTIME_RADIUS + margin, lo_open=True,
                           hint="(the control API's limit: radius limit + the configured margin r_max - r_base)")
        try:
            model = RadiusModel(r_base=float(r), adaptive=cur.adaptive, k_sigma=cur.k_sigma, r_max=float(rmax))
        except InputError as e:
            raise ControlError(400, str(e)) from None
        return self._reconfigure(radius=model, what="radius")

    def post_selection(self, body) -> dict:
        kind = body.get("kind")
        extra = set(body) - {"kind", "min", "max", "lo", "hi"}
        if extra:
            raise ControlError(400, f"selection: unknown key(s) {_short(sorted(extra))}; expected kind, min, max, lo, hi")
        try:
            if kind == "box":
                lo, hi = (self._triple(body, key, "selection box", "expected [x, y, z] in metres (world frame)")
                          for key in ("min", "max"))
                lo = tuple(_number(f"selection box min[{i}]", x, -MAX_BOX_COORD, MAX_BOX_COORD) for i, x in enumerate(lo))
                hi = tuple(_number(f"selection box max[{i}]", x, -MAX_BOX_COORD, MAX_BOX_COORD) for i, x in enumerate(hi))
                if not all(a < b for a, b in zip(lo, hi)):
                    raise ControlError(400, f"selection box min {list(lo)} / max {list(hi)}: expected min < max on "
                                            "every axis (an empty or flat box protects nothing)")
                ws = self.service.fixture_params.workspace
                if any(b <= wa or a >= wb for a, b, wa, wb in zip(lo, hi, ws.min, ws.max)):
                    raise ControlError(400, f"selection box min {list(lo)} / max {list(hi)} lies outside the workspace "
                                            f"{list(ws.min)}..{list(ws.max)} (m): it would protect nothing")
                sel = Selection("box", box_min=lo, box_max=hi)
            elif kind == "color":
                lo, hi = (self._triple(body, key, "selection color", "expected [R, G, B] integers 0..255")
                          for key in ("lo", "hi"))
                for key, v in (("lo", lo), ("hi", hi)):
                    if not all(isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= 255 for x in v):
                        raise ControlError(400, f"selection color {key} = {_short(v)}; expected [R, G, B] integers 0..255")
                if not all(a <= b for a, b in zip(lo, hi)):
                    raise ControlError(400, f"selection color lo {lo} / hi {hi}: expected lo <= hi on every channel "
                                            "(an empty range protects nothing)")
                sel = Selection("color", color_lo=tuple(lo), color_hi=tuple(hi))
            elif kind in ("all", "mask"):
                sel = Selection(kind)
            else:
                raise ControlError(400, f"selection kind = {_short(kind)}; expected one of all, box, color, mask")
        except InputError as e:
            raise ControlError(400, str(e)) from None
        return self._reconfigure(selection=sel, what="selection")

    @staticmethod
    def _triple(body: dict, key: str, what: str, expected: str) -> list:
        v = body.get(key)
        if not isinstance(v, list) or len(v) != 3:
            raise ControlError(400, f"{what} {key} = {_short(v)}; {expected}")
        return v

    # --- runtime reconfiguration of the snapshots' parameters -----------------------------------
    def _reconfigure(self, what: str, radius=None, selection=None) -> dict:
        """Prepared outside the tick (``Service.prepare_reconfiguration``), committed between two
        ticks; if the tick does not take it, it is undone (nothing changed)."""
        with self._lock:
            try:
                change = self.service.prepare_reconfiguration(radius=radius, selection=selection)
            except InputError as e:
                raise ControlError(400, f"{what}: {e}") from None
            except ConflictError as e:
                raise ControlError(409, f"{what}: {e}") from None
            if change is None:
                return {"changed": False, "fixture": self.fixture_config()}

            def commit(svc):
                change.commit()
                return svc.last_tick + 1

            try:
                tick = self._in_tick(commit, what)
            except ControlError:
                change.abort()                  # the feeder goes back to the pipeline the ticks still query
                raise
            change.release()                    # the old pipeline is released here, not in a tick
            self.reconfigurations += 1
            return {"changed": True, "applied_before_tick": tick, "fixture": self.fixture_config()}

    ROUTES = {
        ("GET", "/status"): get_status,
        ("GET", "/metrics"): get_metrics,
        ("GET", "/config"): get_config,
        ("GET", "/masters"): get_masters,
        ("POST", "/architecture"): post_architecture,
        ("POST", "/haptics"): post_haptics,
        ("POST", "/teleop"): post_teleop,
        ("POST", "/radius"): post_radius,
        ("POST", "/selection"): post_selection,
        ("POST", "/clear-faults"): post_clear_faults,
    }
