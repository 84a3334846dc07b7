"""The motion estimator against the true motion of real frames (issue 23): how much of one
frame's motion the per-cell velocities predict, on real depth frames moved at known speeds
(``dynamic_real_frames``), in simulated time.

The surface moves for the whole run (``advance`` inf: the estimator is studied on steady
motion). After every snapshot the points within ``NEAR`` of the moving contact point are advanced by
their estimated velocity over one frame period and compared with the true surface one frame
later: ``static_mm`` is the median distance of the unmoved points to it (what a fixture without
prediction is off by), ``predicted_mm`` that of the predicted points (what prediction leaves),
``now_mm`` that of the points to the surface at their own time (the floor: re-projection and
1 mm depth codes). ``estimated`` is the share of those points with a velocity, ``measured`` the
share whose motion cell was measured, ``propagated`` the share whose cell took its measured
neighbours' velocity (``MotionEstimator.confidence_of``); ``cells``: the medians of the
estimator's whole-snapshot counts (``MotionEstimator.summary``: cells measured, propagated,
unknown, and why not measured).
"""
from __future__ import annotations

import math

import numpy as np

from pointfence.kernels.motion import CELL_MEASURED, CELL_PROPAGATED, MotionModel

from .dynamic_real import RATE_HZ, real_surface, run_case
from .dynamic_real_frames import MOTIONS, Motion

#: radius (m) around the moving contact point whose points are studied
NEAR = 0.04


def estimator_run(surface, kind: str, speed: float, *, backend: str = "opencl", device: str | None = None,
                  model: MotionModel | None = None) -> dict:
    """One run (toward: master holding; else pushing) with the study's probe; medians over the
    snapshots of the run (after the first estimate), distances in mm."""
    a = surface.anchor()
    motion = Motion(kind, speed, tuple(a))
    rows, summaries = [], []
    dt = 1.0 / RATE_HZ

    def probe(hs, t):
        snap = hs.pipeline.host_snapshot()
        if snap.velocity is None or snap.vmax <= 0:
            return
        p = snap.points[:, :3].astype(np.float64)
        R, c = motion.pose(t)
        near = np.linalg.norm(p - (R @ a + c), axis=1) < NEAR
        if not near.any():
            return
        pn, ve = p[near], snap.velocity[near].astype(np.float64)
        state = hs.pipeline.motion.confidence_of(snap.cell_of()[near])
        summaries.append(hs.pipeline.motion.summary())
        rows.append((np.mean(np.linalg.norm(ve, axis=1) > 0), np.mean(state == CELL_MEASURED),
                     np.mean(state == CELL_PROPAGATED),
                     np.median(np.abs(surface.distance(motion, pn, t))),
                     np.median(np.abs(surface.distance(motion, pn, t + dt))),
                     np.median(np.abs(surface.distance(motion, pn + ve * dt, t + dt)))))

    model = model if model is not None else MotionModel(enabled=True)
    run_case(surface, motion, speed, True, r_f=0.01, master="hold" if kind == "toward" else "push",
             backend=backend, device=device, model=model, probe=probe, advance=math.inf)
    if not rows:
        return {"snapshots": 0}
    m = np.median(np.asarray(rows), axis=0)
    return {"snapshots": len(rows), "estimated": round(float(m[0]), 3), "measured": round(float(m[1]), 3),
            "propagated": round(float(m[2]), 3), "now_mm": round(float(m[3]) * 1e3, 2),
            "static_mm": round(float(m[4]) * 1e3, 2), "predicted_mm": round(float(m[5]) * 1e3, 2),
            "cells": {k: int(np.median([s[k] for s in summaries]))
                      for k in summaries[0] if k.startswith(("cells_", "rejected_"))}}


def estimator_table(scenes, *, speeds=(0.1, 0.3), motions=MOTIONS, **options) -> list:
    """``estimator_run`` rows for every scene x motion x speed."""
    out = []
    for name in scenes:
        surface = real_surface(name)
        for kind in motions:
            for v in speeds:
                out.append({"scene": surface.name, "motion": kind, "speed_mps": v,
                            **estimator_run(surface, kind, v, **options)})
    return out
