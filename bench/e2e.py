"""`pointfence bench e2e`: one client at 1 kHz over loopback against a live service.

Starts ``pointfence serve`` in its own process (``python -m pointfence.service.serve``; the scene
of the embedded defaults with a 160x120 synthetic camera at 30 Hz, PoCL, the simulated Raven II,
or ``--config``),
waits until its loop runs, then drives it with the Python SDK's per-tick callback
(``Client.control``: 1 kHz, phase-locked ``--lead-us`` ahead of the service tick) for
``--duration`` s, moving the master in a slow 2 cm circle. Meanwhile ``--attack-hz`` hostile
datagrams per second (forged tags, replays of earlier states, truncated, oversized, NaN with a
bad tag, unknown session; in turn) go to the same port from another socket.

Reports ``rtt_us_p50/p99/max`` (a state's send -> arrival of the first force computed from it),
``loss_ratio`` (datagrams lost on the link, both ways: states the client sent that the service
never received (neither accepted nor superseded by a newer one in the same drain), plus feedback the service sent that the client never received, over all sent;
the service's counters are read through its control API at the start and end of the measured
run), ``unanswered_ratio`` (states whose own sequence no feedback echoed: lost, or accepted in
the same tick as, or drained together with, a newer state of the same device, which the tick
used instead: ``states_superseded``), ``feedback_gaps`` (service ticks whose feedback never arrived), the
service's ``rejected`` counters, its loop timing and the client's timing violations. When the link is lost (no feedback for the session timeout: the service or
this process stalled) the client reconnects and ``link_lost`` counts it.
``master_state_age_ms_p50/p99/max``: how old the master sample each service tick used was (its
kernel arrival at the service to the tick; the hub's ``state_age_ms``); ``--flood-hz`` adds a
forged flood from a process of its own (``kernel_dropped``: datagrams the service's socket had
no room for). Target (2-core CPU,
loopback): rtt p99 <= 1 ms, zero loss over 60 s.
"""
from __future__ import annotations

import json
import math
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pointfence.clients import Client, Command, LinkLost, TimingError
from pointfence.clients import protocol as P
# imported here, not where the counters are read: between two runs of the client loop, an
# import that takes longer than the session timeout would drop the session
from pointfence.service.ctl import ControlClient


#: the embedded defaults with a 160x120 camera: the link is measured, not the 30 Hz ingest
LIGHT_SCENE = """
backend = "opencl"
[workspace]
min = [-0.25, -0.25, -0.02]
max = [0.25, 0.25, 0.25]
[fixture]
mode = "fixture"
radius = 0.02
select = { kind = "color", lo = [150, 0, 0], hi = [255, 90, 90] }
[[camera]]
name = "overhead"
source = "synthetic:sphere"
fx = 143.95
fy = 143.95
cx = 79.5
cy = 59.5
width = 160
height = 120
T_world_cam = [1, 0, 0, 0,  0, -1, 0, 0,  0, 0, -1, 0.6,  0, 0, 0, 1]
options = { color = true }
[teleop]
architecture = "III"
scale = 0.5
[robot]
model = "raven2"
mount_tool_down = [0.0, 0.0, 0.25]
"""


def add_arguments(p):
    p.add_argument("--duration", type=float, default=60.0, help="seconds of 1 kHz traffic (default 60)")
    p.add_argument("--render-live", action="store_true",
                   help="the service renders its synthetic camera's frames live (default: 30 frames pre-rendered and "
                        "served at the camera's rate, as `bench loop` does, as a real camera's C driver would cost)")
    p.add_argument("--config", default=None,
                   help="service configuration (default: the embedded defaults' scene with a 160x120 camera; "
                        "'defaults' for the embedded defaults as they are)")
    p.add_argument("--lead-us", type=float, default=250.0, help="client sends this long before the service tick (default 250)")
    p.add_argument("--client-rt-priority", type=int, default=70,
                   help="SCHED_FIFO priority of the client's control thread where allowed, as a haptic device "
                        "driver runs (default 70, below the service loop's 80; 0: normal)")
    p.add_argument("--spin-us", type=float, default=300.0, help="client busy-waits this long before each tick (default 300)")
    p.add_argument("--attack-hz", type=float, default=10.0, help="hostile datagrams per second (default 10; 0: none)")
    p.add_argument("--flood-hz", type=float, default=0.0,
                   help="a forged-datagram flood at this rate from a process of its own during the measured run "
                        "(STATE-shaped, this session's header, random tags; default 0: none)")
    p.add_argument("--startup-timeout", type=float, default=180.0, help="seconds to wait for the service to run")


def wait_ready(proc, ready: Path, log: Path, timeout: float) -> dict:
    """The ready file's contents (host, port, ...) once the `serve` process ``proc`` has written
    ``ready``; RuntimeError with the end of its ``log`` if it exits first, or after ``timeout`` s."""
    end = time.monotonic() + timeout
    while not ready.exists():
        if proc.poll() is not None:
            raise RuntimeError(f"the service exited ({proc.returncode}): {log.read_text()[-2000:]}")
        if time.monotonic() > end:
            raise RuntimeError(f"the service did not start within {timeout} s")
        time.sleep(0.05)
    return json.loads(ready.read_text())


