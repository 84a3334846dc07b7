"""Chapter 6 on a real two-camera rig, in simulated time (no wall clock anywhere): the robot's
tool hiding a protected point from one real camera (6.4), a master pushing into a point two
real cameras see, and the fixed vs adaptive radius on the frames' own noise (6.3,
``dynamic_real_noise.py``). ``rig_figures`` gathers them for ``pointfence bench dynamic --real``.

The rig (``real_rig.py``): two viewpoints of the 7-Scenes kitchen, 0.21 m apart, about 2.5 m
from the protected point, each with its recorded pose. Architecture III throughout: the HIP is
the master, the robot's command the proxy (``service/teleop.py``, the tick core's arithmetic),
rate-limited, sent to a simulated point-mass robot (``service/robot/point_mass.py``) stepped at
1 kHz. Frames at 30 Hz; the tool is rendered into every camera's real depth image at the
robot's pose of the frame's capture, and the self-filter removes it (``kernels/selffilter.py``)
as the service does, leaving the tool's shadow as a hole.

Safety is measured at every tick, exactly (``real_rig.Surface``: the nearest points, as brute
force finds them): the signed distance of the proxy and of the robot to the true surface, the
fused cloud of both cameras without the tool, as measured (``raw``), denoised over ``SMOOTH``
(``mean``), and dequantised (``deq``: each camera's depths moved within half of its Kinect's
disparity step onto a smooth surface, ``depth_steps``; as measured, the cloud is two staircases
of 18 mm steps at 2.5 m, one per camera, whose treads the other camera's points sit behind);
penetration of the forbidden region is max(0, r_f - distance).

Findings the figures rest on (``rig_figures``): the rig's parallax at the site is 4.4 degrees,
so a tool along camera A's line of sight shades B almost as much as A when rendered into both
(``two_cameras_both_shaded``); the brief's rig renders the shadow into A only. A master pushing
along A's line of sight slides the proxy over the noisy fused cloud; it slips by up to 2 cm in
a few ticks, and the rate-limited command, sent straight at it, cut through the bumps between
(the robot, 7 mm behind its command at 0.4 m/s, cut deeper): the teleop's slip lift fixes that.
On the hand-held sequence the fused surface itself steps by up to 5 mm between frames (each
frame's pose error): there the worst robot penetrations come 0-3 ms after a frame, before any
command can move the robot, and no command shaping removes them.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from pointfence.kernels.errors import InputError
from pointfence.kernels import PipelineParams, RadiusModel, Selection, Workspace
from pointfence.kernels.haptics import HapticParams, HapticScene, haptic_pipeline_params
from pointfence.kernels.selffilter import SelfFilter
from pointfence.service.real_rig import SMOOTH, RigCamera, Site, Surface, load_rig, pick_site, render_tool, tool_capsules
from pointfence.service.teleop import Teleop

RATE_HZ = 30.0
TICK_HZ = 1000.0
#: half-width of the workspace box around the protected point, m (every point in it is protected)
HALF = 0.12
#: the tool, from its tip up its axis: (start m, end m, radius m): an 8 mm instrument shaft 15 cm
#: long, then the instrument's 2.4 cm-wide body. Camera A looks down its axis (as the synthetic
#: top camera looks down the shaft): the body hides the whole fixture around the tip from A.
TOOL = ((0.0, 0.15, 0.004), (0.15, 0.30, 0.012))


@dataclass
class Rig:
    """The loaded rig: cameras A and B, the protected site, and the true surface (the fused
    unoccluded cloud around the site, world m) per pair of frame indices."""

    a: RigCamera
    b: RigCamera
    site: Site
    _truth: dict = field(default_factory=dict)

    def truth(self, ia: int, ib: int, smooth: float = 0.0, dequantized: bool = False) -> Surface:
        """The true surface while A shows window frame ``ia`` and B frame ``ib``: the fused
        cloud as measured (``smooth`` = 0), denoised over ``smooth`` m (``Surface``), or of the
        dequantised images (``RigCamera.points``)."""
        key = (ia, ib, smooth, dequantized)
        if key not in self._truth:
            box = self.site.box(HALF)
            pts = [self.a.points(ia, box, dequantized), self.b.points(ib, box, dequantized)]
            self._truth[key] = Surface(np.vstack(pts), self.site.normal, smooth=smooth)
        return self._truth[key]


_RIGS: dict = {}


def rig(window: int = 1, data=None) -> Rig:
    """The kitchen rig (cached per window: loading and the site search take about a second)."""
    key = (window, None if data is None else str(data))
    if key not in _RIGS:
        a, b = load_rig(window=window, data=data)
        _RIGS[key] = Rig(a, b, pick_site(a, b))
    return _RIGS[key]




@dataclass
class RigRun:
    """Outcome of one run: the worst penetration of the r_f region around the true surface by
    the proxy and by the robot (m), against the fused cloud as measured (``raw``) and against
    the same cloud denoised (``mean``: ``Surface(smooth=SMOOTH)``), the robot's smallest signed
    distance to the measured cloud (m), and per-tick traces when asked for."""

    cameras: int
    r_f: float
    proxy_raw: float
    robot_raw: float
    proxy_mean: float
    robot_mean: float
    proxy_deq: float
    robot_deq: float
    robot_min_distance: float
    ticks: int
    trace: dict | None = None

    def mm(self) -> dict:
        r = lambda v: round(max(v, 0.0) * 1e3, 3)  # noqa: E731
        return {"cameras": self.cameras, "fixture_radius_m": self.r_f,
                "proxy_penetration_mm": r(self.proxy_raw), "robot_penetration_mm": r(self.robot_raw),
                "proxy_penetration_mean_surface_mm": r(self.proxy_mean),
                "robot_penetration_mean_surface_mm": r(self.robot_mean),
                "proxy_penetration_dequantized_mm": r(self.proxy_deq),
                "robot_penetration_dequantized_mm": r(self.robot_deq),
                "robot_min_distance_mm": round(self.robot_min_distance * 1e3, 3)}


def _robot(start, max_velocity: float):
    from pointfence.service.robot import make_robot

    lo, hi = np.asarray(start) - 0.5, np.asarray(start) + 0.5
    return make_robot("point-mass", x0=tuple(start), workspace_min=tuple(lo), workspace_max=tuple(hi),
                      max_velocity=max_velocity, fault_error=0)


def arch3_run(R: Rig, *, cameras: int = 2, r_f: float = 0.01, direction=None, start_out: float = 0.03,
              push: float = 0.03, speed: float = 0.1, hold: float = 0.5, max_robot_speed: float = 0.5,
              tool=TOOL, tool_axis=None, shade: str = "A", slip_lift: bool = False, backend: str = "opencl",
              device: str | None = None, trace: bool = False, near_reading: bool = False) -> RigRun:
    """Architecture III on the real rig: the master starts ``start_out`` m outside the surface
    (normal distance) on the line through the protected point along ``direction`` (the push,
    default -normal), moves along it at ``speed`` m/s until it is ``push`` m beneath the
    surface (normal depth), and holds there for ``hold`` s. ``cameras``: 2 (A and B fused) or 1 (A only). ``tool``: the tool's parts
    (``TOOL``; None: no tool rendered), along ``tool_axis`` (default: -direction, up out of the
    surface), rendered into the cameras named in ``shade`` ("A", "B", "AB"). ``slip_lift``: the
    teleop's slip lift at the fixture radius (``Teleop``), the proxies' normals bound.
    ``near_reading``: each camera takes its readings at the near end of their depth steps
    (``Camera.near_reading``, with the step ``RigCamera.steps`` fitted from its frames)."""
    site = R.site
    n_dir = -site.normal if direction is None else np.asarray(direction, np.float64)
    n_dir = n_dir / np.linalg.norm(n_dir)
    axis = -n_dir if tool_axis is None else np.asarray(tool_axis, np.float64) / np.linalg.norm(tool_axis)
    cams = [R.a, R.b][:cameras]
    p = HapticParams(mode="fixture")
    box = site.box(HALF)
    pp = haptic_pipeline_params(p, PipelineParams(workspace=Workspace(tuple(box[0]), tuple(box[1])),
                                                  selection=Selection("all"), radius=RadiusModel(r_base=r_f, r_max=r_f)))
    depth_rate = float(-n_dir @ site.normal)  # normal depth per metre along the push
    if depth_rate < 0.2:
        raise InputError(f"push direction {n_dir} meets the surface at {np.degrees(np.arccos(depth_rate)):.0f} deg "
                         "from its normal; expected a push into it (within 78 deg of -normal)")
    start = site.point - (start_out / depth_rate) * n_dir
    seen = [replace(c.camera, depth_step_inv=c.steps().inv_step, near_reading=True) if near_reading else c.camera
            for c in cams]
    hs = HapticScene(seen, [start], p, pp, backend=backend, device=device)
    filt = SelfFilter([c.camera for c in cams], margin=0.003)
    robot = _robot(start, max_robot_speed)
    tp = Teleop(1, scale=1.0, max_robot_speed=max_robot_speed, dt=1.0 / TICK_HZ, architecture="III",
                slip_lift=r_f if slip_lift else 0.0)
    if slip_lift:
        tp.bind_normals(hs.normals)
    dev = start[None].copy()
    tp.start(dev, robot.measured_cp_position()[None])
    pedal, ok, coupled = np.ones(1, bool), np.ones(1, bool), np.ones(1, bool)
    travel = (start_out + push) / depth_rate
    n_ticks = int(round((travel / speed + hold) * TICK_HZ))
    seq = -1
    truth = mean = deq = None
    xr = robot.measured_cp_position()
    # the tick's positions, measured against the frame's true surfaces when the frame ends (the
    # surfaces are constant over it: every tick is measured, in one query per frame)
    pos = np.zeros((n_ticks, 3, 3))  # proxy, robot, command per tick
    dist = np.zeros((n_ticks, 6))    # signed distances: proxy, robot (raw); (mean); (deq)
    first = 0

    def measure(end):
        if end > first:
            p = pos[first:end, :2].reshape(-1, 3)
            dist[first:end, :2] = truth.signed_distance(p).reshape(-1, 2)
            dist[first:end, 2:4] = mean.signed_distance(p).reshape(-1, 2)
            dist[first:end, 4:] = deq.signed_distance(p).reshape(-1, 2)

    normals = np.zeros((n_ticks, 3)) if trace else None
    for k in range(n_ticks):
        t = k / TICK_HZ
        s = int(np.floor(t * RATE_HZ + 1e-9))
        if s != seq:  # a frame of every camera, the tool where the robot is now
            measure(k)
            first = k
            seq = s
            caps = tool_capsules(xr, axis, tool) if tool else []
            frames = []
            for c in cams:
                i = c.index(seq)
                shaded = caps and c.camera.name[-1] in shade
                depth = render_tool(c.camera, c.depths[i], c.poses[i], caps) if shaded else None
                frames.append(c.frame(seq, t, depth))
            hs.ingest(filt.apply(frames, caps) if caps else frames)
            truth = R.truth(R.a.index(seq), R.b.index(seq))
            mean = R.truth(R.a.index(seq), R.b.index(seq), SMOOTH)
            deq = R.truth(R.a.index(seq), R.b.index(seq), dequantized=True)
        dev[0] = start + min(speed * t, travel) * n_dir
        tp.map_masters(dev, pedal, ok)
        tp.update_hip(xr[None])
        hs.step(tp.proxy_hip(), now=t)
        tp.command_goal(hs.proxies, True)
        tp.limit_command(coupled)
        robot.servo_cp(tp.cmd[0])
        robot.step(1.0 / TICK_HZ)
        xr = robot.measured_cp_position()
        pos[k, 0], pos[k, 1], pos[k, 2] = hs.proxies[0], xr, tp.cmd[0]
        if trace:
            normals[k] = hs.normals[0]
    measure(n_ticks)
    worst = np.max(r_f - dist, axis=0)
    dmin_r = float(dist[:, 1].min())
    tr = None
    if trace:
        t = np.arange(n_ticks) / TICK_HZ
        tr = {"t": t, "master": start + np.minimum(speed * t, travel)[:, None] * n_dir, "proxy": pos[:, 0],
              "robot": pos[:, 1], "cmd": pos[:, 2], "normal": normals, "d_proxy": dist[:, 0], "d_robot": dist[:, 1],
              "m_proxy": dist[:, 2], "m_robot": dist[:, 3], "q_proxy": dist[:, 4], "q_robot": dist[:, 5]}
    return RigRun(cameras, r_f, *np.maximum(worst, 0.0).tolist(), dmin_r, n_ticks, tr)


# --- the figures for `pointfence bench dynamic --real` --------------------------------------------------

def occlusion_figures(*, quick: bool = False, **options) -> dict:
    """The tool's shadow on the real rig (``arch3_run`` with ``TOOL`` along camera A's line of
    sight, pushed along it 3 cm into the surface at 5 cm/s, robot rate limit 5 cm/s as the
    synthetic ``occlusion_run``): camera A alone, A and B fused (the tool rendered into A, B
    seeing the surface), and A and B both shaded (the tool rendered into both: what this rig's
    4.4 degree parallax leaves B)."""
    R = rig(1, options.pop("data", None))
    kw = dict(r_f=0.01, direction=-R.site.view, speed=0.05, max_robot_speed=0.05, hold=0.5)
    if quick:  # from closer, faster, shorter
        kw.update(start_out=0.015, push=0.02, speed=0.2, max_robot_speed=0.2, hold=0.1)
    kw.update(options)
    out = {"one_camera": arch3_run(R, cameras=1, **kw).mm(), "two_cameras": arch3_run(R, cameras=2, **kw).mm()}
    if not quick:
        out["two_cameras_both_shaded"] = arch3_run(R, cameras=2, shade="AB", **kw).mm()
    return out


def push_figures(*, quick: bool = False, **options) -> dict:
    """The master pushing 3 cm into the point both cameras see (architecture III, point-mass
    robot, rate limit 0.5 m/s, master at 0.1 m/s along camera A's line of sight, 69 degrees from
    the surface normal, so the proxy slides), without and with the teleop's slip lift: on the
    rigid rig (each camera on one real frame) and, in full, on the hand-held sequence (each
    camera playing 8 consecutive real frames with their own poses)."""
    data = options.pop("data", None)
    out = {}
    for label, window in (("rigid_rig", 1),) + ((() if quick else (("handheld_8_frames", 8),))):
        R = rig(window, data)
        kw = dict(r_f=0.01, tool=None, direction=-R.site.view, speed=0.1, max_robot_speed=0.5,
                  hold=0.0 if quick else 1.0, **options)
        out[label] = {"command_as_is": arch3_run(R, **kw).mm(), "slip_lift": arch3_run(R, slip_lift=True, **kw).mm()}
    return out


def rig_figures(backend: str = "opencl", device: str | None = None, quick: bool = False, data=None) -> dict:
    """Chapter 6 on real frames: the rig's site, the occlusion and push runs (and, in full, the
    same with ``near_reading``), the noise fit and
    the fixed vs adaptive radius study (``dynamic_real_noise``: on the kitchen's 8 recorded
    frames, and with the fitted noise x1, x2). ``quick``: fewer and shorter
    runs (seconds, for tests). All in simulated time: the same frames give the same figures."""
    from pointfence.service import dynamic_real_noise as drn

    R = rig(1, data)
    s = R.site
    out = {"backend": backend, "frame_rate_hz": RATE_HZ, "tick_rate_hz": TICK_HZ,
           "rig": {"recording": "7scenes_kitchen_50f", "frames": "first (A) and last (B)",
                   "baseline_m": round(float(np.linalg.norm(R.a.poses[0][:3, 3] - R.b.poses[-1][:3, 3])), 3),
                   "site_distance_m": round(float(np.linalg.norm(s.point - R.a.poses[0][:3, 3])), 3),
                   "parallax_deg": s.parallax_deg, "incidence_deg": round(float(np.degrees(np.arccos(s.view @ s.normal))), 1),
                   "registration_offset_mm": s.offset_mm, "local_rms_mm": s.rms_mm}}
    kw = dict(backend=backend, device=device, data=data)
    out["occlusion"] = occlusion_figures(quick=quick, **kw)
    out["push"] = push_figures(quick=quick, **kw)
    if not quick:  # the same with the cameras' readings at the near end of their Kinect steps
        occ = occlusion_figures(near_reading=True, **kw)
        push = push_figures(near_reading=True, **kw)
        out["near_reading"] = {"occlusion": {k: occ[k] for k in ("one_camera", "two_cameras")},
                               "push_slip_lift": {k: v["slip_lift"] for k, v in push.items()}}
    every = 25 if quick else 5
    kitchen = drn.fit_noise(drn.recording_frames("7scenes_kitchen_50f", data=data, every=every))
    out["noise_model"] = {"built_in_kinect": {"a_mm": drn.kinect_model().a * 1e3, "b_per_m": drn.kinect_model().b},
                          "fitted_7scenes_kinect_v1": kitchen.summary()}
    if not quick:
        apc = drn.fit_noise(drn.recording_frames("apc_shelfbin_50f", data=data, every=every), bin_width=0.05,
                            min_blocks=10)
        out["noise_model"]["fitted_apc_close_range"] = apc.summary()
    rows = drn.radius_real_study(kitchen, noise_scales=(1.0,) if quick else (1.0, 2.0), data=data,
                                 window=0 if quick else 8, duration=0.3 if quick else 0.5, backend=backend,
                                 device=device)
    out["radius_study"] = rows
    out["radius_summary"] = drn.summarize(rows)
    return out


def main() -> dict:
    """``python -m pointfence.service.dynamic_real_rig [--quick]``: print ``rig_figures`` as JSON."""
    import json
    import sys

    fig = rig_figures(quick="--quick" in sys.argv[1:])
    print(json.dumps(fig, indent=1, default=float))
    return fig


if __name__ == "__main__":
    main()
