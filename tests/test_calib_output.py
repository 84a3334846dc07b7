"""calib writing into a user's configuration: only the calibrated keys change (comments and
layout stay), the write is atomic, and every earlier version is kept (SAFETY.md S8)."""
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from pointfence.calib.output import update_config
from pointfence.service import config

SCENE = textwrap.dedent("""\
    # my rig: do not lose this comment
    backend = "numpy"

    [workspace]   # metres
    min = [-0.5, -0.5, -0.5]
    max = [0.5, 0.5, 0.5]

    [[camera]]
    name = "a"            # the overhead one
    source = "synthetic:plane"
    fx = 575.8   # from the 2023 calibration
    fy = 575.8
    cx = 320.0
    cy = 240.0
    width = 640
    height = 480

    # the second camera, on the arm
    [[camera]]
    name = "b"
    source = "synthetic:sphere"
    T_world_cam = [
        1, 0, 0, 0.1,   # shifted 10 cm
        0, 1, 0, 0,
        0, 0, 1, 0,
        0, 0, 0, 1,
    ]

    [service]
    stale_s = 0.1   # tuned by hand
""")


def test_only_the_calibrated_keys_change_and_comments_survive(tmp_path):
    f = tmp_path / "scene.toml"
    f.write_text(SCENE)
    T = np.eye(4)
    T[:3, 3] = (0.2, 0.0, 0.5)
    r1 = update_config(f, "a", {"fx": 600.5, "noise": {"a": 0.0, "b": 2e-3}})
    r2 = update_config(f, "b", {"T_world_cam": T})
    text = f.read_text()
    for comment in ("# my rig: do not lose this comment", "[workspace]   # metres", 'name = "a"            # the overhead one',
                    "fx = 600.5   # from the 2023 calibration", "# the second camera, on the arm",
                    "stale_s = 0.1   # tuned by hand"):
        assert comment in text, comment
    old, new = SCENE.splitlines(), text.splitlines()
    assert [ln for ln in new if ln not in old] == [
        "fx = 600.5   # from the 2023 calibration", "noise = { a = 0.0, b = 0.002 }",
        "    1.0, 0.0, 0.0, 0.2,", "    0.0, 1.0, 0.0, 0.0,", "    0.0, 0.0, 1.0, 0.5,", "    0.0, 0.0, 0.0, 1.0,"]
    assert [ln for ln in old if ln not in new] == [
        "fx = 575.8   # from the 2023 calibration", "    1, 0, 0, 0.1,   # shifted 10 cm", "    0, 1, 0, 0,",
        "    0, 0, 1, 0,", "    0, 0, 0, 1,"]
    assert new.index("noise = { a = 0.0, b = 0.002 }") == new.index("height = 480") + 1  # after the table's last key
    cfg = config.load(f)
    a, b = (c.camera for c in cfg.cameras)
    assert a.fx == 600.5 and a.fy == 575.8 and a.noise.b == 2e-3 and np.array_equal(b.T_world_cam, T)
    assert cfg.service.stale_s == 0.1 and r1.layout_kept and r2.layout_kept


def test_two_writes_leave_two_backups_and_say_where(tmp_path):
    f = tmp_path / "scene.toml"
    f.write_text(SCENE)
    r1 = update_config(f, "a", {"fx": 600.0})
    after_first = f.read_text()
    r2 = update_config(f, "a", {"fx": 601.0})
    assert r1.backup == tmp_path / "scene.toml.bak" and r2.backup == tmp_path / "scene.toml.bak.2"
    assert r1.backup.read_text() == SCENE and r2.backup.read_text() == after_first
    assert str(r2.backup) in r2.describe(f)
    r3 = update_config(tmp_path / "new.toml", "c", {"fx": 500.0, "fy": 500.0, "cx": 160.0, "cy": 120.0,
                                                    "width": 320, "height": 240}, source="synthetic:plane")
    assert r3.backup is None and config.load(tmp_path / "new.toml").cameras[0].camera.fx == 500.0


def test_a_layout_it_cannot_edit_in_place_is_rewritten_and_says_so(tmp_path):
    f = tmp_path / "scene.toml"
    f.write_text(SCENE.replace('source = "synthetic:sphere"\n', 'source = "synthetic:sphere"\n[camera.noise]\nb = 0.001\n').replace(
        'T_world_cam = [\n    1, 0, 0, 0.1,   # shifted 10 cm\n    0, 1, 0, 0,\n    0, 0, 1, 0,\n    0, 0, 0, 1,\n]\n', ""))
    before = f.read_text()
    assert config.load(f).cameras[1].camera.noise.b == 0.001
    r = update_config(f, "b", {"noise": {"a": 0.0, "b": 3e-3}})
    assert not r.layout_kept and "rewritten without comments" in r.describe(f)
    assert r.backup.read_text() == before and config.load(f).cameras[1].camera.noise.b == 3e-3


def test_a_crash_mid_write_leaves_the_configuration_intact(tmp_path):
    """The writing process hits its file-size limit (as on a full disk) halfway through the new
    file: the configuration must still be the old one, whole."""
    f = tmp_path / "scene.toml"
    f.write_text(SCENE)
    limit = len(SCENE.encode()) + 20  # the backup fits, the grown file does not
    code = textwrap.dedent(f"""
        import resource, signal
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, resource.RLIM_INFINITY))
        from pointfence.calib.output import update_config
        try:
            update_config({str(f)!r}, "a", {{"dist": [0.1, 0.01, 0.001, 0.0001, 0.00001], "fx": 601.25,
                                              "T_world_cam": [1, 0, 0, 0.123456789, 0, 1, 0, 0.123456789,
                                                              0, 0, 1, 0.123456789, 0, 0, 0, 1]}})
        except OSError as e:
            print("failed:", e)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "failed:" in out.stdout, out.stdout + out.stderr
    assert f.read_text() == SCENE
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
