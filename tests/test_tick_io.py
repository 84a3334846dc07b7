"""The tick as a function of plain data: ``Service.step`` turns a ``TickInput`` into a
``TickOutput`` without touching a device; hold reasons are named ``HoldReason`` flags; the
control API reaches the service only through its public methods; replay feeds recorded
``TickInput``s back."""
import ast
import math
from pathlib import Path

import numpy as np
import pytest

from pointfence.service.app import Service
from pointfence.service.holds import LATCHED, HoldReason, describe, reason_names
from pointfence.service.masters import Master
from pointfence.service.record import Recorder, tick_input
from pointfence.service.tick_io import TickInput, TickOutput

from service_cases import POINT_MASS, balloon_config

ROOT = Path(__file__).resolve().parents[1]


class _Untouchable(Master):
    """A master that fails the test if the tick reads or writes it."""

    name = "untouchable"

    def __init__(self):
        super().__init__()
        self.armed = False

    def poll(self, t):
        assert not self.armed, "Service.step polled a master"

    def send_force(self, f):
        assert not self.armed, "Service.step sent a force"


def _service(tmp_path):
    cfg = balloon_config(tmp_path, arch="III", robot=POINT_MASS)
    svc = Service(cfg, [_Untouchable()], backend="numpy")
    from pointfence.service.frames import SimFrames

    sources = cfg.open_sources()
    feeder = SimFrames(svc.pipeline, sources, cfg.service.stale_s, cfg.service.max_frame_age_s)
    svc.attach_frames(feeder)
    feeder.poll(0.0)
    svc.start()
    return svc, sources


def _input(svc, k, pos, pedal=True, ok=True, **kw) -> TickInput:
    inp = TickInput.zeros(svc.n)
    inp.k, inp.t, inp.dt, inp.now = k, k * 1e-3, 1e-3, k * 1e-3
    inp.master_pos[:] = pos
    inp.pedal[:] = pedal
    inp.master_ok[:] = ok
    inp.robot_pos[:] = svc.teleop.cmd
    inp.architecture, inp.haptics, inp.teleop = 3, True, True
    for key, v in kw.items():
        setattr(inp, key, v)
    return inp


def test_step_is_a_function_of_plain_data_and_touches_no_device(tmp_path):
    svc, sources = _service(tmp_path)
    svc.masters[0].armed = True
    robot = svc.robots[0]
    held = robot.setpoint_cp().copy()
    down = np.array([0.0, 0.0, -0.002])
    out = None
    for k in range(1, 200):                  # the master moves down 0.2 m in 0.2 s (robot: 0.1 m at scale 0.5)
        out = svc.step(_input(svc, k, down * k / 2))
    assert isinstance(out, TickOutput) and out is svc.out
    assert out.hold == 0 and out.coupled.all() and out.gain[0] == pytest.approx(1.0)
    assert out.xm[0, 2] < 0.1 and out.proxy[0, 2] > 0.139      # X_m deep in the balloon, the proxy on its fixture
    assert out.command[0, 2] >= out.proxy[0, 2] - 1e-9          # III: the command follows the proxy, never X_m
    assert np.isfinite(out.force).all() and np.linalg.norm(out.force[0]) > 0.1   # pushing into the balloon
    assert robot.state.name == "HOLDING" and np.array_equal(robot.setpoint_cp(), held)   # step sent it nothing
    # an invalid master sample: that arm holds for MASTER, by name, and its gain ramps down
    k0 = 200
    for k in range(k0, k0 + 30):
        out = svc.step(_input(svc, k, np.nan, ok=False))
    assert out.arm_hold[0] & HoldReason.MASTER and not out.coupled[0]
    assert HoldReason(int(out.arm_hold[0])).name == "MASTER" and out.gain[0] == 0.0 and not out.force.any()
    for s in sources:
        s.close()


def test_frames_too_old_in_the_input_hold_every_arm_with_its_reason(tmp_path):
    svc, sources = _service(tmp_path)
    for k in range(1, 5):
        out = svc.step(_input(svc, k, 0.0))
    assert out.hold == 0
    out = svc.step(_input(svc, 5, 0.0, frame_age=10.0, frames_too_old=True))
    assert out.hold_reasons == HoldReason.STALE and reason_names(out.hold) == ["frames too old"]
    out = svc.step(_input(svc, 6, 0.0, frame_age=10.0, frames_too_old=False))
    assert out.hold_reasons == HoldReason.STALE | HoldReason.INGEST      # STALE still within recover_s
    assert [d["invariant"] for d in describe(out.hold)] == ["S2", "S2"]
    for s in sources:
        s.close()


