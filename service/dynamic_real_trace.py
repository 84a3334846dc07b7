"""Where a fixture's penetration comes from, tick by tick (issue 23): one run of
``dynamic_real.run_case`` recorded at every tick, its penetration split into three exact terms.

At tick t the proxy X_p rests against the snapshot's points as the kernel sees them (taken at
t_s, each moved by its estimated velocity over the tick's prediction time dt, ``kernels/motion.py``).
With d the proxy's signed distance to the true surface at t (m), the penetration r_f - d is
exactly the sum of

* ``sampling``: c_true - d, c_true the distance from X_p to the nearest snapshot point moved
  by the TRUE motion from t_s to t. What a perfect predictor would still leave: the cloud
  itself sits behind the true surface where X_p touches it (depth noise, depth codes, the gap
  between the pixels' samples that a sphere sinks into). No causal estimator removes it;
* ``prediction``: c_pred - c_true, c_pred the distance to the nearest point as predicted
  (without prediction: where the snapshot left it). How far the predicted cloud lags the
  truly moved one at X_p (> 0) or runs ahead of it (< 0);
* ``overlap``: r_f - c_pred, how far X_p is inside the fixture of the predicted cloud (the
  kernel's ``slack`` while sliding, and where the scene moved into the proxy).

Everything is in the camera frame, distances in m (the reports in mm), times in s on the
frames' clock; the per-tick arrays are those the issue asks for: frame time, dt, the HIP, the
proxy and the robot, the estimated and the true velocity of the point the proxy rests on.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .dynamic_real import TickView, run_case

#: per-tick fields of a ``Trace`` (arrays of n ticks; positions and velocities (n, 3))
FIELDS = ("t", "t_snapshot", "dt", "hip", "proxy", "robot", "proxy_mm", "robot_mm", "sampling_mm",
          "prediction_mm", "overlap_mm", "v_est", "v_true")


@dataclass
class Trace:
    """A recorded run: the ``RealRun`` and one array per name in ``FIELDS`` (see the module
    docstring; penetrations and their terms in mm, > 0 inside the forbidden region)."""

    run: object
    ticks: dict = field(default_factory=dict)

    def __getattr__(self, name):
        try:
            return self.__dict__["ticks"][name]
        except KeyError:
            raise AttributeError(name) from None

    def worst(self, of: str = "proxy_mm") -> dict:
        """The tick of the largest ``of`` (``proxy_mm`` or ``robot_mm``): its time, frame time,
        dt, age of the frame (ms), and the proxy's penetration with its three terms (mm)."""
        i = int(np.argmax(self.ticks[of]))
        return {"tick": i, "t_s": round(float(self.t[i]), 4), "frame_t_s": round(float(self.t_snapshot[i]), 4),
                "dt_ms": round(float(self.dt[i]) * 1e3, 2),
                "frame_age_ms": round(float(self.t[i] - self.t_snapshot[i]) * 1e3, 2),
                of: round(float(self.ticks[of][i]), 3),
                **{k: round(float(self.ticks[k][i]), 3) for k in ("proxy_mm", "sampling_mm", "prediction_mm",
                                                                  "overlap_mm")}}

    def contact(self, within_mm: float = 1.0) -> dict:
        """Over the frames in which the proxy came within ``within_mm`` of the fixture's
        boundary: their number, and the median and the largest of their per-frame maxima of
        each term (mm). The worst tick of a run is the largest of a few per-frame draws: a run
        with more frames in contact (a slower surface over the same stroke) draws more."""
        fr = [f for f in self.frames() if f["proxy_mm_max"] > -within_mm]
        out = {"frames": len(fr)}
        for k in ("proxy_mm", "sampling_mm", "prediction_mm"):
            v = np.array([f[f"{k}_max"] for f in fr]) if fr else np.zeros(1)
            out[f"{k}_median"], out[f"{k}_max"] = round(float(np.median(v)), 3), round(float(v.max()), 3)
        return out

    def frames(self) -> list:
        """Per snapshot (frame time): its ticks, the proxy's penetration at its first tick and
        its largest, and the largest of each term and of the robot's penetration (mm)."""
        out = []
        for ts in np.unique(self.t_snapshot):
            m = self.t_snapshot == ts
            first = int(np.flatnonzero(m)[0])
            out.append({"frame_t_s": round(float(ts), 4), "ticks": int(m.sum()),
                        "proxy_mm_first": round(float(self.proxy_mm[first]), 3),
                        **{f"{k}_max": round(float(self.ticks[k][m].max()), 3)
                           for k in ("proxy_mm", "robot_mm", "sampling_mm", "prediction_mm", "overlap_mm")}})
        return out


