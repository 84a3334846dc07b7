"""The whole ROS 2 path on loopback (issue 21): a camera-node process playing a recorded sequence,
a sim-arm process driven as a CRTK arm from the robot process (service/ros2/sim_rig.py), and the
live service with a simulated master pressing into the fixture under architecture III: the arm
never enters the fixture, while the master's own target lies deep inside it."""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from pointfence.bench.loop import circling_master
from pointfence.service.ros2 import sim_rig

#: the default scene through a 160x120 camera: 2 cores run the service and three ROS processes
SMALL_CAMERA = """fx = 143.95
fy = 143.95
cx = 79.5
cy = 59.5
width = 160
height = 120
T_world_cam = [1, 0, 0, 0,  0, -1, 0, 0,  0, 0, -1, 0.6,  0, 0, 0, 1]"""


def _scenes(tmp_path):
    """(scene path, scene, the sim-arm's scene path): the sim-arm a point mass (3 joints, cheap to
    simulate) where the scene's Raven II tip starts."""
    from pointfence.service import config as config_mod

    text = (Path(config_mod.__file__).parent / "defaults.toml").read_text()
    text = sim_rig.ros_scene_text(text).replace('source = "synthetic:sphere"', 'source = "synthetic:sphere"\n' + SMALL_CAMERA)
    path = tmp_path / "scene.toml"
    path.write_text(text)
    cfg = config_mod.load(str(path))
    arm = tmp_path / "arm.toml"
    arm.write_text(sim_rig.point_mass_arm(text, cfg))
    return path, cfg, arm


def test_architecture_iii_keeps_a_ros2_arm_out_of_a_fixture_seen_through_a_ros2_camera(ros2_env, tmp_path):
    from pointfence.service import measures
    from pointfence.service.canned import canned_sources
    from pointfence.service.runner import LiveRun

    cfg_path, cfg, arm_path = _scenes(tmp_path)
    region = measures.region_for(cfg, canned_sources(cfg, 1))   # the scene's true fixture (signed distance, m)
    gear = sim_rig.SimEquipment(cfg, cfg_path, tmp_path, {**os.environ, **ros2_env}, master=False,
                                arm_config=arm_path, arm_rate_hz=250)
    run = None
    xr, hip = [], []
    try:
        # the arm watchdog at its 250 ms ceiling: the sim-arm shares 2 cores with the service here
        cfg_on = gear.arm_config(cfg, measured_timeout_s=0.25, dof=3)
        run = LiveRun(cfg_on, [circling_master(0, 1, 60.0)], sources=[gear.source(cfg)])
        assert cfg_on.teleop.architecture == "III"
        run.start(first_frame_timeout=60.0)
        coupled = 0
        end = time.monotonic() + 8.0
        while time.monotonic() < end:
            time.sleep(0.005)
            inp, out = run.service.inp, run.service.out
            xr.append(inp.robot_pos[0].copy())
            hip.append(out.hip[0].copy())
            coupled += bool(out.coupled[0])
        frames = run.frames.frames_in[0]
        st = run.service.status()
        ended = gear.ended()
    finally:
        if run is not None:
            run.stop()
        gear.close()
    assert not ended, f"equipment processes ended during the run: {ended}"
    xr, hip = np.array(xr), np.array(hip)
    assert frames > 60, f"the ROS camera delivered {frames} frames in 8 s"
    assert coupled > 100, f"the arm was coupled in {coupled} samples only; status {st}"
    assert np.ptp(xr, axis=0).max() > 0.005, "the sim-arm never moved"
    ok = np.isfinite(xr).all(axis=1)
    d_robot = region(xr[ok], np.zeros(ok.sum()))
    assert d_robot.min() >= -1e-3, f"the sim-arm entered the fixture by {-d_robot.min() * 1e3:.2f} mm"
    ok = np.isfinite(hip).all(axis=1)
    assert region(hip[ok], np.zeros(ok.sum())).min() < -0.005, f"the master never pressed into the fixture; status {st}"
