"""`pointfence demo --viewer` / `--viewer-save FILE.rrd`: the demo's experiments in a rerun viewer.

Logging happens after each experiment (a live viewer fills in run by run), from what the run
already recorded (its ``Recorder``) and the scene snapshot its pipeline holds at the end;
nothing is logged from the 1 kHz haptic tick, which does no I/O. Needs the optional ``rerun-sdk`` package (``pip install
'pointfence[viewer]'``; the API used here is rerun-sdk 0.23 or later).

Frame and units: the world (robot base) frame, z up, metres; forces in newtons. Timeline
``loop_time``: seconds of loop time (the recorder's ``t``), the tick streams decimated to
``rate_hz`` (100 Hz by default). Recorded streams are of arm 0 (the demo has one arm). Every
experiment logs under its own prefix ``demo/<scene>_<arch>/`` (e.g. ``demo/balloon_III/``):

* ``cloud/protected``, ``cloud/other``: the end-of-experiment snapshot (``host_snapshot()``),
  protected points (those carrying a forbidden-region sphere) red, the rest grey; static
  (shown at every time; on a moving scene it is the scene as it was at the end).
* ``proxy``: the proxy centre, a sphere of the proxy radius r1, coloured by its state (free
  green, contact orange, entrenched red).
* ``hip``: the haptic interaction point; ``master``: the master position mapped to the world.
* ``force``: the force rendered at the HIP, in the world frame (the master receives it rotated
  into its own frame), as an arrow from the HIP, ``FORCE_SCALE`` m per N (1 N draws 1 cm);
  ``force_N``: its magnitude in N, a plot.
* ``robot/tool``, ``robot/command``: the measured tool position X_r and the command X_r*;
  ``robot/path``: the measured tool path of the whole run as one line strip (static).
* ``summary``: the run's 6.1 measures as text (static).
"""
from __future__ import annotations

import sys
from inspect import signature
from pathlib import Path
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError, PointfenceError

#: arrow length per newton of force, m/N (1 N -> 1 cm)
FORCE_SCALE = 0.01
TIMELINE = "loop_time"
PROTECTED_RGB = (220, 40, 40)
OTHER_RGB = (150, 150, 150)
STATE_RGB = np.array([(40, 180, 60), (240, 150, 20), (220, 30, 30)], np.uint8)   # free, contact, entrenched
POINT_RADIUS = 0.001   # m, drawn size of cloud points and path markers
MEASURES = (("safety_max_penetration_m", "safety (max penetration)"),
            ("submittance_min_distance_m", "submittance (closest approach held off)"),
            ("tracking_rms_m", "tracking (r.m.s. |X_r - X_r*|)"))
INSTALL = "pip install 'pointfence[viewer]'"


class ViewerUnavailable(PointfenceError, RuntimeError):
    """The rerun viewer was asked for but rerun-sdk cannot be imported."""


def import_rerun():
    """``rerun`` (rerun-sdk), or a ``ViewerUnavailable`` that says what to install."""
    try:
        import rerun as rr
    except ImportError as e:
        raise ViewerUnavailable(f"--viewer and --viewer-save need the rerun-sdk package, which is not importable "
                                f"here ({e}); install it with: {INSTALL}") from e
    return rr


def add_arguments(p) -> None:
    p.add_argument("--viewer", nargs="?", const="spawn", default=None, metavar="URL",
                   help="stream every experiment (points, proxy, HIP, forces, robot path) to a rerun viewer: spawn "
                        "one, or connect to URL (e.g. rerun+http://127.0.0.1:9876/proxy); needs " + INSTALL)
    p.add_argument("--viewer-save", default=None, metavar="FILE.rrd",
                   help="write the same to a rerun recording file (headless; open it with `rerun FILE.rrd`)")


def from_args(args) -> Optional["Viewer"]:
    """A ``Viewer`` for the ``--viewer`` / ``--viewer-save`` options, or None when neither is given."""
    target, save = getattr(args, "viewer", None), getattr(args, "viewer_save", None)
    if target is None and not save:
        return None
    return Viewer(spawn=target == "spawn", connect=None if target in (None, "spawn") else target, save=save)


