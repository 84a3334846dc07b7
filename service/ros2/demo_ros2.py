"""`pointfence demo --ros2`: the whole ROS 2 path on this machine, no hardware needed.

The scene (the embedded defaults, or ``--config``) runs with its camera, master and arm as ROS 2
equipment in processes of their own (``sim_rig.SimEquipment``): a ``camera-node`` publishing the
scene camera's frames, a ``sim-master`` circling down into the fixture (a dVRK MTM's topics:
``measured_cp``, the foot pedal, ``body/servo_cf`` back), a ``sim-arm`` (a point mass where the
scene's arm tip starts, at 250 Hz: cheap enough to share two cores with the service) as a CRTK
node; the service reads the camera as ``ros2:``, the master through the CRTK master
bridge and drives the arm as ``[robot] model = "crtk"`` from its robot process, publishing
telemetry for RViz or Foxglove (``--ros2-telemetry``). DDS stays on this machine (a domain of its
own, ``dds.local_env``). It prints what crossed ROS and the run's safety: how deep the arm went
into the scene's true fixture (synthetic scenes) against how deep the master asked it to go, and
exits 1 if the arm entered it by more than 1 mm.
"""
from __future__ import annotations

import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from pointfence.kernels.errors import InputError

from . import dds, sim_rig

#: the arm may enter the fixture by at most this much (m) for the demo to pass (SPEC: 1 mm)
MAX_PENETRATION = 1e-3


def run(args, cfg) -> int:
    from ..canned import canned_sources
    from ..config import load
    from ..measures import region_for
    from ..runner import LiveRun
    from .crtk_device import CrtkDevice
    from .crtk_master import CrtkMasterHost

    if not dds.available():
        raise InputError(f"demo --ros2 needs ROS 2 here: {dds.INSTALL_HINT}")
    seconds = float(args.ros2_seconds)
    if not (0 < seconds <= 3600):
        raise InputError(f"--ros2-seconds {args.ros2_seconds!r}; expected seconds in (0, 3600]")
    src_text = Path(cfg.path).read_text() if cfg.path and Path(str(cfg.path)).is_file() else \
        (Path(__file__).parents[1] / "defaults.toml").read_text()
    with tempfile.TemporaryDirectory(prefix="pointfence-demo-ros2-") as t:
        tmp = Path(t)
        env = dds.local_env(dds.unique_domain_id(), tmp / "dds")
        dds.apply(env)
        env = {**os.environ, **env}
        scene = tmp / "scene.toml"
        scene.write_text(sim_rig.ros_scene_text(src_text))
        # the demo's lateness bound (demo --max-lateness) carries over to the ROS scene
        cfg = replace(load(str(scene)), service=replace(load(str(scene)).service, max_lateness_s=cfg.service.max_lateness_s))
        try:
            region = region_for(cfg, canned_sources(cfg, 1))
        except ValueError:
            region = None            # not a synthetic scene: no ground truth to measure against
        print(f"pointfence demo --ros2: domain {env['ROS_DOMAIN_ID']} on this machine only; equipment: "
              f"camera-node {sim_rig.CAMERA_NS}, sim-master /{sim_rig.MASTER_NS}, sim-arm /{sim_rig.ARM_NS}", flush=True)
        # the arm simulated as a point mass at 250 Hz where the scene's arm starts: on one machine
        # with the service, a Raven II model in Python at 1 kHz starves (its watchdog faults it)
        arm_scene = tmp / "arm.toml"
        arm_scene.write_text(sim_rig.point_mass_arm(scene.read_text(), cfg))
        gear = sim_rig.SimEquipment(cfg, scene, tmp, env, nice=sim_rig.EQUIPMENT_NICE, arm_config=arm_scene,
                                    arm_rate_hz=250.0)
        host = run_ = None
        xr, hip, force = [], [], []
        try:
            host = CrtkMasterHost([CrtkDevice(namespace=sim_rig.MASTER_NS)], env=env)
            # the arm's watchdog at its 250 ms ceiling: the sim-arm shares this machine's cores
            run_ = LiveRun(gear.arm_config(cfg, measured_timeout_s=0.25, dof=3), list(host.masters), sources=[gear.source(cfg)],
                           ros2_telemetry=bool(args.ros2_telemetry))
            run_.start(first_frame_timeout=60.0)
            run_.mark()
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                time.sleep(0.005)
                inp, out = run_.service.inp, run_.service.out
                if out.coupled[0]:
                    xr.append(inp.robot_pos[0].copy())
                    hip.append(out.hip[0].copy())
                force.append(float(np.linalg.norm(out.force[0])))
            tm = run_.timing()
            st = run_.service.status()
            frames = run_.frames.frames_in[0]
            ended = gear.ended()
        finally:
            if run_ is not None:
                run_.stop()
            if host is not None:
                host.close()
            gear.close()
    print(f"  camera over ROS: {frames} frames; master over ROS: max force sent {max(force, default=0.0):.2f} N; "
          f"arm over ROS: {len(xr)} coupled samples; holds at the end: {st['hold'] or 'none'}")
    print(f"  loop: tick p50 {tm.compute_us_p50:.0f} us, lateness p99 {tm.late_us_p99:.0f} us, "
          f"misses {100 * tm.miss_ratio:.2f} % (this machine also runs the three equipment processes)")
    if ended:
        print(f"  equipment processes that ended early: {ended} (logs were in the run's temporary folder)")
    if not xr:
        print(f"  the arm never coupled: {st['arms_holding']}; robots {[r and r.get('fault') for r in st['robots']]}")
    if region is None or not xr:
        print("  no ground truth or no coupled motion: penetration not measured")
        return 1 if not xr else 0
    d_arm = region(np.array(xr), np.zeros(len(xr))).min()
    d_hip = region(np.array(hip), np.zeros(len(hip))).min()
    print(f"  fixture (architecture {cfg.teleop.architecture}): the master asked for {max(0.0, -d_hip) * 1e3:.1f} mm "
          f"inside, the arm went {max(0.0, -d_arm) * 1e3:.2f} mm inside (limit {MAX_PENETRATION * 1e3:.0f} mm)")
    return 0 if -d_arm <= MAX_PENETRATION else 1