def trace_case(surface, motion, speed: float, predict: bool = True, **options) -> Trace:
    """``run_case(surface, motion, speed, predict, **options)`` with every tick recorded (see
    the module docstring). ``options``: run_case's keywords (r_f, master, slip_lift, model,
    backend, ...; not probe nor on_tick)."""
    snap = {}
    rows = {k: [] for k in FIELDS}

    def probe(hs, t):
        s = hs.pipeline.host_snapshot()
        p = s.points[:, :3].astype(np.float64)
        v = s.velocity.astype(np.float64) if s.velocity is not None and s.vmax > 0 else np.zeros_like(p)
        from scipy.spatial import cKDTree

        snap.update(time=float(s.time), points=p, velocity=v, tree=cKDTree(p),
                    vmax=float(np.max(np.linalg.norm(v, axis=1), initial=0.0)))

    def on_tick(view: TickView):
        p, v, ts, tree = snap["points"], snap["velocity"], snap["time"], snap["tree"]
        dt = float(view.scene.batch.last_dt)
        g = view.proxy
        # the true motion is rigid: the distance to the truly moved cloud is that of the proxy
        # carried back to the snapshot's time to the snapshot as it is
        c_true = float(tree.query(view.carry(g, view.t, ts)[0])[0])
        # a predicted point p + v dt within c of g has |p - g| <= c + vmax dt, and the nearest
        # static point, predicted, is within c_static + vmax dt: the candidates are exact
        reach = float(tree.query(g)[0]) + 2.0 * snap["vmax"] * dt + 1e-9
        near = np.asarray(tree.query_ball_point(g, reach), np.int64)
        dist_pred = np.linalg.norm(p[near] + v[near] * dt - g, axis=1)
        j = int(np.argmin(dist_pred))
        i = int(near[j])
        c_pred = float(dist_pred[j])
        h = 1e-3
        at = view.carry(p[i:i + 1], ts, view.t)
        rows["t"].append(view.t)
        rows["t_snapshot"].append(ts)
        rows["dt"].append(dt)
        rows["hip"].append(view.hip)
        rows["proxy"].append(g)
        rows["robot"].append(view.robot)
        rows["proxy_mm"].append((view.r_f - view.d_proxy) * 1e3)
        rows["robot_mm"].append((view.r_f - view.d_robot) * 1e3)
        rows["sampling_mm"].append((c_true - view.d_proxy) * 1e3)
        rows["prediction_mm"].append((c_pred - c_true) * 1e3)
        rows["overlap_mm"].append((view.r_f - c_pred) * 1e3)
        rows["v_est"].append(v[i])
        rows["v_true"].append(((view.carry(at, view.t, view.t + h) - at) / h)[0])

    for key in ("probe", "on_tick"):
        if key in options:
            raise TypeError(f"trace_case: {key} is the trace's own")
    run = run_case(surface, motion, speed, predict, probe=probe, on_tick=on_tick, **options)
    return Trace(run, {k: np.asarray(v, np.float64) for k, v in rows.items()})


def floor_table(scenes, *, speeds=(0.1, 0.3), masters=("hold", "push"), r_f: float = 0.01, synthetic: bool = True,
                backend: str = "opencl", device: str | None = None) -> list:
    """Per scene (names or paths of recordings, ``dynamic_real.real_surface``; with
    ``synthetic`` the synthetic plane too) x master x speed, the surface moving toward the
    camera, with prediction: the proxy's and the robot's largest penetration (mm), the worst
    tick's terms (``Trace.worst``) and, over the frames the proxy touched, the median and the
    largest per-frame maximum of each term (``Trace.contact``)."""
    from .dynamic_real import _PlaneSurface, real_surface
    from .dynamic_real_frames import Motion

    targets = [(real_surface(s), True) for s in scenes] + ([(None, False)] if synthetic else [])
    out = []
    for surf, real in targets:
        for master in masters:
            for v in speeds:
                s = surf if real else _PlaneSurface(v)
                motion = Motion("toward", v, tuple(s.anchor())) if real else None
                tr = trace_case(s, motion, v, True, r_f=r_f, master=master, backend=backend, device=device)
                out.append({"scene": s.name, "master": master, "speed_mps": v, "r_f_mm": round(r_f * 1e3, 1),
                            "proxy_mm": round(tr.run.proxy_penetration * 1e3, 2),
                            "robot_mm": round(tr.run.robot_penetration * 1e3, 2),
                            "worst": tr.worst("proxy_mm"), "contact": tr.contact()})
    return out