def _attack(sock, addr, client, k: int) -> None:
    kind = k % 6
    last = client.last_datagram
    if kind == 0 and last:                       # forged: valid layout, wrong tag
        b = bytearray(last); b[-1] ^= 0x55; b[P.HEADER_LEN + 16] ^= 1
        data = bytes(b)
    elif kind == 1 and last:                     # replay of an earlier authentic state
        data = last
    elif kind == 2 and last:
        data = last[:-7]                         # truncated
    elif kind == 3 and last:
        data = last + b"\0" * 9                  # oversized
    elif kind == 4 and last:                     # NaN position with an unfixable tag
        b = bytearray(last); b[P.HEADER_LEN + 16:P.HEADER_LEN + 24] = struct.pack("<d", math.nan)
        data = bytes(b)
    else:                                        # a STATE for a session that does not exist
        data = P.State().encode(os.urandom(32), client.device_id, 12345, 1)
    try:
        sock.sendto(data, addr)
    except OSError:
        pass


def _hub_counters(host: str, control_port, token_file=None) -> tuple:
    """(states accepted, feedback sent, states superseded) by the service's UDP hub so far, read
    through its control API with the run's token; (None, None, None) without a control API."""
    if not control_port:
        return None, None, None
    c = ControlClient(host, control_port, 10.0, token_file=token_file).status()["clients"]
    return int(c["accepted"]), int(c["feedback_sent"]), int(c.get("superseded", 0))


def _start_flood(host: str, port: int, header_of, seconds: float, rate_hz: float):
    """The forged flood of ``bench soak`` (``soak_devices.flood_main``) in a process of its own."""
    import multiprocessing

    from .soak_devices import flood_main

    ctx = multiprocessing.get_context("spawn")
    conn, child = ctx.Pipe()
    p = ctx.Process(target=flood_main, args=(child, host, port, "forged", seconds, rate_hz, [header_of]), daemon=True)
    p.start()
    return p, conn


def _end_flood(flood) -> int:
    p, conn = flood
    n = conn.recv() if conn.poll(60) else 0
    p.join(timeout=5)
    if p.is_alive():
        p.kill()
    return int(n)


