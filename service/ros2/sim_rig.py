"""The whole ROS 2 path on one machine without hardware: simulated equipment in processes of its
own (a ``camera-node`` playing a scene's frames, a ``sim-master``, a ``sim-arm``) and the
service configured to use them (a ``ros2:`` camera, a CRTK master, ``[robot] model = "crtk"``).
``pointfence demo --ros2``, ``pointfence bench ros2`` and the tests run it.

The scene is a configuration whose first camera is synthetic: its first frames are written as a
recording (16-bit PNG in mm, tsdf layout) that the camera-node publishes at the camera's rate,
so the ROS camera shows what the synthetic one would. A ROS depth camera has no colour: a fixture
selected by colour is selected instead as every point above the table (``BOX_SELECT``). The arm
is the scene's own ``[robot]`` model, simulated by the sim-arm with the scene's table (its world
is the arm's base frame on the wire: ``T_world_base`` stays the identity).
"""
from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Optional

import numpy as np

from pointfence.kernels.errors import InputError

#: the fixture of a ROS run: every point above the table (world m)
BOX_SELECT = 'select = { kind = "box", min = [-0.25, -0.25, 0.005], max = [0.25, 0.25, 0.25] }'
COLOR_SELECT = 'select = { kind = "color", lo = [150, 0, 0], hi = [255, 90, 90] }'
CAMERA_NS, MASTER_NS, ARM_NS = "/pf_sim/cam0", "MTMR", "PSM1"
#: the equipment's nice value on a machine shared with the service (a lab runs it elsewhere)
EQUIPMENT_NICE = 5


def ros_scene_text(text: str, extra: str = "") -> str:
    """A scene's TOML for a ROS run: its colour selection replaced by ``BOX_SELECT``, ``extra``
    appended."""
    if "kind = \"color\"" in text:
        if COLOR_SELECT not in text:
            raise InputError("a ROS camera carries no colour: select the fixture by box, mask or all "
                             f"(e.g. {BOX_SELECT}) instead of by colour")
        text = text.replace(COLOR_SELECT, BOX_SELECT)
    return text + extra


def write_frames(cfg, folder: Path, n: int = 30) -> Path:
    """The first camera's first ``n`` frames as a recording the ``recorded:`` source reads (tsdf
    layout: ``frame-NNNNNN.depth.png`` in mm and ``camera-intrinsics.txt``); returns ``folder``."""
    import cv2

    from ..canned import canned_sources

    src = canned_sources(cfg, n)[0]
    cam = src.camera
    if abs(cam.depth_scale - 1e-3) > 1e-12:
        raise InputError(f"camera {cam.name!r}: depth_scale {cam.depth_scale} m; the recording for the ROS camera "
                         "is written in mm (depth_scale 0.001)")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(src.frames):
        cv2.imwrite(str(folder / f"frame-{i:06d}.depth.png"), f.depth.astype(np.uint16))
    np.savetxt(folder / "camera-intrinsics.txt", np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]]))
    return folder


def point_mass_arm(text: str, cfg) -> str:
    """A scene text for the sim-arm: ``text`` with its ``[robot]`` table (which must come last)
    replaced by a point mass (3 joints, cheap to simulate) where ``cfg``'s arm tip starts, so the
    arm over ROS starts where the scene's own arm would."""
    from ..robot import robot_from_config

    if "[robot]" not in text:
        raise InputError("the scene has no [robot] table to simulate")
    x0 = robot_from_config(cfg.robot).measured_cp()[:3, 3]
    return text[:text.index("[robot]")] + f'[robot]\nmodel = "point-mass"\nx0 = [{x0[0]}, {x0[1]}, {x0[2]}]\n'


def with_robot(cfg, table: dict):
    """``cfg`` with its ``[robot]`` table replaced by ``table``."""
    from ..robot.settings import parse_robot

    return replace(cfg, robot=parse_robot(table))


def spawn(args: list, env: dict, log: Path, nice: int = 0) -> subprocess.Popen:
    """A ``pointfence ros2 ...`` process (stderr to ``log``) at ``nice``."""
    return subprocess.Popen([sys.executable, "-m", "pointfence", "ros2", *args], env=env,
                            stdout=subprocess.DEVNULL, stderr=open(log, "wb"),
                            preexec_fn=(lambda: os.nice(nice)) if nice else None)


def stop(procs, timeout: float = 10.0) -> list:
    """SIGTERM each process, then wait (kill after ``timeout``); their exit codes."""
    for p in procs:
        if p.poll() is None:
            p.terminate()
    codes = []
    for p in procs:
        try:
            codes.append(p.wait(timeout=timeout))
        except subprocess.TimeoutExpired:
            p.kill()
            codes.append(p.wait())
    return codes


class SimEquipment:
    """The three equipment processes of a ROS run, started for the scene ``cfg`` (loaded from
    ``cfg_path``) with the ROS environment ``env``; logs and the frames in ``folder``. ``nice``:
    their nice value (a lab runs them on other computers; here they may yield the cores to the
    service). ``master``: also start the sim-master (False: the service's master is scripted).
    ``arm_config``: the sim-arm's scene file (default ``cfg_path``: the scene's own arm);
    ``arm_rate_hz``: its rate (default 1 kHz)."""

    def __init__(self, cfg, cfg_path: Path, folder: Path, env: dict, nice: int = 0, master: bool = True,
                 arm_config: Optional[Path] = None, arm_rate_hz: Optional[float] = None):
        folder = Path(folder)
        frames = write_frames(cfg, folder / "frames")
        self.rate_hz = float(cfg.cameras[0].rate_hz)
        arm = ["sim-arm", "--namespace", ARM_NS, "--config", str(arm_config or cfg_path)]
        if arm_rate_hz is not None:
            arm += ["--rate", f"{arm_rate_hz:g}"]
        self.procs = [spawn(["camera-node", "--source", f"recorded:{frames}", "--namespace", CAMERA_NS,
                             "--rate", f"{self.rate_hz:g}"], env, folder / "camera-node.log", nice),
                      spawn(arm, env, folder / "sim-arm.log", nice)]
        self.master = None
        if master:
            # (its motion starts when the service first answers: the sink into the fixture happens coupled)
            self.master = spawn(["sim-master", "--namespace", MASTER_NS, "--circle", "--start-on-force"], env,
                                folder / "sim-master.log", nice)
            self.procs.append(self.master)
        self.folder = folder

    def source(self, cfg, wait_s: float = 60.0):
        """The service's ``ros2:`` camera of the scene's first camera (intrinsics and pose its)."""
        from ..sources import open_source

        return open_source(f"ros2:{CAMERA_NS}", cfg.cameras[0].camera, wait=wait_s)

    @staticmethod
    def arm_config(cfg, **options):
        """``cfg`` with the arm as ``[robot] model = "crtk"`` on the sim-arm's namespace."""
        return with_robot(cfg, {"model": "crtk", "namespace": ARM_NS, "connect_timeout_s": 60.0, **options})

    def ended(self) -> list:
        """The equipment processes that have ended: (name, exit code)."""
        names = ["camera-node", "sim-arm", "sim-master"]
        return [(n, p.returncode) for n, p in zip(names, self.procs) if p.poll() is not None]

    def close(self) -> list:
        return stop(self.procs)