def test_hold_reasons_are_a_named_int_flag():
    assert issubclass(HoldReason, int) and {r.name for r in HoldReason} == {
        "OVERRUN", "STALE", "KERNEL", "MASTER", "ROBOT", "EXCEPTION", "INGEST", "WATCHDOG"}
    assert LATCHED == HoldReason.KERNEL | HoldReason.ROBOT | HoldReason.EXCEPTION
    assert all(bin(int(r)).count("1") == 1 for r in HoldReason)


def test_tick_structs_copy_without_sharing():
    out = TickOutput.zeros(2)
    out.force[0] = 1.0
    out.hold = int(HoldReason.KERNEL)
    c = out.copy()
    out.force[0] = 2.0
    assert c.force[0, 0] == 1.0 and c.hold == HoldReason.KERNEL
    dst = TickOutput.zeros(2)
    arrays = {k: id(v) for k, v in vars(dst).items() if isinstance(v, np.ndarray)}
    out.copy_into(dst)
    assert dst.force[0, 0] == 2.0 and {k: id(v) for k, v in vars(dst).items() if isinstance(v, np.ndarray)} == arrays
    inp = TickInput.zeros(1)
    assert math.isnan(inp.frame_time) and inp.copy() is not inp


def test_the_control_api_uses_no_private_field_of_the_service():
    """The control API parses and calls ``Service`` methods: no ``svc._x``, and it never reaches
    through the service into a component (``svc.teleop.x``, ``svc.pipeline.x``, ``svc.batch``)."""
    tree = ast.parse((ROOT / "service" / "control_api.py").read_text())
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            base = node.value
            names = {"svc", "s"}
            if isinstance(base, ast.Name) and base.id in names and node.attr.startswith("_"):
                bad.append(f"line {node.lineno}: {base.id}.{node.attr}")
            if (isinstance(base, ast.Attribute) and base.attr in ("teleop", "pipeline", "batch", "gate", "scene",
                                                                  "devices", "health")
                    and (isinstance(base.value, ast.Name) and base.value.id in names
                         or isinstance(base.value, ast.Attribute) and base.value.attr == "service")):
                bad.append(f"line {node.lineno}: ...{base.attr}.{node.attr}")
            if isinstance(base, ast.Attribute) and base.attr == "service" and node.attr in (
                    "teleop", "pipeline", "batch", "gate", "scene", "devices", "health"):
                bad.append(f"line {node.lineno}: service.{node.attr}")
    assert not bad, bad


def test_a_recorded_tick_input_reads_back_as_it_was_written():
    """``record.tick_input`` is the inverse of ``Recorder.write`` for the input (what replay feeds)."""
    rng = np.random.default_rng(3)
    rec = Recorder(4, 2)
    inp, out = TickInput.zeros(2), TickOutput.zeros(2)
    inp.k, inp.dt, inp.overrun, inp.frame_age, inp.frame_time = 17, 2e-3, True, 0.125, 3.5
    inp.architecture, inp.haptics, inp.teleop = 2, False, True
    inp.master_pos[:] = rng.normal(size=(2, 3))
    inp.pedal[:] = [True, False]
    inp.master_ok[:] = [False, True]
    out.hold, out.arm_hold[:] = int(HoldReason.STALE), [int(HoldReason.STALE), int(HoldReason.STALE | HoldReason.MASTER)]
    rec.write(inp, out)
    back = TickInput.zeros(2)
    tick_input(rec.arrays(), 0, back)
    for name in ("k", "dt", "overrun", "frame_age", "frame_time", "architecture", "haptics", "teleop"):
        assert getattr(back, name) == getattr(inp, name), name
    for name in ("master_pos", "pedal", "master_ok"):
        np.testing.assert_array_equal(getattr(back, name), getattr(inp, name))
    np.testing.assert_array_equal(rec.arrays()["holds"][0], [out.hold, *out.arm_hold])