def run(args) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="pf-e2e-"))
    key_path = tmp / "key"
    key_path.write_text(os.urandom(32).hex() + "\n")
    key_path.chmod(0o600)        # a key file others may read is refused (clients/keyfile.py)
    ready, stats = tmp / "ready.json", tmp / "stats.json"
    cmd = [sys.executable, "-m", "pointfence.service.serve", "--key-file", str(key_path), "--port", "0",
           "--control-port", "0", "--clients", "1", "--ready-file", str(ready), "--stats-file", str(stats), "--status-every", "0",
           "--duration", str(args.duration + args.startup_timeout + 30)]
    if not args.render_live:
        cmd += ["--prerender", "30"]
    if args.config is None:
        (tmp / "scene.toml").write_text(LIGHT_SCENE)
        cmd += ["--config", str(tmp / "scene.toml")]
    elif args.config != "defaults":
        cmd += ["--config", args.config]
    if getattr(args, "backend", None) and args.backend != "opencl":
        cmd += ["--backend", args.backend]
    if getattr(args, "device", None):
        cmd += ["--device", args.device]
    log = open(tmp / "serve.log", "w")
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log)
    try:
        addr = wait_ready(proc, ready, tmp / "serve.log", args.startup_timeout)
        host, port = addr["host"], addr["port"]
        attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        attack_every = int(1000 / args.attack_hz) if args.attack_hz > 0 else 0
        ticks_seen = []
        sent_attacks = [0]
        holder = {}

        def tick(t):
            if attack_every and t.index % attack_every == attack_every // 2:
                _attack(attacker, (host, port), holder["c"], sent_attacks[0])
                sent_attacks[0] += 1
            if t.feedback is not None:
                ticks_seen.append(t.feedback.tick)
            a = 2 * math.pi * (time.perf_counter() - t_start) / 8.0
            return Command((0.02 * math.cos(a) - 0.02, 0.02 * math.sin(a), 0.0), clutch=True)

        def new_client():
            c = Client(host, port, key_path, 1, max_force=3.3, workspace=((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1)),
                       model="bench-e2e")
            c.connect(timeout=30.0)
            holder["c"] = c
            return c

        t_start = time.perf_counter()
        client = new_client()
        # warm-up second (phase lock, first kernel launches), then the measured run; a link lost in
        # it (a loaded machine stalled the service or this process past the timeout) is not measured
        for attempt in range(5):
            try:
                client.control(tick, duration=1.0, lead_us=args.lead_us, spin_us=args.spin_us,
                               rt_priority=args.client_rt_priority)
                break
            except (LinkLost, TimingError):
                if attempt == 4:
                    raise
                client.close()
                client = new_client()
        client.stats = type(client.stats)()
        ticks_seen.clear()
        hub0 = _hub_counters(host, addr.get("control_port"), addr.get("control_token_file"))
        flood = _start_flood(host, port, client.last_datagram, args.duration, args.flood_hz) if args.flood_hz > 0 else None
        totals = {"sent": 0, "echoed": 0, "feedback": 0, "rejected_in": 0, "rtt": [], "ticks": 0}
        link_lost, timing_errors, lost_msgs = 0, 0, []
        t0 = time.perf_counter()
        while True:
            left = args.duration - (time.perf_counter() - t0)
            if left <= 0.01:
                break
            try:
                client.control(tick, duration=left, lead_us=args.lead_us, spin_us=args.spin_us,
                                   rt_priority=args.client_rt_priority)
            except LinkLost as e:            # the service (or this process) stalled beyond the timeout
                link_lost += 1
                lost_msgs.append(str(e))
            except TimingError as e:
                timing_errors += 1
                lost_msgs.append(str(e))
            end = time.monotonic() + 0.05
            while time.monotonic() < end:
                client.poll()
            st = client.stats
            totals["sent"] += st.sent
            totals["ticks"] += st.sent
            totals["echoed"] += st.echoed
            totals["feedback"] += st.feedback
            totals["rejected_in"] += st.rejected_in
            totals["rtt"] += st.rtt_us
            totals.setdefault("lead", []).extend(st.answer_lead_us)
            client.close()
            if time.perf_counter() - t0 < args.duration - 0.01:
                client = new_client()
        wall = time.perf_counter() - t0
        flooded = _end_flood(flood) if flood is not None else 0
        hub1 = _hub_counters(host, addr.get("control_port"), addr.get("control_token_file"))
        attacker.close()
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
        log.close()
    service = json.loads(stats.read_text()) if stats.exists() else {}
    rtt = np.asarray(totals["rtt"]) if totals["rtt"] else np.array([math.nan])
    seen = np.unique(np.asarray(ticks_seen))
    gaps = int((seen[-1] - seen[0] + 1) - len(seen)) if len(seen) else None
    udp = service.get("udp", {})
    sent, echoed, fb_in = totals["sent"], totals["echoed"], totals["feedback"]
    if hub0[0] is not None and hub1[0] is not None:
        accepted, fb_out, newer = hub1[0] - hub0[0], hub1[1] - hub0[1], hub1[2] - hub0[2]
        # (a datagram of the warm-up still in flight at the first reading counts once too many);
        # a state that a newer one replaced in the receiver's drain arrived: superseded, not lost
        lost_states, lost_fb = max(0, sent - accepted - newer), max(0, fb_out - fb_in)
        link = {"states_accepted_by_service": accepted, "states_lost": lost_states,
                "states_superseded_in_drain": newer, "states_superseded": max(0, accepted - echoed) + newer,
                "feedback_sent_by_service": fb_out, "feedback_lost": lost_fb,
                "loss_ratio": round((lost_states + lost_fb) / (sent + fb_out), 6) if sent + fb_out else None}
    else:
        link = {"loss_ratio": None}
    return {
        "duration_s": round(wall, 2), "ticks": totals["ticks"], "states_sent": totals["sent"],
        "states_answered": totals["echoed"],
        "rtt_us_p50": round(float(np.percentile(rtt, 50)), 1), "rtt_us_p99": round(float(np.percentile(rtt, 99)), 1),
        "rtt_us_max": round(float(np.max(rtt)), 1),
        # send -> deadline of the answering tick: about lead_us when a state makes its tick,
        # a period more when it arrived after the tick had read the socket
        "answered_tick_after_send_us_p10_p50_p90": [round(float(np.percentile(totals.get("lead") or [math.nan], q)), 1)
                                                    for q in (10, 50, 90)],
        **link,
        "unanswered_ratio": round(1.0 - echoed / sent, 6) if sent else None,
        "link_lost": link_lost, "timing_errors": timing_errors, "link_events": lost_msgs[:5],
        "feedback_received": totals["feedback"], "feedback_gaps": gaps, "lead_us": args.lead_us, "spin_us": args.spin_us,
        "client_scheduling": client.scheduling,
        "config": args.config or "light (160x120 camera)",
        "frames": "rendered live" if args.render_live else "30 pre-rendered frames served in real time", "attacks_sent": sent_attacks[0], "rejected": {k: v for k, v in udp.get("rejected", {}).items() if v},
        "rejected_total": udp.get("rejected_total"), "client_rejected": totals["rejected_in"],
        "flood_hz": args.flood_hz, "flood_sent": flooded, "kernel_dropped": udp.get("kernel_dropped"),
        # the age of the master sample each tick used: its kernel arrival at the service to the tick
        **{f"master_state_age_ms_{k[:-3]}": v for k, v in (udp.get("state_age_ms") or {}).items() if k != "n"},
        "sessions_timed_out": udp.get("sessions_timed_out"),
        "service_loop": service.get("loop"), "targets": {"rtt_us_p99": 1000, "loss_ratio": 0.0},
    }
