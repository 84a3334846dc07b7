"""Teleoperation through the whole service on the simulated clock: architectures I/II/III on the
balloon, switching without jumps, clutch indexing, the speed limit, registration and scaling."""
import ctypes

import numpy as np
import pytest

from pointfence.service import config
from pointfence.service.masters import ScriptedMaster
from pointfence.service.replay import simulate
from pointfence.service.teleop import Teleop

from service_cases import POINT_MASS, REGION_TOP, START_Z, balloon_config, needs_opencl, push, steps

pytestmark = needs_opencl
V = 0.05  # max_robot_speed in the test configuration, m/s
DT = 1e-3


def run(cfg, master, duration, **kw):
    svc, loop, sources = simulate(cfg, [master], duration, **kw)
    for s in sources:
        s.close()
    rec = svc.recorder
    return svc, rec.ticks(), rec


@pytest.mark.parametrize("arch", ["I", "III"])
def test_architecture_iii_keeps_the_robot_out_and_i_lets_it_in(tmp_path, arch):
    cfg = balloon_config(tmp_path, arch=arch)
    # the master pushes the command 6 cm down from z = 0.167: 3.3 cm into the 2 cm fixture
    svc, rows, rec = run(cfg, push(0.12), 1.6)
    xr_z = rows[:, 15]
    pen = REGION_TOP - xr_z.min()
    if arch == "III":
        assert pen <= 0.001, f"architecture III let the robot {pen * 1000:.2f} mm into the region"
        assert np.linalg.norm(rows[-1, 16:19]) > 2.0            # the operator feels the fixture
    else:
        assert pen > 0.02, "architecture I is a soft fixture: pushed, the robot goes in"
        assert np.linalg.norm(rows[-1, 16:19]) > 2.0             # while the force opposes it
    assert svc.status()["hold"] == [] and svc.kernel_errors == 0
    # every command increment respects the speed limit
    assert steps(rows[:, 10:13]).max() <= V * DT * (1 + 1e-6)


def test_switching_mid_contact_changes_force_and_command_smoothly(tmp_path):
    cfg = balloon_config(tmp_path, arch="I")
    order = ["I", "III", "II", "III", "I"]
    switch_ticks = [700, 900, 1100, 1300]
    events = {k: (lambda s, a=a: s.set_architecture(a)) for k, a in zip(switch_ticks, order[1:])}
    svc, rows, rec = run(cfg, push(0.10, t_end=0.9, hold=0.7), 1.6, events=events)
    f = rows[:, 16:19]
    cmd = rows[:, 10:13]
    assert np.linalg.norm(f[650]) > 1.0                                  # in contact before the first switch
    df = steps(f)
    dc = steps(cmd)
    assert dc.max() <= V * DT * (1 + 1e-6)                               # no command jump, ever
    # every switch re-anchors X_m on the command (S1) while the HIP keeps its value and decays onto
    # the new target: switched directly, the force would drop from saturation (3.3 N) to zero in
    # one tick. Blended, no tick changes it by more than the proxy's own jitter on the noisy cloud
    # (about 0.2 N per tick at k_s = 800 N/m), anywhere
    assert np.linalg.norm(rows[1098, 4:7] - rows[1102, 4:7]) < 2 * V * DT * 4   # the HIP did not jump
    assert df.max() <= 0.25, f"force step {df.max():.3f} N"
    for k in switch_ticks:
        assert df[k - 1:k + 50].max() <= 0.25
    # what the robot does: pushed in under I; under III the fixture pushes it back out (at the speed
    # limit); the operator holds still from 0.9 s, so under II (1.1 s) and after nothing moves it
    assert rows[699, 15] < REGION_TOP - 0.002
    assert rows[899, 15] > REGION_TOP - 0.001
    assert np.linalg.norm(rows[1100:, 10:13] - rows[1099, 10:13], axis=1).max() < 1e-4
    assert np.linalg.norm(rows[1100:, 13:16] - rows[1099, 13:16], axis=1).max() < 1e-4
    arch = rec.inputs[: rec.count, 4]
    assert list(np.unique(arch)) == [1, 2, 3]


@pytest.mark.parametrize("action", ["haptics off", "III -> I", "III -> II", "teleop off and on", "radius change"])
def test_no_change_of_control_law_moves_the_robot(tmp_path, action):
    """S1 (issue 18, failure 2): architecture III, the operator 3 cm (robot 1.5 cm) inside the
    fixture and holding still, the command resting on the surface. Any change of control law
    must leave the robot where it is; before the fix, haptics off walked the command down to the
    operator at max_robot_speed."""
    cfg = balloon_config(tmp_path, arch="III")
    events = {"haptics off": {1200: lambda s: s.engage_haptics(False)},
              "III -> I": {1200: lambda s: s.set_architecture("I")},
              "III -> II": {1200: lambda s: s.set_architecture("II")},
              "teleop off and on": {1200: lambda s: s.engage_teleop(False), 1220: lambda s: s.engage_teleop(True)},
              "radius change": {1200: lambda s: s.request_reanchor()}}[action]
    # down 10 cm at the master (5 cm robot goal: 3.3 cm into the 2 cm fixture) by 0.9 s, then still
    svc, rows, rec = run(cfg, push(0.10, t_end=0.9, hold=0.9), 1.8, events=events)
    cmd, xr = rows[:, 10:13], rows[:, 13:16]
    assert rows[1199, 1 + 2] < REGION_TOP - 0.02                        # the operator is deep inside
    assert cmd[1199, 2] > REGION_TOP - 0.001                            # the command rests outside
    # and stays there; the arm (a Raven II lagging its command by about 0.1 mm while it slides)
    # settles where it is commanded or, decoupled, stops where it is: nothing like the 30 mm walk
    assert np.linalg.norm(cmd[1200:] - cmd[1199], axis=1).max() < 1.5e-4
    assert np.linalg.norm(xr[1200:] - xr[1199], axis=1).max() < 1.5e-4
    assert svc.status()["hold"] == []


