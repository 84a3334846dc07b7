"""`pointfence bench NAME`: benchmarks that print one JSON object.

Each benchmark is a module ``pointfence.bench.<NAME>`` with ``add_arguments(parser)`` and
``run(args) -> dict``. Timing belongs here, never in tests.
"""
from __future__ import annotations

import importlib
import json
import sys

#: name -> one-line description
BENCHES = {
    "frames": "frame ingest (deproject, transform, radius, hash) vs scipy cKDTree and the projective search",
    "floor": "launch + copy floor of the device (what a tick costs with no work in it)",
    "query": "haptic tick: batched proxy kernel on a real close-range frame (1/64/1024 proxies, steps/s) vs the same algorithm over scipy cKDTree",
    "cable": "cable controller: UKF step vs filterpy's UnscentedKalmanFilter (same model), iLQG MPC tick (horizon 10, 3 iterations, compiled C) and Ipopt on the same horizon, first compile and cached start",
    "loop": "the live 1 kHz haptic loop on a synthetic scene: tick compute and lateness p50/p99, deadline misses, 1 and 4 proxies",
    "e2e": "one client at 1 kHz over loopback against a live `serve` process: rtt_us p50/p99, loss_ratio, rejected counts (--duration, default 60 s)",
    "fuzz": "random and mutated datagrams (default 1,000,000) through the service's packet handler: no crash, no accepted forgery",
    "dynamic": "chapter 6 in simulated time: pop-through speed with/without motion prediction (30 Hz, 2 cm fixture; 100 ms latency; 5 mm proxy), tool-shadow occlusion under architecture III with 1 vs 2 cameras, robot self-filter, fixed vs adaptive radius study (--study DIR writes table, CSV, plot); --real: the same on real depth frames moved at known speeds (penetration of proxy and robot against the true surface, estimator vs true motion)",
    "soak": "the live service at 1 kHz under every injected fault kind (faults, attacks, operator actions), each judged against SAFETY.md on its streamed recording (--minutes, default: every fault once)",
    "ros2": "the ROS 2 path on loopback: camera-node -> ros2: camera latency and dropped frames, CRTK master and arm, servo_cp round trip at 1 kHz; the loop's misses and lateness with ROS on and off in the same call",
    "replay": "how much faster than real time a recorded `serve --record` run replays (`pointfence replay --recording`): replay_x_realtime, its phases, exactness (--seconds recorded, default 20; --recording FILE.mcap)",
    "stress": "raise proxies and cameras until the 1 kHz tick (p99 <= 1 ms) or the 30 Hz ingest (p99 <= 33 ms) no longer fits",
}


def add_arguments(parser):
    sub = parser.add_subparsers(dest="bench", metavar="NAME", required=True)
    for name, help_ in BENCHES.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.add_argument("--backend", default="opencl", help="compute backend (numpy, opencl, warp); default opencl")
        p.add_argument("--device", default=None, help="device spec for the backend (e.g. 'pocl', 'nvidia')")
        p.add_argument("--json", action="store_true", help="print only the JSON result")
        p.add_argument("--repeat", type=int, default=None, help="timed repetitions (default: per benchmark)")
        importlib.import_module(f"pointfence.bench.{name}").add_arguments(p)


def run(args) -> int:
    from pointfence.bench.machine import machine_info

    mod = importlib.import_module(f"pointfence.bench.{args.bench}")
    result = mod.run(args)
    result = {"bench": args.bench, **result, "machine": machine_info()}
    text = json.dumps(result, indent=None if args.json else 2, sort_keys=False)
    print(text)
    sys.stdout.flush()
    return 0
