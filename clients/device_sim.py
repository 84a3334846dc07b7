"""`pointfence device-sim`: a simulated haptic device driving a live service over the protocol.

    pointfence device-sim --key-file pf.key --trajectory push.csv [--host H --port P]
    pointfence device-sim --key-file pf.key --motion circle|push|line|hold [--amplitude 0.02] [--duration 5]

The device plays a trajectory CSV (``t,x,y,z[,clutch]``, master frame, m and s; the format of
``pointfence replay``) or a scripted motion at ``--rate`` Hz through the per-tick callback API
(``Client.control``) and prints a JSON summary: ticks, round trips (state sent -> first force
computed from it, microseconds), states the service never answered, the largest force, the
last proxy and robot positions, and datagrams dropped on either side.
"""
from __future__ import annotations

import json
import math

import numpy as np

from pointfence.kernels.errors import InputError

from . import protocol as P
from .client import Client, Command

MOTIONS = ("circle", "push", "line", "hold")


def add_arguments(p):
    p.add_argument("--host", default="127.0.0.1", help="service address (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=47800, help="service UDP port (default 47800)")
    p.add_argument("--key-file", required=True, help="the pre-shared key file given to `pointfence serve`")
    p.add_argument("--device-id", type=int, default=1, help="this device's id (default 1)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--trajectory", help="trajectory CSV t,x,y,z[,clutch] (master frame)")
    src.add_argument("--motion", choices=MOTIONS, default="circle", help="scripted motion (default circle)")
    p.add_argument("--amplitude", type=float, default=0.02, help="motion size, m (default 0.02)")
    p.add_argument("--period", type=float, default=4.0, help="motion period, s (default 4)")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the trajectory's length, or 5)")
    p.add_argument("--rate", type=float, default=1000.0, help="ticks per second (default 1000)")
    p.add_argument("--lead-us", type=float, default=250.0, help="send this long before the service tick (default 250)")
    p.add_argument("--rt-priority", type=int, default=0,
                   help="SCHED_FIFO priority of the device loop where allowed (a real device driver's; default 0: normal)")
    p.add_argument("--late-limit", type=int, default=20,
                   help="consecutive ticks that overrun the period before the device stops with a timing error "
                        "(default 20, libfranka's contract; a larger value tolerates a loaded machine)")
    p.add_argument("--max-force", type=float, default=3.3, help="device force limit, N (default 3.3)")
    p.add_argument("--workspace", type=float, default=0.1, help="device workspace half-size, m (default 0.1)")
    p.add_argument("--timeout-ms", type=int, default=P.DEFAULT_TIMEOUT_MS, help="session timeout asked for")
    p.add_argument("--connect-timeout", type=float, default=30.0, help="seconds to wait for the service")


def motion(kind: str, amplitude: float, period: float):
    """position(t) of a scripted motion (master frame, m)."""
    w = 2 * math.pi / period
    if kind == "circle":
        return lambda t: (amplitude * math.cos(w * t) - amplitude, amplitude * math.sin(w * t), 0.0)
    if kind == "push":      # down by 3 x amplitude over one period, then hold
        return lambda t: (0.0, 0.0, -3 * amplitude * min(t / period, 1.0))
    if kind == "line":
        return lambda t: (amplitude * math.sin(w * t), 0.0, 0.0)
    if kind == "hold":
        return lambda t: (0.0, 0.0, 0.0)
    raise InputError(f"motion {kind!r}; expected one of {', '.join(MOTIONS)}")


def trajectory_player(path):
    from .trajectory import Trajectory

    m = Trajectory.from_csv(path)
    return m.at, m.duration


def run(args) -> int:
    if args.trajectory:
        play, length = trajectory_player(args.trajectory)
        duration = args.duration if args.duration is not None else length + 0.2
    else:
        f = motion(args.motion, args.amplitude, args.period)
        play = lambda t: (f(t), True)  # noqa: E731
        duration = args.duration if args.duration is not None else 5.0
    h = args.workspace
    client = Client(args.host, args.port, args.key_file, args.device_id, max_force=args.max_force,
                    workspace=((-h, -h, -h), (h, h, h)), rate_hz=args.rate, timeout_ms=args.timeout_ms, model="device-sim")
    fmax = [0.0]
    contact_ticks = [0]

    def tick(t):
        pos, clutch = play(t.time)
        n = float(np.linalg.norm(t.force))
        fmax[0] = max(fmax[0], n)
        if t.feedback is not None and t.feedback.contact:
            contact_ticks[0] += 1
        return Command(pos, clutch=clutch)

    with client:
        w = client.connect(timeout=args.connect_timeout)
        ticks = client.control(tick, rate_hz=args.rate, duration=duration, lead_us=args.lead_us,
                               rt_priority=args.rt_priority, late_limit=args.late_limit)
        # let the last answers arrive
        import time

        end = time.monotonic() + 0.02
        while time.monotonic() < end:
            client.poll()
        st = client.stats
        rtt = np.asarray(st.rtt_us) if st.rtt_us else np.zeros(1)
        fb = client.feedback
        out = {
            "session": client.session, "slot": w.slot, "timeout_ms": w.timeout_ms, "ticks": ticks,
            "states_sent": st.sent, "states_answered": st.echoed,
            "unanswered_ratio": round(1 - st.echoed / st.sent, 6) if st.sent else None,
            "feedback_received": st.feedback, "rtt_us_p50": round(float(np.percentile(rtt, 50)), 1),
            "rtt_us_p99": round(float(np.percentile(rtt, 99)), 1), "rtt_us_max": round(float(rtt.max()), 1),
            "max_force_n": round(fmax[0], 4), "contact_ticks": contact_ticks[0],
            "last_proxy": [round(v, 5) for v in fb.proxy] if fb else None,
            "last_robot": [round(v, 5) for v in fb.robot] if fb else None,
            "service_rejected_for_session": fb.rejected if fb else None, "client_rejected": st.rejected_in,
        }
    print(json.dumps(out))
    return 0


def main(argv=None) -> int:
    """``python -m pointfence.clients.device_sim`` (the same as ``pointfence device-sim``)."""
    import sys

    from pointfence.cli import main as pointfence_main

    return pointfence_main(["device-sim", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())
