"""The whole ROS 2 path on loopback (issue 21): a camera-node process playing a recorded sequence,
a sim-arm process (the Raven II model) driven as a CRTK arm from the robot process, and the live
service with a simulated master pressing into the fixture under architecture III: the arm never
enters the fixture, while the master's own target lies deep inside it."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np

from pointfence.bench import ros2 as bench_ros2
from pointfence.bench.loop import circling_master
from pointfence.service.robot import robot_from_config


SMALL_CAMERA = """fx = 143.95
fy = 143.95
cx = 79.5
cy = 59.5
width = 160
height = 120
T_world_cam = [1, 0, 0, 0,  0, -1, 0, 0,  0, 0, -1, 0.6,  0, 0, 0, 1]"""


def _spawn(args, env, log):
    return subprocess.Popen([sys.executable, "-m", "pointfence", "ros2", *args], env={**os.environ, **env},
                            stdout=subprocess.DEVNULL, stderr=open(log, "wb"))


def test_architecture_iii_keeps_a_ros2_arm_out_of_a_fixture_seen_through_a_ros2_camera(ros2_env, tmp_path):
    from pointfence.service import measures
    from pointfence.service.canned import canned_sources
    from pointfence.service.runner import LiveRun
    from pointfence.service.sources import open_source

    from pointfence.service import config as config_mod

    _, cfg = bench_ros2._scene(tmp_path)
    cfg_path = tmp_path / "small.toml"   # the same scene through a 160x120 camera: 2 cores run 4 processes here
    text = (tmp_path / "scene.toml").read_text()
    cfg_path.write_text(text.replace('source = "synthetic:sphere"', 'source = "synthetic:sphere"\n' + SMALL_CAMERA))
    cfg = config_mod.load(str(cfg_path))
    bench_ros2._write_frames(cfg, tmp_path / "frames")
    arm_cfg = tmp_path / "arm.toml"     # a point mass where the scene's Raven II tip starts (cheaper to simulate)
    x0 = robot_from_config(cfg.robot).measured_cp()[:3, 3]
    scene = cfg_path.read_text()
    arm_cfg.write_text(scene[:scene.index("[robot]")] + f'[robot]\nmodel = "point-mass"\nx0 = [{x0[0]}, {x0[1]}, {x0[2]}]\n')
    cam_ns, arm_ns = f"/pf_sys{os.getpid()}/cam0", f"PSMSYS{os.getpid()}"
    procs = [_spawn(["camera-node", "--source", f"recorded:{tmp_path / 'frames'}", "--namespace", cam_ns],
                    ros2_env, tmp_path / "camera-node.log"),
             _spawn(["sim-arm", "--namespace", arm_ns, "--config", str(arm_cfg), "--rate", "250"], ros2_env,
                    tmp_path / "sim-arm.log")]
    region = measures.region_for(cfg, canned_sources(cfg, 1))   # the scene's true fixture (signed distance, m)
    run = None
    xr, hip = [], []
    try:
        # (the watchdog's ceiling, 250 ms: the sim-arm is a Python process sharing this 2-core machine with the test)
        cfg_on = bench_ros2._with_robot(cfg, {"model": "crtk", "namespace": arm_ns, "connect_timeout_s": 60.0,
                                              "measured_timeout_s": 0.25, "dof": 3})   # (a point mass: 3 joints)
        source = open_source(f"ros2:{cam_ns}", cfg.cameras[0].camera, wait=60.0)
        run = LiveRun(cfg_on, [circling_master(0, 1, 60.0)], sources=[source])
        assert cfg_on.teleop.architecture == "III"
        run.start(first_frame_timeout=60.0)
        coupled = 0
        end = time.monotonic() + 8.0
        while time.monotonic() < end:
            time.sleep(0.005)
            inp, out = run.service.inp, run.service.out
            xr.append(inp.robot_pos[0].copy())
            hip.append(out.hip[0].copy() if hasattr(out, "hip") else out.command[0].copy())
            coupled += bool(out.coupled[0])
        frames = run.frames.frames_in[0]
        st = run.service.status()
    finally:
        if run is not None:
            run.stop()
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(timeout=20)
    xr, hip = np.array(xr), np.array(hip)
    assert frames > 60, f"the ROS camera delivered {frames} frames in 8 s"
    assert coupled > 100, f"the arm was coupled in {coupled} samples only; status {st}"
    assert np.ptp(xr, axis=0).max() > 0.005, "the sim-arm never moved"
    ok = np.isfinite(xr).all(axis=1)
    d_robot = region(xr[ok], np.zeros(ok.sum()))
    assert d_robot.min() >= -1e-3, f"the sim-arm entered the fixture by {-d_robot.min() * 1e3:.2f} mm"
    ok = np.isfinite(hip).all(axis=1)
    assert region(hip[ok], np.zeros(ok.sum())).min() < -0.005, f"the master never pressed into the fixture; status {st}"
