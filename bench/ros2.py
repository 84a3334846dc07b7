"""`pointfence bench ros2`: the ROS 2 path on this machine's loopback, beside the same loop without it.

Live runs of the same scene (the embedded defaults' camera and Raven II arm, the fixture the
objects above the table, one circling master pressing into it, architecture III), one after the
other in one call: ROS off, ROS on, ROS off again (``*_ros_off_after``: the machine's drift over
the call shows as the difference between the two ROS-off runs) (the service's own defaults otherwise: PoCL's pool under SCHED_IDLE, raised by
``service/build_watch.py`` while builds starve):

* **ROS off**: ``bench loop``'s run: 30 pre-rendered frames served in real time, a scripted
  master, the arm simulated in the robot process.
* **ROS on**: the same 30 frames written as a recording and published by a ``ros2 camera-node``
  process (``sensor_msgs/Image`` + ``CameraInfo``, stamps on ROS time) into a ``ros2:`` camera;
  the master a ``ros2 sim-master`` process (``measured_cp`` and the pedal in, ``body/servo_cf``
  out, through the CRTK master bridge process); the arm a ``ros2 sim-arm`` process (the same
  Raven II model) driven as ``[robot] model = "crtk"`` from the robot process; telemetry on.
  The three simulated-equipment processes run at nice ``EQUIPMENT_NICE`` (a lab runs them on
  their own computers).

Each run gives the loop's figures (``loop_miss_ratio``, ``loop_late_us_p99``, tick p50, missed
ticks, the machine's busy share and stolen time). The ROS run adds ``camera_latency_ms_p50/p99``
(a frame's ``header.stamp``, its capture on ROS time, to the moment the snapshot holding it was
published; wall clock, one machine), ``frames_dropped`` (frames the camera published in the
measured seconds that no snapshot held), ``camera_messages`` (the ``ros2:`` source's counts in
those seconds: images received by its bridge, read as frames, replaced before the reader took
them, refused; a dropped frame that was read was passed over by the builds), and ``cpu_pct_by_process`` (each process's share of one
core in the measured seconds: the service, its robot process, master and camera bridges and telemetry, the
three equipment processes). Then, with the service stopped, ``servo_rtt_us_p50/p99``:
a CRTK arm (``robot/crtk.py``, its node in this process) streams ``servo_cp`` at 1 kHz to the
sim-arm, which echoes each applied command's stamp in its ``measured_cp``
(``CrtkRobot.round_trip_us``: to the echo's reception; ``servo_rtt_taken_us_*``: to the arm's
step that took it, up to a period later). DDS stays on this machine (``service/ros2/dds.py``).
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from pointfence.service.ros2 import sim_rig

from .late_causes import RunTrace
from .loop import LOOP_KEYS, _one
from .machine import cpu_times, cpu_usage, process_times, process_usage
from .stats import pct

#: the equipment's nice value (a lab runs it on its own computers)
EQUIPMENT_NICE = sim_rig.EQUIPMENT_NICE
#: the processes of the ROS run, by a text of their command lines (``cpu_pct_by_process``)
ROLES = {"robot process": "robot.hosted_child", "master bridge": "ros2.master_bridge",
         "camera bridge": "ros2.camera_bridge", "telemetry": "ros2.telemetry_node", "camera-node": "ros2 camera-node", "sim-arm": "ros2 sim-arm",
         "sim-master": "ros2 sim-master"}


def add_arguments(p):
    p.add_argument("--seconds", type=float, default=10.0, help="measured seconds of each live run (default 10)")
    p.add_argument("--warmup", type=float, default=2.0, help="seconds run before measuring (default 2)")
    p.add_argument("--late-causes", action="store_true",
                   help="trace the kernel's scheduler over each run's measured seconds (Linux, as root) and sort "
                        "its ticks later than 5 us by cause, ROS on and off (bench/late_causes.py)")
    p.add_argument("--rtt-seconds", type=float, default=5.0, help="seconds of servo_cp at 1 kHz for the round trip (default 5)")


def _scene(tmp: Path):
    """(config path, config) of both runs: the embedded defaults for a ROS camera (sim_rig)."""
    from pointfence.service import config as config_mod

    text = (Path(config_mod.__file__).parent / "defaults.toml").read_text()
    path = tmp / "scene.toml"
    path.write_text(sim_rig.ros_scene_text(text))
    return path, config_mod.load(str(path))


def _ros_run(cfg, cfg_path: Path, tmp: Path, env: dict, seconds: float, warmup: float, backend, device,
             late_causes: bool = False) -> dict:
    from pointfence.service.ros2.crtk_device import CrtkDevice
    from pointfence.service.ros2.crtk_master import CrtkMasterHost
    from pointfence.service.runner import LiveRun

    gear = sim_rig.SimEquipment(cfg, cfg_path, tmp, env, nice=EQUIPMENT_NICE)
    rate = gear.rate_hz
    host = run = trace = None
    try:
        source = gear.source(cfg)
        host = CrtkMasterHost([CrtkDevice(namespace=sim_rig.MASTER_NS)], env=env)
        run = LiveRun(gear.arm_config(cfg), list(host.masters), backend=backend, device=device, sources=[source],
                      ros2_telemetry=True)
        lat, stamps, measuring = [], set(), [False]
        orig = run.frames.on_snapshot

        def noted(seq, built, _orig=orig):
            if measuring[0]:
                lat.append(time.time() - float(built[0].timestamp))
                stamps.add(round(float(built[0].timestamp) * rate))
            if _orig is not None:
                _orig(seq, built)

        run.frames.on_snapshot = noted
        run.start(first_frame_timeout=60.0)
        run.wait(warmup)
        run.mark()
        trace = RunTrace(run) if late_causes else None
        if trace is not None:
            trace.begin()
        measuring[0] = True
        c0, p0, s0 = cpu_times(), process_times(ROLES), source.status()
        run.wait(seconds)
        if trace is not None:
            trace.end()
        tm = run.timing()
        cpu = cpu_usage(c0, cpu_times())
        by_process = process_usage(p0, process_times(ROLES))
        s1 = source.status()
        measuring[0] = False
        st = run.service.status()
    except BaseException:
        if trace is not None:
            trace.abort()
        raise
    finally:
        if run is not None:
            run.stop()
        if host is not None:
            host.close()
        gear.close()
    expected = (max(stamps) - min(stamps) + 1) if stamps else 0
    return {"ticks": tm.ticks, "periods": tm.periods,
            "tick_us_p50": round(tm.compute_us_p50, 1), "tick_us_p99": round(tm.compute_us_p99, 1),
            "loop_late_us_p99": round(tm.late_us_p99, 1), "loop_miss_ratio": round(tm.miss_ratio, 5),
            "loop_misses": tm.misses, "loop_missed_ticks": tm.missed_ticks, **cpu,
            "camera_latency_ms_p50": round(pct(lat, 50) * 1e3, 2) if lat else None,
            "camera_latency_ms_p99": round(pct(lat, 99) * 1e3, 2) if lat else None,
            "camera_frames_published": int(expected), "frames_dropped": int(expected - len(stamps)),
            # the source's counts over the measured seconds: images the bridge received, frames
            # read, images replaced before the reader took them, images refused
            "camera_messages": {k: s1[k] - s0[k] for k in ("received", "delivered", "overwritten", "rejected")},
            "holds_at_end": st["hold"], "telemetry": st.get("telemetry"), "cpu_pct_by_process": by_process,
            **({"late_causes": trace.result()} if trace is not None else {})}


def _servo_rtt(env: dict, tmp: Path, cfg_path: Path, seconds: float) -> dict:
    """servo_cp at 1 kHz from a CRTK arm in this process to a sim-arm process and back."""
    from pointfence.service.periodic import PeriodicLoop
    from pointfence.service.robot.crtk import CrtkRobot

    proc = sim_rig.spawn(["sim-arm", "--namespace", sim_rig.ARM_NS, "--config", str(cfg_path)], env,
                         tmp / "sim-arm-rtt.log", EQUIPMENT_NICE)
    arm = None
    try:
        arm = CrtkRobot(namespace=sim_rig.ARM_NS, connect_timeout_s=30.0)
        x0 = arm.measured_cp()[:3, 3].copy()
        loop = PeriodicLoop(1e-3)
        t_end = time.monotonic() + seconds
        target = np.empty(3)

        def tick(k):
            a = 2 * np.pi * k / 4000.0
            target[:] = x0 + 0.005 * np.array([np.cos(a) - 1.0, np.sin(a), 0.0])
            arm.servo_cp(target)
            arm.step(1e-3)
            if time.monotonic() >= t_end:
                loop.stop()

        loop.run(tick)
        rtt, taken = arm.round_trip_us(), arm.round_trip_us(taken=True)
    finally:
        if arm is not None:
            arm.close()
        sim_rig.stop([proc])
    return {"servo_rtt_us_p50": round(pct(rtt, 50), 1) if rtt else None,
            "servo_rtt_us_p99": round(pct(rtt, 99), 1) if rtt else None, "servo_round_trips": len(rtt),
            "servo_rtt_taken_us_p50": round(pct(taken, 50), 1) if taken else None,
            "servo_rtt_taken_us_p99": round(pct(taken, 99), 1) if taken else None,
            "servo_commands": loop.ticks}


def run(args) -> dict:
    from pointfence.service.ros2 import dds

    with tempfile.TemporaryDirectory(prefix="pointfence-bench-ros2-") as t:
        tmp = Path(t)
        env = dds.local_env(dds.unique_domain_id(), tmp / "dds")
        dds.apply(env)
        env = {**os.environ, **env}
        cfg_path, cfg = _scene(tmp)
        causes = getattr(args, "late_causes", False)
        off = _one(cfg, 1, args.seconds, args.warmup, args.backend, args.device, False, {}, late_causes=causes)
        on = _ros_run(cfg, cfg_path, tmp, env, args.seconds, args.warmup, args.backend, args.device, causes)
        after = _one(cfg, 1, args.seconds, args.warmup, args.backend, args.device, False, {}, late_causes=causes)
        rtt = _servo_rtt(env, tmp, cfg_path, args.rtt_seconds)
    return {"seconds": args.seconds, "rate_hz": cfg.service.rate_hz, **rtt,
            "camera_latency_ms_p50": on["camera_latency_ms_p50"], "camera_latency_ms_p99": on["camera_latency_ms_p99"],
            "frames_dropped": on["frames_dropped"], "camera_messages": on["camera_messages"],
            "cpu_pct_by_process": on["cpu_pct_by_process"],
            "loop_miss_ratio": on["loop_miss_ratio"], "loop_late_us_p99": on["loop_late_us_p99"],
            "loop_miss_ratio_ros_off": off["loop_miss_ratio"], "loop_late_us_p99_ros_off": off["loop_late_us_p99"],
            "loop_miss_ratio_ros_off_after": after["loop_miss_ratio"],
            "loop_late_us_p99_ros_off_after": after["loop_late_us_p99"],
            "ros_on": on, "ros_off": {k: off.get(k) for k in LOOP_KEYS + ("late_causes",) if k in off},
            "ros_off_after": {k: after.get(k) for k in LOOP_KEYS + ("late_causes",) if k in after},
            "note": "one machine: the camera-node, sim-master and sim-arm processes share its cores with the service"}
