"""The dissertation's measures (6.1) of a recorded run, from its recorded depth: what
``serve --record`` prints and stores at the end of a run and ``pointfence inspect`` shows.

No analytic scene is needed, so a live run with real cameras is measured as a synthetic one.
Every snapshot a tick used (``TickOutput.frame_seq``) is rebuilt offline from the recorded
depth frames (``Recording.snapshots``: the frames after the robot self-filter) by a backend's
own frame pipeline with the recorded configuration (workspace, selection, fixture radius,
adaptive radii), and each tick is measured against that snapshot's protected points
(``recorded_surface.RecordedSurface``: the signed distance d(X), m, negative inside the
forbidden region). For arm b at tick k (all positions world frame, m):

* X_r = ``TickOutput.robot_pos`` (the measured tool tip; an ideal robot's command),
  X_r* = ``TickOutput.command``, X_m = ``TickOutput.xm`` (the mapped master point);
* **safety** (``safety_max_penetration_m``, m): max(0, -min_k d(X_r)) over every measured tick,
  coupled or not: how deep the robot tip got into the forbidden region;
* **submittance** (``submittance_min_distance_m``, m): min d(X_r) over the coupled ticks where the
  master is inside the region (d(X_m) < 0) and the robot is not (d(X_r) >= 0): how close the
  robot came while held off; None if it never was;
* **tracking** (``tracking_rms_m``, m): sqrt(mean |X_r - X_r*|^2) over the coupled ticks with the
  master outside the region (d(X_m) >= 0); ``tracking_master_rms_m`` the same of |X_r - X_m|;
* ``min_robot_distance_m``: min d(X_r) (None: farther than ``recorded_surface.REACH_M``);
  ``ticks_inside``: ticks with d(X_r) < 0 (``time_inside_s`` at the recorded rate).

"Coupled" is ``TickOutput.coupled`` (the master drives the robot on that tick). The run's values
are the worst over its arms (max safety and tracking, min submittance). Not seen by the measures:
changes made through the control API while running (a new radius or selection; the recording
holds the configuration the run started with) and ticks before the first snapshot.

The result is stored in the recording itself, as MCAP metadata named ``METADATA`` (each value
JSON text): ``before_close`` runs at the end of a run while the recording is still open, after
the recorder's flush barrier (``McapRecorder.seal``: every tick and frame on disk), measures the
file as it is then and adds the record before the recorder closes it. Where that cannot be done
(the writer process gone, a recording from a crash, an older file) ``after_run`` measures the
closed file and keeps the result beside it (``sidecar_path``: ``FILE.mcap.measures.json``, tied to
the recording's size); ``stored`` finds either, the file's record first.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import numpy as np

from pointfence.kernels.backend import run_steps
from pointfence.kernels.errors import InputError, PointfenceError

from . import measures
from .recorded_frames import FrameDecoder
from .recorded_surface import RecordedSurface
from .ros2_schemas import robot_ns

#: name of the MCAP metadata record (and of the sidecar's key) holding the measures
METADATA = "pointfence/measures"
#: the measures every arm and the run report (m)
KEYS = ("safety_max_penetration_m", "submittance_min_distance_m", "tracking_rms_m", "tracking_master_rms_m",
        "min_robot_distance_m")


class Evaluation:
    """What ``evaluate`` found: ``summary`` (JSON-ready dict, see the module docstring),
    ``traces`` (per arm: t (s), xr, cmd, xm, proxy (N, 3) m, force (N, 3) N, d_r, d_m (N,) m
    over the measured ticks) and ``last_surface`` (the last rebuilt snapshot's region)."""

    def __init__(self, summary: dict, traces: list, last_surface: Optional[RecordedSurface]):
        self.summary, self.traces, self.last_surface = summary, traces, last_surface


def _col(rec, part: str, name: str) -> np.ndarray:
    c, k = rec.layout.cols[(part, name)]
    return rec.rows[:, c: c + k]


def evaluate(rec, backend: Optional[str] = None, device: Optional[str] = None, progress=None) -> Evaluation:
    """Measure recording ``rec`` (``mcap_read.Recording``) on ``backend`` (default: the recorded
    run's; ``numpy`` is the reference). ``progress(done, total)`` is called after each snapshot.
    Raises InputError if the recording holds no configuration or cameras to rebuild from."""
    from pointfence.kernels import get_backend

    from .mcap_replay import recording_config

    cfg = recording_config(rec)
    meta = rec.meta
    name = backend or meta.get("backend") or "numpy"
    be = get_backend(name, device or (None if backend else meta.get("device_spec")))
    pipe = be.pipeline([c.camera for c in cfg.cameras], cfg.pipeline)
    n, rate = rec.layout.n, float(meta.get("rate_hz", 1000.0))
    rows = len(rec.rows)
    seqs = _col(rec, "out", "frame_seq")[:, 0].astype(np.int64) if rows else np.zeros(0, np.int64)
    t = _col(rec, "in", "t")[:, 0] if rows else np.zeros(0)
    k = _col(rec, "in", "k")[:, 0].astype(np.int64) if rows else np.zeros(0, np.int64)
    xr, cmd, xm = (_col(rec, "out", f).reshape(rows, n, 3) for f in ("robot_pos", "command", "xm"))
    coupled = _col(rec, "out", "coupled").astype(bool)
    d_r, d_m = np.full((rows, n), np.nan), np.full((rows, n), np.nan)
    wanted = [int(s) for s in np.unique(seqs) if s > 0]
    missing, built, last = [], 0, None
    # The snapshots are built one after the other (motion estimates carry over), each while the
    # ticks of the one before it are measured: a build's device work is submitted
    # (``ingest_steps``) before the measuring and finished after it; the PNGs decode ahead in
    # threads of their own.
    decoder = FrameDecoder(rec, {i: [seq] for i, seq in enumerate(wanted)})
    nxt = (None, None)
    try:
        nxt = _start(pipe, decoder, rec, wanted, 0)
        for i, seq in enumerate(wanted):
            frames, steps = nxt
            if frames is None:
                missing.append(seq)
                nxt = _start(pipe, decoder, rec, wanted, i + 1)
                continue
            run_steps(steps)
            snapshot = pipe.host_snapshot()
            nxt = _start(pipe, decoder, rec, wanted, i + 1)
            last = RecordedSurface(snapshot, pipe.rig.cameras, pipe.rig.order(frames), pipe.rig.offsets)
            built += 1
            sel = np.flatnonzero(seqs == seq)
            both = np.concatenate([xr[sel].reshape(-1, 3), xm[sel].reshape(-1, 3)])
            d = last.signed_distance(both)
            d_r[sel], d_m[sel] = d[: len(sel) * n].reshape(-1, n), d[len(sel) * n:].reshape(-1, n)
            if progress is not None:
                progress(i + 1, len(wanted))
    finally:
        if nxt[1] is not None:
            nxt[1].close()
        decoder.close()
    arms, traces = [], []
    for b in range(n):
        ok = np.isfinite(xr[:, b]).all(axis=1) & ~np.isnan(d_r[:, b])
        err_cmd = np.linalg.norm(xr[ok, b] - cmd[ok, b], axis=1)
        err_m = np.linalg.norm(xr[ok, b] - xm[ok, b], axis=1)
        m = measures.summarise(d_r[ok, b], d_m[ok, b], err_cmd, err_m, coupled[ok, b])
        inside = d_r[ok, b] < 0
        worst = None
        if m["safety_max_penetration_m"]:
            j = np.flatnonzero(ok)[int(np.argmin(d_r[ok, b]))]
            worst = {"tick": int(k[j]), "t_s": round(float(t[j]), 4)}
        arms.append({"arm": b, "robot": robot_ns(b), **m, "ticks_measured": int(ok.sum()),
                     "ticks_coupled": int(coupled[ok, b].sum()), "ticks_inside": int(inside.sum()),
                     "time_inside_s": round(float(inside.sum()) / rate, 4), "deepest": worst})
        traces.append({"t": t[ok], "xr": xr[ok, b], "cmd": cmd[ok, b], "xm": xm[ok, b], "d_r": d_r[ok, b],
                       "d_m": d_m[ok, b], "proxy": _col(rec, "out", "proxy").reshape(rows, n, 3)[ok, b],
                       "force": _col(rec, "out", "force").reshape(rows, n, 3)[ok, b],
                       "radius": float(cfg.pipeline.radius.r_base)})
    summary = {"from": "recorded depth", "backend": be.name, "ticks": rows,
               "ticks_measured": int(max((a["ticks_measured"] for a in arms), default=0)),
               "snapshots_rebuilt": built, "snapshots_missing": missing, **_worst(arms), "arms": arms}
    return Evaluation(summary, traces, last)


def _start(pipe, decoder, rec, wanted: list, i: int) -> tuple:
    """(frames, the started build's steps) of snapshot ``wanted[i]``; (None, None) past the end
    or where a frame of it is not in the file (dropped while recording, or past a torn end)."""
    if i >= len(wanted):
        return None, None
    entry = rec.snapshots.get(wanted[i])
    if entry is None:
        return None, None
    fseqs, findex, stamps, poses = entry
    try:
        frames = [decoder.get(c, idx, fseq, stamps[c], poses[16 * c: 16 * c + 16])
                  for c, (fseq, idx) in enumerate(zip(fseqs, findex))]
    except InputError:
        return None, None
    steps = pipe.ingest_steps(frames)
    next(steps)                     # (the build's device work submitted: see ``evaluate``)
    return frames, steps


def _worst(arms: list) -> dict:
    """The run's measures: max safety and tracking, min submittance and distance, over arms."""
    def pick(key, fn):
        vals = [a[key] for a in arms if a.get(key) is not None]
        return fn(vals) if vals else None

    return {"safety_max_penetration_m": pick("safety_max_penetration_m", max),
            "submittance_min_distance_m": pick("submittance_min_distance_m", min),
            "tracking_rms_m": pick("tracking_rms_m", max), "tracking_master_rms_m": pick("tracking_master_rms_m", max),
            "min_robot_distance_m": pick("min_robot_distance_m", min)}


# --- storing and finding them ------------------------------------------------------------------------
def sidecar_path(path) -> Path:
    """The JSON file beside recording ``path`` that holds its measures: ``FILE.mcap.measures.json``."""
    p = Path(path)
    return p.with_name(p.name + ".measures.json")


def store(path, summary: dict, recorder=None) -> str:
    """Keep ``summary`` with the recording at ``path``: in the file through ``recorder.add_metadata``
    where a still-open recorder offers it, else in ``sidecar_path(path)`` (with the recording's
    size, so a sidecar of another file of that name is not believed). Returns where it went."""
    if recorder is not None and hasattr(recorder, "add_metadata"):
        recorder.add_metadata(METADATA, measures.json_safe(summary))   # (each value stored as its JSON)
        return str(path)
    from .files import write_atomic

    side = sidecar_path(path)
    doc = {"recording": Path(path).name, "recording_bytes": Path(path).stat().st_size, METADATA: measures.json_safe(summary)}
    write_atomic(side, json.dumps(doc, indent=2) + "\n", keep_backups=False)
    return str(side)


def stored(path, metadata: dict) -> Optional[tuple]:
    """(summary, where) of measures kept with recording ``path``: the file's ``METADATA`` record
    (``metadata``: name -> values of its metadata records), else a sidecar written for a file of
    this size; None if neither."""
    if isinstance(metadata.get(METADATA), dict):     # (mcap_read decodes each value's JSON)
        return dict(metadata[METADATA]), "recording"
    side = sidecar_path(path)
    if side.is_file():
        try:
            doc = json.loads(side.read_text())
        except (OSError, ValueError):
            return None
        if doc.get("recording_bytes") == Path(path).stat().st_size and isinstance(doc.get(METADATA), dict):
            return doc[METADATA], str(side)
    return None


def before_close(path, recorder, log=None) -> Optional[dict]:
    """Measure the run recorded at ``path`` by ``recorder`` (an open ``McapRecorder``; call after
    the run's last tick, before ``recorder.close()``) and store the measures in the recording
    (``METADATA``). Returns them (``stored_in``: the recording), {"error": why} if the recording
    cannot be measured, or None where the recorder could not flush everything first (its writer
    gone): measure the closed file with ``after_run`` then. ``log(text)`` as for ``after_run``."""
    seal = getattr(recorder, "seal", None)
    if seal is None or not seal():
        return None
    return _measure(path, log, recorder)


def after_run(path, log=None) -> dict:
    """Measure the recording a run just finished (``serve --record``) once it is closed, store the
    measures (``store``: beside the file) and return them (with ``stored_in``); a recording that
    cannot be measured gives {"error": why}. ``log(text)`` gets a line when it starts and when it
    is done."""
    return _measure(path, log, None)


def _measure(path, log, recorder) -> dict:
    from .mcap_read import open_recording

    t0 = time.monotonic()
    try:
        rec = open_recording(path)
        if log is not None:
            log(f"measuring {path} from its recorded depth ({len(rec.snapshots)} snapshots, {len(rec.rows)} ticks)")
        summary = evaluate(rec).summary
        summary["stored_in"] = store(path, summary, recorder)
    except (PointfenceError, OSError) as e:      # the run's own status is still printed
        return {"error": str(e)}
    if log is not None:
        log(f"measures done in {time.monotonic() - t0:.1f} s: {line(summary)}")
    return summary


def line(summary: dict) -> str:
    """One line of the run's measures, in mm."""
    def mm(key):
        v = summary.get(key)
        return "-" if v is None else f"{v * 1000:.2f} mm"

    return (f"safety (max penetration) {mm('safety_max_penetration_m')}, submittance (closest held off) "
            f"{mm('submittance_min_distance_m')}, tracking (rms |X_r - X_r*|) {mm('tracking_rms_m')}")


__all__ = ["evaluate", "Evaluation", "store", "stored", "before_close", "after_run", "line", "sidecar_path",
           "METADATA", "KEYS"]
