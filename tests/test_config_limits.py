"""Every configuration value that could weaken safety has a hard limit (SAFETY.md S7): each
limited key just beyond its limit, NaN or infinite is a configuration error naming the key,
the value and the limit; at its limit it loads."""
import copy
import math

import pytest

from pointfence.kernels.errors import InputError
from pointfence.service import config
from pointfence.service.limits import CLI_PREFIXES, LIMITS, check

#: the limits of configuration keys (the others bound command-line values: test_serve_args.py)
CONFIG_LIMITS = sorted(k for k in LIMITS if not k.startswith(CLI_PREFIXES))

BASE = {
    "backend": "numpy",
    "workspace": {"min": [-0.25, -0.25, -0.02], "max": [0.25, 0.25, 0.25]},
    "fixture": {"radius": 0.02},
    "camera": [{"name": "c", "source": "synthetic:plane", "fx": 144.0, "fy": 144.0, "cx": 80.0, "cy": 60.0,
                "width": 160, "height": 120}],
    "motion": {},
}

#: other keys a value needs beside it to load (the relations between keys are checked too)
COMPANIONS = {
    ("service.stale_s", "hi"): {"service.max_frame_age_s": 1.0},
    ("service.max_frame_age_s", "lo"): {"service.stale_s": 0.001},
    ("fixture.radius_max", "lo"): {"fixture.radius": 0.001},
    ("fixture.radius", "hi"): {"fixture.radius_max": 0.1},
    ("haptics.step", "hi"): {"haptics.r3": 0.05},
    ("haptics.r3", "lo"): {"haptics.r1": 3e-4, "haptics.r2": 5e-4, "haptics.step": 1e-4},
    ("motion.v_max", "lo"): {"motion.v_min": 0.0},
    ("workspace.max", "lo"): {"workspace.min": [-5.0, -0.25, -0.02]},
    ("workspace.min", "hi"): {"workspace.max": [5.0, 0.25, 0.25]},
    ("service.rate_hz", "lo"): {},
}
#: values at the limit that no valid configuration can hold (min < max, cell >= query reach)
UNREACHABLE = {("workspace.min", "hi"), ("workspace.max", "lo"), ("hash.cell_size", "lo"), ("camera.z_min", "hi"),
               ("camera.z_max", "lo")}


def with_value(key: str, value, extra=None) -> dict:
    doc = copy.deepcopy(BASE)
    for k, v in {**(extra or {}), key: value}.items():
        table, name = k.split(".")
        where = doc["camera"][0] if table == "camera" else doc.setdefault(table, {})
        if table == "robot":            # (robot limits bound options of the CRTK arm: robot/crtk.py)
            where["model"] = "crtk"
        if table == "workspace" and not isinstance(v, list):
            v = [v] + where[name][1:]
        where[name] = v
    return doc


def beyond(key: str, side: str):
    lim = LIMITS[key]
    if lim.integer:
        return int(lim.hi) + 1 if side == "hi" else int(lim.lo) - 1
    edge = lim.hi if side == "hi" else lim.lo
    step = max(abs(edge) * 1e-6, 1e-9)
    return edge + step if side == "hi" else edge - step


def test_the_embedded_defaults_and_the_base_document_load():
    config.load()
    config.parse(copy.deepcopy(BASE))


@pytest.mark.parametrize("key", CONFIG_LIMITS)
def test_each_limit_refuses_beyond_and_nan_and_accepts_at_it(key):
    lim = LIMITS[key]
    label = key.split(".")[1]
    over = beyond(key, "hi")
    with pytest.raises(InputError) as e:
        config.parse(with_value(key, over, COMPANIONS.get((key, "hi"))))
    msg = str(e.value)
    assert label in msg and "hard limit" in msg and f"{lim.hi:g}" in msg, msg
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(InputError, match=label):
            config.parse(with_value(key, bad))
    with pytest.raises(InputError, match=label):
        config.parse(with_value(key, beyond(key, "lo"), COMPANIONS.get((key, "lo"))))
    for side in ("hi", "lo"):
        if (key, side) in UNREACHABLE:
            continue
        edge = getattr(lim, side)
        config.parse(with_value(key, int(edge) if lim.integer else edge, COMPANIONS.get((key, side))))


def test_the_error_says_what_to_do_and_why():
    with pytest.raises(InputError) as e:
        config.parse(with_value("service.max_frame_age_s", 1e9))
    msg = str(e.value)
    assert msg.startswith("[service] max_frame_age_s = 1e+09 s is above its hard limit of 1 s")
    assert "use a value <= 1" in msg and "snapshot" in msg
    with pytest.raises(InputError, match=r"\[\[camera\]\] 'c'.rate_hz = 5000 Hz is above"):
        config.parse(with_value("camera.rate_hz", 5000))
    assert check("teleop.scale", 0.5) == 0.5
    with pytest.raises(InputError, match="teleop.scale = 3 is above"):
        check("teleop.scale", 3)


def test_a_synthetic_camera_with_a_pose_and_no_intrinsics_loads():
    doc = copy.deepcopy(BASE)
    cam = doc["camera"][0]
    for k in ("fx", "fy", "cx", "cy", "width", "height"):
        del cam[k]
    cam["T_world_cam"] = [1, 0, 0, 0.1, 0, -1, 0, 0, 0, 0, -1, 0.5, 0, 0, 0, 1]
    c = config.parse(doc).cameras[0].camera
    assert c.width == 640 and c.T_world_cam[0, 3] == 0.1 and c.T_world_cam[2, 3] == 0.5


def test_every_limit_bounds_a_configuration_key_or_a_command_line_value():
    from pointfence.service import settings
    from pointfence.service.robot.settings import CrtkOptions
    from pointfence.service.schema import keys

    known = {cls.TABLE: set(keys(cls)) for cls in (settings.ServiceConfig, settings.TeleopConfig, settings.HapticsTable,
                                                   settings.FixtureTable, settings.HashTable, settings.WorkspaceTable,
                                                   settings.CameraTable, settings.MotionTable, CrtkOptions)}
    for key in CONFIG_LIMITS:
        table, name = key.split(".")
        assert name in known[table], key
    assert set(LIMITS) - set(CONFIG_LIMITS) == {"serve.timeout_ms"}


def test_the_robot_watchdog_is_configured_within_the_robot_process_ceiling():
    from pointfence.service.robot.hosted import WATCHDOG_MAX_S, WATCHDOG_S

    assert LIMITS["service.robot_watchdog_s"].hi == WATCHDOG_MAX_S
    assert config.load().service.robot_watchdog_s == WATCHDOG_S == config.ServiceConfig().robot_watchdog_s
    assert config.parse(with_value("service.robot_watchdog_s", 0.1)).service.robot_watchdog_s == 0.1
    with pytest.raises(InputError, match=r"\[service\] robot_watchdog_s = 0.3 s is above its hard limit of 0.25 s"):
        config.parse(with_value("service.robot_watchdog_s", 0.3))
    with pytest.raises(InputError, match=r"\[service\] robot_watchdog_s = 0.001 s is below its hard limit of 0.002 s"):
        config.parse(with_value("service.robot_watchdog_s", 0.001))
