"""Capturing the guided master motion live from a running `pointfence serve`
(``pointfence calib master --live``): the steps that ``master_reg.register_guided`` solves.

The operator is prompted for each step: hold the master still at a start point, then move it
about 5 cm along each world direction (+x, -x, +y, -y, +z, -z: the robot base's axes, as the
operator sees them) and hold it still. Each step's position is the master's raw sample (the
master device's own frame, m), read from the control API's ``GET /masters`` (the tick's
published copy: nothing runs in the 1 kHz tick for it) and averaged over ``AVG_S`` of wall time
once the master has stayed within ``STILL_TOL_M`` of its mean for ``hold_s``. A step is taken
automatically once the master is still at least ``MIN_MOVE_M`` away from the previous step's
position, or, with ``enter``, when the operator presses Enter (then it waits for stillness).

A step that does not come within ``step_timeout`` s (the master never moved, never held still,
or gave no valid sample) is left out with a message saying what happened; the solver's verdict
then says NOT TRUSTED (too few steps) with those messages. Errors that make the capture
meaningless (no such arm, the service's loop stopped or in its safe mode, no start position)
raise ``InputError``; a refused request (no or wrong token) raises ``ctl.ControlRefused``.
Windows are in wall time (the operator's), samples deduplicated by tick number.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from pointfence.kernels.errors import InputError

MIN_MOVE_M = 0.03       # a step counts once the master rests this far from the previous one (m)
STILL_TOL_M = 0.0015    # still: every sample of the hold window within this of the window's mean (m)
HOLD_S = 0.6            # how long the master must stay still before a step is taken (s)
AVG_S = 0.3             # the step's position: the mean over the last AVG_S of the hold (s)
POLL_S = 0.01           # between two reads of GET /masters (s)
STALE_S = 1.0           # no new tick for this long: the service is not ticking (s)


@dataclass
class Capture:
    """``steps`` [(direction, (x, y, z)), ...] (master frame, m) with "start" first, only the
    captured ones; ``problems`` one message per step left out."""

    steps: list
    problems: list = field(default_factory=list)


class MasterFeed:
    """One arm's raw master samples from a running service's control API.

    ``client``: a ``service.ctl.ControlClient`` (it carries the run's token); ``arm``: which
    master (0-based)."""

    def __init__(self, client, arm: int = 0):
        self.client, self.arm = client, int(arm)

    def read(self) -> tuple:
        """(tick number, loop time s, position (3,) master frame m or None when invalid)."""
        r = self.client.get("/masters")
        arms = r.get("masters") or []
        if not 0 <= self.arm < len(arms):
            raise InputError(f"calib master --live: --arm {self.arm}, but the service has {len(arms)} master(s) "
                             f"(arms 0..{len(arms) - 1})")
        if r.get("loop_error"):
            raise InputError(f"calib master --live: the service's haptic loop is in its safe mode ({r['loop_error']}); "
                             "clear it (`pointfence ctl clear-faults`) and start again")
        if r.get("loop_running") is False:
            raise InputError("calib master --live: the service's haptic loop is not running")
        m = arms[self.arm]
        pos = np.asarray(m["position"], dtype=np.float64) if m.get("valid") and m.get("position") is not None else None
        return int(r["tick"]), float(r["t"]), pos


class GuidedCapture:
    """The prompts and the capture (module docstring).

    Args:
        feed: a ``MasterFeed`` (or anything with ``read() -> (tick, t, position or None)``).
        directions: the prompted directions after "start", e.g. ``master_reg.DIRECTIONS``' keys.
        distance: the step length asked for (m).
        hold_s, step_timeout: s (wall time).
        enter: take each step when the operator presses Enter (``wait_enter``), not automatically.
        prompt: ``prompt(direction, text)`` for each step ("start" first); default prints.
        say: progress messages; default prints.
        wait_enter: ``wait_enter(text)`` blocks until the operator is ready; default ``input``.
        clock, sleep: wall clock (s) and sleep, for tests.
    """

    def __init__(self, feed, directions, distance: float = 0.05, hold_s: float = HOLD_S, step_timeout: float = 30.0,
                 enter: bool = False, prompt: Optional[Callable] = None, say: Optional[Callable] = None,
                 wait_enter: Optional[Callable] = None, clock: Callable = time.monotonic, sleep: Callable = time.sleep):
        if not hold_s > 0 or not step_timeout > hold_s:
            raise InputError(f"calib master --live: hold {hold_s} s and step timeout {step_timeout} s; expected "
                             "0 < hold < timeout")
        self.feed, self.directions, self.distance = feed, list(directions), float(distance)
        self.hold_s, self.avg_s, self.step_timeout = float(hold_s), min(AVG_S, float(hold_s)), float(step_timeout)
        self.enter = bool(enter)
        self.say = say if say is not None else (lambda s: print(s, flush=True))
        self.prompt = prompt if prompt is not None else (lambda d, text: self.say(text))
        self.wait_enter = wait_enter if wait_enter is not None else input
        self.clock, self.sleep = clock, sleep

    def text(self, direction: str) -> str:
        how = "then press Enter" if self.enter else "the step is taken once it rests"
        if direction == "start":
            return f">> start: hold the master still at a comfortable point in the middle of its workspace ({how})"
        return (f">> {direction}: move the master about {self.distance * 100:.0f} cm toward world {direction} (the robot "
                f"base's {direction} axis, as you see it) and hold it still ({how})")

    def run(self) -> Capture:
        self.prompt("start", self.text("start"))
        if self.enter:
            self.wait_enter(self.text("start"))
        pos, why = self._take(None)
        if pos is None:
            raise InputError(f"calib master --live: no start position: {why}")
        cap = Capture([("start", tuple(pos.tolist()))])
        self.say(f"   start: {_fmt(pos)} (master frame)")
        last = pos
        for d in self.directions:
            self.prompt(d, self.text(d))
            if self.enter:
                self.wait_enter(self.text(d))
            pos, why = self._take(last)
            if pos is None:
                cap.problems.append(f"step {d} not captured: {why}")
                self.say(f"   {d}: NOT captured: {why}")
                continue
            cap.steps.append((d, tuple(pos.tolist())))
            self.say(f"   {d}: {_fmt(pos)}, moved {np.linalg.norm(pos - last) * 100:.1f} cm")
            last = pos
        return cap

    def _take(self, ref: Optional[np.ndarray]) -> tuple:
        """(position or None, why not): the mean of the last ``avg_s`` once the master has been
        still for ``hold_s`` (and, without ``enter``, at least ``MIN_MOVE_M`` from ``ref``)."""
        win: deque = deque()       # (wall s, position)
        t0 = self.clock()
        last_tick, last_new = None, t0
        valid_seen = moved_max = 0.0
        still_seen = False
        while True:
            now = self.clock()
            if now - t0 > self.step_timeout:
                return None, self._why(ref, valid_seen > 0, moved_max, still_seen)
            tick, _t, pos = self.feed.read()
            now = self.clock()
            if tick != last_tick:
                last_tick, last_new = tick, now
                if pos is None:
                    win.clear()
                else:
                    valid_seen += 1
                    win.append((now, pos))
                    if ref is not None:
                        moved_max = max(moved_max, float(np.linalg.norm(pos - ref)))
            elif now - last_new > STALE_S:
                raise InputError(f"calib master --live: the service published no new tick for {now - last_new:.1f} s "
                                 f"(last tick {last_tick}); is its haptic loop running?")
            while len(win) > 1 and win[1][0] <= now - self.hold_s:
                win.popleft()
            if len(win) >= 3 and win[0][0] <= now - self.hold_s:
                P = np.array([p for _, p in win])
                if np.max(np.linalg.norm(P - P.mean(axis=0), axis=1)) <= STILL_TOL_M:
                    still_seen = True
                    avg = np.array([p for s, p in win if s >= now - self.avg_s]).mean(axis=0)
                    if ref is None:
                        return avg, ""
                    if np.linalg.norm(avg - ref) >= MIN_MOVE_M:
                        return avg, ""
                    if self.enter:
                        return None, (f"the master rests {np.linalg.norm(avg - ref) * 100:.1f} cm from the previous "
                                      f"position (at least {MIN_MOVE_M * 100:.0f} cm needed); move it about "
                                      f"{self.distance * 100:.0f} cm before pressing Enter")
            self.sleep(POLL_S)

    def _why(self, ref, valid: bool, moved: float, still: bool) -> str:
        t = f"within {self.step_timeout:g} s"
        if not valid:
            return (f"the master gave no valid sample {t} (device absent, silent or faulty: check `pointfence ctl "
                    "status` and the master's connection)")
        if ref is not None and moved < MIN_MOVE_M:
            return (f"the master did not move (at most {moved * 100:.1f} cm from the previous position {t}; at least "
                    f"{MIN_MOVE_M * 100:.0f} cm needed): is this the arm the operator holds (--arm)?")
        if not still or ref is None:
            return (f"the master never held still (within {STILL_TOL_M * 1000:.1f} mm for {self.hold_s:g} s) {t}; rest "
                    "the hand on the master after each move")
        return f"the master did not rest at least {MIN_MOVE_M * 100:.0f} cm from the previous position {t}"


def _fmt(p) -> str:
    return "(" + ", ".join(f"{x * 1000:.1f}" for x in p) + ") mm"


# -- CLI ------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    """The live mode's options (``pointfence calib master --live``); the control API's address
    and token are found as `pointfence ctl` finds them (``service/ctl.py``)."""
    from pointfence.service import ctl_auth
    from pointfence.service.control_http import DEFAULT_CONTROL_PORT

    g = p.add_argument_group("live (--live: capture the guided motion from a running `pointfence serve`)")
    g.add_argument("--live", action="store_true", help="prompt the operator and read the master from the running service")
    g.add_argument("--arm", type=int, default=0, help="which master (0-based, default 0)")
    g.add_argument("--host", default=None, help="control API host (default 127.0.0.1)")
    g.add_argument("--port", type=int, default=None, help=f"control API port (default {DEFAULT_CONTROL_PORT}, "
                                                          "or $POINTFENCE_CONTROL=[HOST:]PORT)")
    g.add_argument("--token-file", default=None,
                   help=f"the service's control token (default ${ctl_auth.TOKEN_ENV}, else the file `pointfence serve` "
                        "writes for the port)")
    g.add_argument("--enter", action="store_true", help="take each step when Enter is pressed (default: once the master rests)")
    g.add_argument("--hold", type=float, default=HOLD_S, help=f"s the master must rest before a step is taken (default {HOLD_S})")
    g.add_argument("--step-timeout", type=float, default=30.0, help="s to wait for each step (default 30)")


def capture_from_args(args, directions, prompt=None, say=None, wait_enter=None) -> Capture:
    """Connect as `pointfence ctl` does and run the prompts (``GuidedCapture``)."""
    import os

    from pointfence.service import ctl_auth
    from pointfence.service.ctl import ControlClient, address

    host, port = address(args)
    token_file = args.token_file if args.token_file is not None else os.environ.get(ctl_auth.TOKEN_ENV)
    feed = MasterFeed(ControlClient(host, port, timeout=10.0, token_file=token_file), args.arm)
    feed.read()   # the address, the token and the arm, before the first prompt
    return GuidedCapture(feed, directions, hold_s=args.hold, step_timeout=args.step_timeout, enter=args.enter,
                         prompt=prompt, say=say, wait_enter=wait_enter).run()