class Viewer:
    """One rerun recording for a demo: ``log_run`` after each experiment, ``close`` at the end.

    Args:
        spawn: start a viewer process and stream to it.
        connect: stream to the viewer at this gRPC URL instead.
        save: also (or only) write the recording to this .rrd file.
        rate_hz: rate of the logged tick streams (the loop's ticks decimated to it), Hz.
    """

    def __init__(self, *, spawn: bool = False, connect: Optional[str] = None, save=None, rate_hz: float = 100.0,
                 application_id: str = "pointfence_demo"):
        if not (spawn or connect or save):
            raise InputError("Viewer: nothing to stream to; give spawn=True, connect=URL or save=FILE.rrd")
        if not rate_hz > 0:
            raise InputError(f"Viewer rate_hz = {rate_hz!r}; expected a positive rate in Hz (e.g. 100)")
        self.rr = rr = import_rerun()
        self.rate_hz = float(rate_hz)
        self.save = Path(save) if save else None
        self.rec = rr.RecordingStream(application_id)
        sinks = []
        if spawn:
            # the venv's viewer even when the venv's bin folder is not on PATH
            exe = Path(sys.executable).with_name("rerun")
            use = exe.exists() and "executable_path" in signature(rr.spawn).parameters
            kw = {"executable_path": str(exe)} if use else {}
            rr.spawn(connect=False, recording=self.rec, **kw)
            sinks.append(rr.GrpcSink())
        elif connect:
            sinks.append(rr.GrpcSink(connect))
        if self.save is not None:
            self.save.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(self.save)))
        self.rec.set_sinks(*sinks)
        self.rec.log("demo", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.runs: list = []

    def log_run(self, name: str, svc, summary: Optional[dict] = None) -> dict:
        """Log one finished experiment under ``demo/<name>/`` from ``svc`` (its recorder and its
        pipeline's current snapshot); return what was logged (entity -> rows or points)."""
        rr, rec, pre = self.rr, self.rec, f"demo/{name}"
        if pre in self.runs:
            raise InputError(f"viewer: experiment {name!r} already logged; give each run its own name")
        self.runs.append(pre)
        out = {}
        snap = svc.pipeline.host_snapshot()
        pts = np.asarray(snap.points[:, :3], np.float32)
        prot = np.asarray(snap.protected, bool)
        for part, sel, rgb in (("protected", prot, PROTECTED_RGB), ("other", ~prot, OTHER_RGB)):
            rec.log(f"{pre}/cloud/{part}", rr.Points3D(pts[sel], colors=rgb, radii=POINT_RADIUS), static=True)
            out[f"cloud/{part}"] = int(sel.sum())
        if summary:
            lines = [f"- architecture: {summary.get('architecture')}"]
            for key, label in MEASURES:
                v = summary.get(key)
                lines.append(f"- {label}: " + ("-" if v is None else f"{v * 1000:.2f} mm"))
            text = "\n".join(lines + [f"- frames: {summary.get('frames')}"])
            rec.log(f"{pre}/summary", rr.TextDocument(text, media_type="text/markdown"), static=True)
        r = svc.recorder
        if r is None or r.count == 0:
            return out
        every = max(1, int(round(svc.rate_hz / self.rate_hz)))
        a = r.arrays()       # in tick order (a streamed recording: read back from its file)
        rows = a["rows"][::every]
        n = rows.shape[0]
        times = [rr.TimeColumn(TIMELINE, duration=rows[:, 0])]
        hip, proxy, force = rows[:, 4:7], rows[:, 7:10], rows[:, 16:19]
        state = np.clip(rows[:, 19].astype(int), 0, 2)
        xr, cmd = a["robots"][::every, 0, :3], a["robots"][::every, 0, 3:]
        xm = a["masters_world"][::every, 0]
        r1 = float(svc.params.r1)
        streams = {
            "proxy": rr.Points3D.columns(positions=proxy, radii=np.full(n, r1), colors=STATE_RGB[state]),
            "hip": rr.Points3D.columns(positions=hip, radii=np.full(n, POINT_RADIUS * 2)),
            "master": rr.Points3D.columns(positions=xm, radii=np.full(n, POINT_RADIUS * 2)),
            "force": rr.Arrows3D.columns(origins=hip, vectors=force * FORCE_SCALE),
            "force_N": rr.Scalars.columns(scalars=np.linalg.norm(force, axis=1)),
            "robot/tool": rr.Points3D.columns(positions=xr, radii=np.full(n, POINT_RADIUS * 3)),
            "robot/command": rr.Points3D.columns(positions=cmd, radii=np.full(n, POINT_RADIUS * 2)),
        }
        for entity, cols in streams.items():
            rec.send_columns(f"{pre}/{entity}", indexes=times, columns=cols)
            out[entity] = n
        rec.log(f"{pre}/robot/path", rr.LineStrips3D([xr], radii=POINT_RADIUS / 2), static=True)
        out["robot/path"] = n
        return out

    def close(self, check: bool = True) -> None:
        """Flush everything to the sinks (the .rrd file is complete after this) and disconnect.
        With ``check``, a sink that could not take the data (no viewer at the URL) is an error."""
        try:
            self.rec.flush()
        except RuntimeError as e:
            if check:
                raise ViewerUnavailable(f"the rerun viewer did not take the recording ({e}); start one with `rerun` "
                                        "and give its URL to --viewer, use --viewer alone to spawn one, or write a "
                                        "file with --viewer-save FILE.rrd") from e
        finally:
            self.rec.disconnect()
