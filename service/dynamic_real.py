"""Motion prediction on real depth frames (dissertation ch. 6, issue 23), in simulated time.

A real frame is moved at a known speed (``dynamic_real_frames``: toward the camera, sideways,
rocking), seen at 30 Hz, while a fixture proxy (architecture III: the HIP is the master, the
robot follows the proxy) is held against it at 1 kHz:

* ``hold``: the master holds still ``r_f + 1 cm`` in front of the surface's start; the surface
  then advances r_f + 2 cm (the issue's 3 cm stroke for the 1 cm fixture), pushing the proxy
  1 cm back past the master, and stops there; the run lasts at least 4 frames and goes on for
  ``AFTER_STOP`` (4 frames) after the stop, so prediction is tried over several frames and over
  the stop at every speed. A surface that kept moving for 4 frames at
  1 m/s would push the proxy 11 cm back, and a real surface slanted to the motion carries it
  that far across the scene (4.5 cm on apc's bin floor), into the occlusion shadow of a
  foreground object, where no camera sees the surface: that is the occlusion problem (a second
  camera), not prediction (true velocities give the same pop), so the hold stroke is bounded;
* ``push``: the master pushes 2 cm into the surface and follows the point it pushes (a
  surgeon pressing on a moving organ): the proxy rides the moving fixture's boundary.

The robot is a point mass on the service's architecture-III command (``Teleop``, the compiled
core's arithmetic): the proxy as its goal, raised along the proxy's normal by the slip lift
(``[teleop] slip_lift``, on by default) while the command trails a proxy that slides away from
it, rate-limited to ``ROBOT_SPEED``. At every tick the
proxy's and the robot's penetration of the forbidden region (r_f around the true surface at
that tick's exact time) is measured against it: r_f - d, d the exact signed distance to the
triangulated real surface (``dynamic_real_frames``, ``depth_mesh``). The same loop runs the
synthetic translating plane of ``dynamic_scenes`` (analytic distance) so both sit in one table.

Time: tick k at t0 + k / 1000 s; frame seq captured at seq / 30 s and ingested, stamped with
its capture time, at the first tick at or after it (no latency: ``MotionModel.latency`` = 0).
No wall clock anywhere: the figures do not depend on the machine.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pointfence.kernels import DepthFrame, PipelineParams, RadiusModel, Workspace
from pointfence.kernels.errors import InputError
from pointfence.kernels.haptics import HapticParams, HapticScene, haptic_pipeline_params
from pointfence.kernels.motion import MotionModel

from .dynamic_real_frames import Motion, MovingRealFrame, load_real
from .teleop import Teleop

RATE_HZ = 30.0
TICK_HZ = 1000.0
ROBOT_SPEED = 0.5  # m/s, the point-mass robot's rate limit
#: how long (s) a hold run goes on after the surface stops: 4 frames, whatever the speed
AFTER_STOP = 4 / RATE_HZ
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
#: the real recordings the evaluation uses by default (../shared/data)
REAL_SCENES = ("apc_shelfbin_50f", "7scenes_kitchen_50f")
SPEEDS = (0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 1.5)
QUICK_SPEEDS = (0.1, 0.3)
RADII = (0.01, 0.02)
#: (motion, master) cases of the sweep
CASES = (("toward", "hold"), ("toward", "push"), ("sideways", "push"), ("rocking", "push"))


@dataclass
class RealRun:
    """Outcome of one run: max penetrations of the forbidden region (m), and of its surface."""

    proxy_penetration: float
    robot_penetration: float
    proxy_popped: bool      # the proxy centre went behind the true surface
    ticks: int
    frames: int


class _PlaneSurface:
    """The synthetic translating plane of ``dynamic_scenes`` (Kinect noise, holes) behind the
    same interface as ``MovingRealFrame``: camera, render, distance, anchor, approach."""

    name = "synthetic_plane"

    def __init__(self, speed: float, seed: int = 0, stop: float | None = None):
        from pointfence.service.sources import SyntheticSource, default_camera

        self.cam = default_camera("cam0", eye=(0.0, 0.0, 0.5), width=160, height=120)
        self.src = SyntheticSource("translating_plane", self.cam, speed=speed, travel=0.0, position=(0.0, 0.0, -0.1),
                                   quantize=False, rate_hz=RATE_HZ, seed=seed)
        self.seed = seed
        self.stop = stop  # s: the plane halts at this time (None: it moves throughout)

    def stopped_at(self, stop: float) -> "_PlaneSurface":
        """The same plane halting at time ``stop`` (s)."""
        return _PlaneSurface(self.src.scene.speed, self.seed, stop)

    def _scene_time(self, t):
        return t if self.stop is None else min(t, self.stop)

    def anchor(self):
        return np.array([0.0, 0.0, -0.1])

    def anchor_at(self, t):
        return np.asarray(self.src.scene.anchor(self._scene_time(t)), np.float64)

    def approach(self, anchor):
        return np.array([0.0, 0.0, 1.0])

    def render(self, motion, t, seq):
        depth, _, _ = self.src.render(self._scene_time(t), np.random.default_rng([self.seed, seq]))
        return DepthFrame(self.cam.name, depth, float(t), int(seq))

    def distance(self, motion, q, t):
        return self.src.scene.distance(np.asarray(q, np.float64).reshape(-1, 3), self._scene_time(t))


@dataclass
class TickView:
    """One tick of ``run_case``, for ``on_tick``: its time t (s), the master's point (the HIP),
    the proxy (the robot's goal) and the robot (m, camera frame), their signed distances to the
    true surface at t (m), r_f (m), the ``HapticScene`` (its snapshot, the dt used) and
    ``carry(points, t_from, t_to)``: points of the scene at t_from moved by the true motion."""

    t: float
    hip: np.ndarray
    proxy: np.ndarray
    robot: np.ndarray
    d_proxy: float
    d_robot: float
    r_f: float
    scene: HapticScene
    carry: object


def _approach(anchor) -> np.ndarray:
    """Unit vector from a real surface point toward the camera (the camera frame's origin)."""
    a = np.asarray(anchor, np.float64)
    return -a / np.linalg.norm(a)


def run_case(surface, motion: Motion | None, speed: float, predict: bool, *, r_f: float = 0.01, master: str = "hold",
             backend: str = "opencl", device: str | None = None, model: MotionModel | None = None,
             probe=None, advance: float | None = None, on_tick=None, slip_lift: bool = True,
             near_reading: bool = False) -> RealRun:
    """One run of the loop in the module docstring on ``surface`` (a ``MovingRealFrame`` with
    ``motion``, or the synthetic plane with motion None). ``model``: the motion model (default:
    ``MotionModel(enabled=predict)``). ``probe(hs, t)``: called after every ingest (the
    estimator study reads the snapshot there). ``on_tick(TickView)``: called after every tick
    (``dynamic_real_trace`` records the ticks with it). ``advance``: hold only, how far (m) the surface
    advances from its place at engagement before it stops (default r_f + 2 cm; inf: it moves
    for the whole run; a ``motion`` with its own ``stop`` keeps it). ``slip_lift``: the robot's
    command raised along the proxy's normal while it trails a slipping proxy (``[teleop]
    slip_lift``, on by default in the service; False: the bare rate-limited proxy).
    ``near_reading``: the camera's readings taken at the near end of their depth steps
    (``Camera.near_reading``; the steps of ``surface.cam``: a real frame's fitted ones)."""
    if master not in ("hold", "push"):
        raise InputError(f"master = {master!r}; expected 'hold' or 'push'")
    if advance is not None and not (isinstance(advance, (int, float)) and advance > 0):
        raise InputError(f"advance = {advance!r}; expected a distance > 0 m (inf: no stop)")
    anchor = np.asarray(surface.anchor(), np.float64)
    n = surface.approach(anchor) if motion is None else _approach(anchor)
    travel = r_f + 0.02  # the hold case's advance past the master: r_f + 1 cm of push
    duration = max(travel / max(speed, 1e-9), 4 / RATE_HZ)
    if model is None:
        model = MotionModel(enabled=bool(predict))
    lo, hi = np.minimum(anchor, anchor + n * 0.3), np.maximum(anchor, anchor + n * 0.3)
    reach = 0.1 + (speed * duration if motion is not None and motion.kind != "toward" else 0.0)
    lo, hi = lo - reach, hi + reach
    if motion is not None and motion.kind != "sideways":
        lo[2] -= speed * duration + 0.05
    p = HapticParams(mode="fixture")
    pp = haptic_pipeline_params(p, PipelineParams(workspace=Workspace(tuple(lo), tuple(hi)),
                                                  radius=RadiusModel(r_base=r_f, r_max=r_f), motion=model))
    t0 = 1 / RATE_HZ  # the proxy engages at frame 1, where the surface is then
    if master == "hold" and speed > 0:
        stop = t0 + (travel if advance is None else advance) / speed
        if math.isfinite(stop):
            duration = max(duration, stop - t0 + AFTER_STOP)
            if motion is None:
                surface = surface.stopped_at(stop)
            elif motion.stop is None:
                motion = replace(motion, stop=stop)

    def moved(x, t):
        if motion is None:
            return x + surface.anchor_at(t) - anchor
        R, c = motion.pose(t)
        return R @ x + c

    def carry(x, t_from, t_to):
        """Points (N, 3) of the scene at ``t_from`` where the true motion has them at ``t_to``."""
        x = np.asarray(x, np.float64).reshape(-1, 3)
        if motion is None:
            return x + (surface.anchor_at(t_to) - surface.anchor_at(t_from))
        R0, c0 = motion.pose(t_from)
        R1, c1 = motion.pose(t_to)
        return ((x - c0) @ R0) @ R1.T + c1

    start = moved(anchor + n * (r_f + p.band / 2 + 1e-3), t0)
    hold = moved(anchor + n * (r_f + 0.01), t0)
    pushed = anchor - n * 0.02
    cam = replace(surface.cam, near_reading=bool(near_reading))
    hs = HapticScene([cam], [start], p, pp, backend=backend, device=device)

    def ingest(seq):
        hs.ingest([surface.render(motion, seq / RATE_HZ, seq)])
        if probe is not None:
            probe(hs, seq / RATE_HZ)

    # the camera watches the moving scene for one frame before the proxy engages
    ingest(0)
    ingest(1)
    seq, frames = 1, 2
    for _ in range(40):
        hs.step([start], now=t0)
    # the robot's command is the service's (architecture III: ``Teleop``, the compiled core's
    # arithmetic): the proxy as the goal, raised by the slip lift while the command trails it,
    # rate-limited to ROBOT_SPEED; the master's point maps 1:1 onto the HIP
    x0 = hs.proxies[0].astype(np.float64)[None].copy()
    tp = Teleop(1, scale=1.0, max_robot_speed=ROBOT_SPEED, dt=1.0 / TICK_HZ, architecture="III",
                slip_lift=r_f if slip_lift else 0.0)
    if slip_lift:
        tp.bind_normals(hs.normals)
    on = np.ones(1, bool)
    tp.start(x0, x0)
    tp.map_masters(x0, on, on)
    dev = x0.copy()
    worst_p = worst_r = -np.inf
    popped = False
    n_ticks = int(round(duration * TICK_HZ))
    for k in range(n_ticks):
        t = t0 + k / TICK_HZ
        avail = int(np.floor(t * RATE_HZ + 1e-9))
        if avail != seq:
            seq = avail
            ingest(seq)
            frames += 1
        dev[0] = hold if master == "hold" else moved(pushed, t)
        tp.map_masters(dev, on, on)
        tp.update_hip(tp.cmd)
        hs.step(tp.proxy_hip(), now=t)
        tp.command_goal(hs.proxies, True)
        tp.limit_command(on)
        goal = hs.proxies[0].astype(np.float64)
        xr = tp.cmd[0].copy()
        dp, dr = surface.distance(motion, np.stack([goal, xr]), t)
        worst_p, worst_r = max(worst_p, r_f - dp), max(worst_r, r_f - dr)
        popped |= bool(dp < 0)
        if on_tick is not None:
            on_tick(TickView(t, dev[0].copy(), goal, xr, float(dp), float(dr), r_f, hs, carry))
    return RealRun(max(worst_p, 0.0), max(worst_r, 0.0), popped, n_ticks, frames)


def real_surface(frames) -> MovingRealFrame:
    """The ``MovingRealFrame`` of a recording: a name in ../shared/data or a path."""
    path = Path(frames)
    if not path.exists() and (DATA / str(frames)).exists():
        path = DATA / str(frames)
    depth, cam = load_real(path)
    return MovingRealFrame(depth, cam, name=path.name)


def sweep(scenes=REAL_SCENES, *, speeds=SPEEDS, radii=RADII, cases=CASES, backend: str = "opencl",
          device: str | None = None, synthetic: bool = True, model_options: dict | None = None,
          slip_lift: bool = True, near_reading: bool = False) -> dict:
    """Every scene x case x r_f x speed, with and without prediction. Returns {"rows": [...],
    "scenes": {name: {valid_fraction, anchor_depth_m}}}; a row: scene, motion, master, r_f_mm,
    speed_mps, and proxy/robot max penetration (mm) and proxy popped, without and with prediction.
    ``synthetic``: add the synthetic plane (toward, hold and push) for comparison.
    ``model_options``: MotionModel fields for the prediction runs (besides enabled).
    ``slip_lift``: the robot command's slip lift, ``near_reading``: the camera's (``run_case``)."""
    rows, info = [], {}
    mo = dict(model_options or {})
    targets = [(real_surface(s), s) for s in scenes]
    for surf, label in targets:
        a = surf.anchor()
        info[surf.name] = {"valid_fraction": round(surf.valid_fraction, 3), "anchor_depth_m": round(float(a[2]), 3),
                           "source": str(label)}
    jobs = [(surf, kind, master) for surf, _ in targets for kind, master in cases]
    if synthetic:
        jobs += [(None, "toward", m) for m in sorted({m for k, m in cases if k == "toward"})]
    for surf, kind, master in jobs:
        for r_f in radii:
            for v in speeds:
                row = {"scene": surf.name if surf is not None else _PlaneSurface.name, "motion": kind,
                       "master": master, "r_f_mm": round(r_f * 1e3, 1), "speed_mps": v}
                for tag, predict in (("without", False), ("with", True)):
                    s = surf if surf is not None else _PlaneSurface(v)
                    motion = Motion(kind, v, tuple(s.anchor())) if surf is not None else None
                    model = MotionModel(enabled=predict, **(mo if predict else {}))
                    r = run_case(s, motion, v, predict, r_f=r_f, master=master, backend=backend, device=device,
                                 model=model, slip_lift=slip_lift, near_reading=near_reading)
                    row[f"proxy_mm_{tag}"] = round(r.proxy_penetration * 1e3, 2)
                    row[f"robot_mm_{tag}"] = round(r.robot_penetration * 1e3, 2)
                    row[f"popped_{tag}"] = r.proxy_popped
                rows.append(row)
    return {"rows": rows, "scenes": info}


def held_speeds(rows: list, proxy_mm: float, robot_mm: float, popped: bool = False) -> dict:
    """Per (scene, motion, master, r_f, prediction): the fastest speed up to which every run kept
    the proxy within ``proxy_mm`` and the robot within ``robot_mm`` of penetration (and, with
    ``popped``, the proxy centre in front of the true surface); None: not even the slowest."""
    groups, out = {}, {}
    for r in rows:
        groups.setdefault((r["scene"], r["motion"], r["master"], r["r_f_mm"]), []).append(r)
    for tag in ("without", "with"):
        for key, rs in groups.items():
            held = None
            for r in sorted(rs, key=lambda r: r["speed_mps"]):
                over = r[f"proxy_mm_{tag}"] > proxy_mm or r[f"robot_mm_{tag}"] > robot_mm
                if over or (popped and r[f"popped_{tag}"]):
                    break
                held = r["speed_mps"]
            out[f"{key[0]}/{key[1]}/{key[2]}/r_f {key[3]:g} mm/{tag} prediction"] = held
    return out
