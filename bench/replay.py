"""`pointfence bench replay`: how much faster than real time a recorded run replays (issue 20).

Records one live run as a user makes one: ``pointfence serve --record FILE.mcap`` on ``bench e2e``'s
scene (one 160x120 synthetic camera, a Raven II arm in its robot process, architecture III, the
``--backend``), driven for ``--seconds`` by a ``pointfence device-sim --motion circle`` client,
ended by SIGTERM once the client is done. Then replays it ``--repeat`` times with ``pointfence
replay --recording FILE.mcap --out DIR``, each in a process of its own, as a user runs it.
``--recording FILE.mcap`` replays a recording of one's own instead.

Figures: ``replay_x_realtime_p50`` (and every run's ``replay_x_realtime``): the recorded run's
seconds over the replay's wall seconds, from the replay's ``summary.json`` (from opening the file
to the last output written: the interpreter's start-up and imports aside); ``phases_s``: the
median run's open / set-up / ticks / outputs seconds; ``exact``: every replay gave the recorded
TickOutputs bit for bit; the recording's seconds, size, ticks and dropped snapshots. The peer is
real time: a replay at 1x takes as long as the run.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from .stats import pct


def add_arguments(p):
    p.add_argument("--seconds", type=float, default=20.0, help="seconds the client drives the recorded run (default 20)")
    p.add_argument("--recording", default=None, help="replay this FILE.mcap instead of recording a run")
    p.add_argument("--startup-timeout", type=float, default=180.0, help="seconds to wait for the service to run")


def _record(tmp: Path, seconds: float, backend: str, device, startup_timeout: float) -> Path:
    """A recording of a live `serve` run driven by `device-sim` for ``seconds``."""
    from .e2e import LIGHT_SCENE, wait_ready

    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    key, scene, ready, rec = tmp / "pf.key", tmp / "scene.toml", tmp / "ready.json", tmp / "run.mcap"
    subprocess.run([sys.executable, "-m", "pointfence", "serve", "--new-key", str(key)], env=env, check=True,
                   capture_output=True)
    scene.write_text(LIGHT_SCENE)
    cmd = [sys.executable, "-m", "pointfence", "serve", "--key-file", str(key), "--port", "0", "--no-control",
           "--config", str(scene), "--ready-file", str(ready), "--status-every", "0", "--prerender", "30",
           "--duration", str(seconds + startup_timeout + 60), "--record", str(rec), "--backend", backend,
           "--timeout-ms", "1000"]
    if device:
        cmd += ["--device", device]
    log = open(tmp / "serve.log", "w")
    serve = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=log)
    try:
        port = wait_ready(serve, ready, tmp / "serve.log", startup_timeout)["port"]
        client = subprocess.run([sys.executable, "-m", "pointfence", "device-sim", "--key-file", str(key), "--port",
                                 str(port), "--motion", "circle", "--duration", str(seconds),
                                 # (what is measured is the replay: the client rides out a loaded machine)
                                 "--late-limit", "100000", "--timeout-ms", "1000"], env=env,
                                capture_output=True, text=True, timeout=seconds + startup_timeout)
        if client.returncode != 0:
            raise RuntimeError(f"the device-sim client failed: {client.stderr[-2000:]}")
        serve.send_signal(signal.SIGTERM)
        serve.wait(timeout=startup_timeout + 10 * seconds)   # (the run's measures are taken before it ends)
        if serve.returncode != 0:
            raise RuntimeError(f"the service ended with {serve.returncode}: {(tmp / 'serve.log').read_text()[-2000:]}")
    finally:
        if serve.poll() is None:
            serve.kill()
            serve.wait(timeout=10)
        log.close()
    return rec


def _replay(rec: Path, out: Path) -> dict:
    r = subprocess.run([sys.executable, "-m", "pointfence", "replay", "--recording", str(rec), "--out", str(out)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"pointfence replay failed: {r.stderr[-2000:]}")
    return json.loads((out / "summary.json").read_text())


def run(args) -> dict:
    repeat = args.repeat or 3
    if repeat < 1:
        raise ValueError(f"--repeat {repeat}: replay the recording at least once")
    if args.recording and not Path(args.recording).is_file():
        raise FileNotFoundError(f"--recording {args.recording!r}: no such file; give a FILE.mcap of `pointfence serve "
                                "--record`, or leave --recording out to record one")
    with tempfile.TemporaryDirectory(prefix="pointfence-bench-replay-") as t:
        tmp = Path(t)
        rec = Path(args.recording) if args.recording else _record(tmp, args.seconds, args.backend, args.device,
                                                                   args.startup_timeout)
        runs = [_replay(rec, tmp / f"out{i}") for i in range(repeat)]
        size = rec.stat().st_size
    xs = [s["replay_x_realtime"] for s in runs]
    median = sorted(range(repeat), key=lambda i: xs[i])[repeat // 2]
    r0 = runs[0]
    return {"recording": {"file": str(args.recording) if args.recording else "recorded by this bench",
                          "run_s": r0["replay_wall_s"]["run_s"], "mb": round(size / 1e6, 2), "ticks": r0["ticks"],
                          "snapshots_dropped": r0["recording"]["snapshots_dropped_while_recording"],
                          "backend": r0["backend"]},
            "replay_x_realtime_p50": round(pct(xs, 50), 2), "replay_x_realtime_min": min(xs),
            "replay_x_realtime_max": max(xs), "replay_x_realtime": xs,
            "phases_s": runs[median]["replay_wall_s"], "exact": all(s["replay"].get("exact") for s in runs),
            "mismatched_ticks": [s["replay"].get("mismatched_ticks") for s in runs]}