def test_clutch_indexing_never_moves_the_robot(tmp_path):
    cfg = balloon_config(tmp_path, arch="I", robot=POINT_MASS)
    # down 4 cm (master), pedal up, master back up 8 cm, pedal down, down 4 cm again
    t = np.array([0.0, 0.1, 0.6, 0.65, 0.95, 1.0, 1.5, 1.7])   # robot at 4 cm/s: within the speed limit
    z = np.array([0.0, 0.0, -0.04, -0.04, 0.04, 0.04, 0.0, 0.0])
    pedal = np.array([1, 1, 1, 0, 0, 1, 1, 1])
    m = ScriptedMaster(t, np.stack([np.zeros_like(z), np.zeros_like(z), z], 1), pedal)
    svc, rows, rec = run(cfg, m, 1.7)
    cmd, xm = rows[:, 10:13], rows[:, 1:4]
    out = slice(651, 1000)           # pedal up (held from 0.65 s to 1.0 s)
    assert steps(cmd[out]).max() < 1e-12 and steps(xm[out]).max() < 1e-12
    # re-engaging moves nothing by itself: the command only follows the master's motion from there
    # (8 cm/s at the master, scale 0.5)
    assert steps(cmd[990:1010]).max() <= 0.5 * 0.08 * DT * 1.01
    # after re-engaging, motion continues from where it stopped: 2 + 2 cm robot travel in total
    assert cmd[-1, 2] == pytest.approx(START_Z - 0.04, abs=2e-4)
    assert svc.status()["hold"] == []


def test_rate_limit_and_registration_unit():
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]   # master x -> world y
    tp = Teleop(1, T, scale=0.5, max_robot_speed=0.1, dt=1e-3, architecture="III")
    tp.start(np.zeros((1, 3)), np.array([[0.0, 0.0, 0.1]]))
    pedal, ok = np.ones(1, bool), np.ones(1, bool)
    tp.map_masters(np.zeros((1, 3)), pedal, ok)      # first valid sample: anchor only
    tp.map_masters(np.array([[0.02, 0.0, 0.0]]), pedal, ok)
    np.testing.assert_allclose(tp.X_m[0], [0.0, 0.01, 0.1], atol=1e-12)   # scaled and rotated
    tp.goal[:] = [[0.0, 0.01, 0.1]]
    path = []
    for _ in range(150):                              # the goal jumped 1 cm: 100 ticks at 0.1 m/s
        tp.command_goal(np.array([[0.0, 0.01, 0.1]]), True)
        tp.limit_command(np.ones(1, bool))
        path.append(tp.cmd[0].copy())
    path = np.array(path)
    assert steps(path).max() <= 1e-4 * (1 + 1e-9)
    np.testing.assert_allclose(path[-1], [0.0, 0.01, 0.1], atol=1e-12)
    assert np.argmax(np.isclose(path[:, 1], 0.01)) in (99, 100)
    # NaN from the master: X_m does not move and nothing becomes NaN
    tp.map_masters(np.array([[np.nan, 0.0, 0.0]]), pedal, np.zeros(1, bool))
    assert np.isfinite(tp.X_m).all()


def test_disengaging_teleop_holds_and_reengaging_does_not_jump(tmp_path):
    cfg = balloon_config(tmp_path, arch="I", robot=POINT_MASS)
    events = {300: lambda s: s.engage_teleop(False), 700: lambda s: s.engage_teleop(True),
              1000: lambda s: s.engage_haptics(False), 1200: lambda s: s.engage_haptics(True)}
    svc, rows, rec = run(cfg, push(0.08, t_end=1.2, hold=0.2), 1.4, events=events)
    cmd, f = rows[:, 10:13], rows[:, 16:19]
    assert steps(cmd[301:700]).max() < 1e-12                           # held while disengaged
    assert steps(cmd[699:705]).max() <= V * DT * (1 + 1e-6)            # no jump on re-engaging
    assert cmd[-1, 2] < cmd[700, 2] - 0.005                             # and it follows again
    assert np.linalg.norm(f[1000 + 25]) < 1e-9                          # haptics off: force ramped out
    assert steps(f).max() <= 800 * V * DT + 0.2



@pytest.mark.parametrize("lift", [True, False])
def test_the_slip_lift_reads_the_proxy_batchs_normals_in_iii(tmp_path, lift):
    """[teleop] slip_lift (on by default) gives the tick core III's lift at the fixture radius and
    the running batch's own normals array (the one the kernel updates every tick): without the
    wiring the lift is inert (radius 0 or no normals)."""
    cfg = balloon_config(tmp_path)
    if not lift:
        p = tmp_path / "scene.toml"
        p.write_text(p.read_text().replace("[teleop]\n", "[teleop]\nslip_lift = false\n", 1))
        cfg = config.load(p)
    svc, rows, rec = run(cfg, push(0.12), 0.6)
    tp = svc.teleop
    assert tp.slip_lift == (0.02 if lift else 0.0)
    normals = svc.scene.batch.normals
    bound = ctypes.cast(tp.core.normals, ctypes.c_void_p).value
    assert bound == normals.ctypes.data                                # the batch's array, bound
    assert np.abs(normals).sum() > 0                                   # in contact: real normals
