"""One settings schema (service/settings.py): the key and type checks come from the dataclasses,
the README's settings table and the embedded scene (defaults.toml) agree with them, and the
typed [robot] table matches what the robot models accept."""
import inspect
import re
import typing
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from pointfence.kernels.errors import InputError
from pointfence.service import config, settings
from pointfence.service.robot import MODELS, make_robot, robot_from_config
from pointfence.service.robot.settings import OPTIONS, RobotConfig, parse_robot
from pointfence.service.robot.tool import ToolModel, parse_tool
from pointfence.service.schema import default_of, describe, fields, keys, parse_table

README = Path(__file__).resolve().parents[1] / "README.md"
#: every table a user writes, with the least it needs beside the key under test
TABLES = [(label, cls, {"source": "synthetic:plane"} if cls is settings.CameraTable else {})
          for label, cls in settings.TABLES if cls is not settings.SceneTable]
TABLES += [("[robot] " + m, c, {"model": m}) for m, c in OPTIONS.items()] + [("[robot.tool]", ToolModel, {})]


def _parse(cls, doc):
    if cls in OPTIONS.values():
        return parse_robot(doc)
    if cls is ToolModel:
        return parse_tool(doc)
    return parse_table(cls, doc, f"[{cls.TABLE}]")


def _wrong(tp):
    """A value of the wrong type for TOML type ``tp``."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Union:
        arms = [a for a in args if a is not type(None)]
        return 3.5 if all(a is not float for a in arms) and not any(typing.get_origin(a) is typing.Union for a in arms) \
            else "fast"
    if tp is bool:
        return "yes"
    if tp in (int, float):
        return "fast"
    return 3.5 if tp is str or origin is typing.Literal else "fast"


def test_the_readme_settings_table_is_the_schema():
    text = README.read_text()
    start = text.index("<!-- settings table")
    end = text.index("<!-- end of settings table -->")
    rows = [r for r in text[start:end].splitlines() if r.startswith("| `")]
    cells = [[c.strip() for c in r.strip("|").split(" | ")] for r in rows]
    got = [(t.strip("`"), k.strip("`"), tp, d.replace("&#124;", "|")) for t, k, tp, d, _ in cells]
    want = [(t, k, tp, d) for t, k, tp, d, _ in settings.table_rows()]
    assert {r[:2] for r in got} == {r[:2] for r in want}, "README keys differ from the schema"
    assert got == want, "README types or defaults differ from the schema: python -m pointfence.service.settings"


def test_every_key_of_every_table_is_in_the_readme():
    listed = {(t, k) for t, k, *_ in settings.table_rows()}
    for label, cls, _ in TABLES:
        for key in keys(cls):
            assert (label, key) in listed, (label, key)


def test_the_embedded_scene_restates_no_default():
    """defaults.toml sets only what differs from the schema's defaults: a key set there at its
    schema default would be a second copy of it, free to drift."""
    doc = tomllib.loads(config.embedded_defaults())
    schema = {"robot": OPTIONS["raven2"], "camera": settings.CameraTable}
    for table, value in doc.items():
        if not isinstance(value, dict) and not isinstance(value, list):
            f = settings.SceneTable.__dataclass_fields__[table]
            assert value != f.default, f"defaults.toml restates {table} = {value!r}"
            continue
        cls = schema.get(table) or typing.get_type_hints(settings.SceneTable)[table]
        for entry in value if isinstance(value, list) else [value]:
            for key, v in entry.items():
                f = cls.__dataclass_fields__[key]
                d = default_of(f)
                assert d is None or (list(d) if isinstance(d, tuple) else d) != v, \
                    f"defaults.toml restates [{table}] {key} = {v!r}, the schema's default"
    c = config.load()
    assert c.service == settings.ServiceConfig() and c.teleop.architecture == settings.TeleopConfig().architecture
    assert c.haptics == settings.HapticsTable().params("fixture") and c.pipeline.motion == settings.MotionTable().model()
    assert c.robot.options == OPTIONS["raven2"](mount_tool_down=(0.0, 0.0, 0.25))


@pytest.mark.parametrize("label, cls, base", TABLES, ids=[t[0] for t in TABLES])
def test_an_unknown_key_names_the_key_the_table_and_the_known_keys(label, cls, base):
    key = keys(cls)[0] + "x"
    with pytest.raises(InputError) as e:
        _parse(cls, {**base, key: 1})
    msg = str(e.value)
    assert f"unknown key {key!r}" in msg and f"did you mean {keys(cls)[0]!r}" in msg, msg
    assert msg.startswith(("[" + cls.TABLE, "[robot]")), msg
    assert all(k in msg for k in keys(cls)), msg


@pytest.mark.parametrize("label, cls, base", TABLES, ids=[t[0] for t in TABLES])
def test_a_wrong_type_names_the_value_and_the_expected_type(label, cls, base):
    for name, tp, md, _ in fields(cls):
        bad = _wrong(tp)
        with pytest.raises(InputError) as e:
            _parse(cls, {**base, name: bad})
        msg = str(e.value)
        assert f"{name} = {bad!r}" in msg or f"got {type(bad).__name__} {bad!r}" in msg, msg
        assert "expected" in msg and (md.get("parse") is not None or describe(tp, md) in msg), msg


def test_defaults_are_the_dataclasses():
    for label, cls, base in TABLES:
        parsed = _parse(cls, dict(base))
        if cls in OPTIONS.values():
            parsed = parsed.options
        elif cls is settings.CameraTable:
            parsed = settings.CameraTable(**{**parsed.__dict__, "name": None})
        want = cls(**base) if cls is settings.CameraTable else cls()
        assert repr(parsed) == repr(want), label          # repr: TeleopConfig holds an array


@pytest.mark.parametrize("model", sorted(OPTIONS))
def test_robot_options_are_the_constructor_options(model):
    """Each model's options dataclass has a field per keyword option of its constructor (and
    Raven II's mount_tool_down), with the constructor's default."""
    cls = MODELS[model]
    params = {n: p.default for n, p in inspect.signature(cls.__init__).parameters.items()
              if p.kind is inspect.Parameter.KEYWORD_ONLY and n != "connect"}   # (crtk: not an option)
    extra = {"mount_tool_down"} if model == "raven2" else set()
    assert set(keys(OPTIONS[model])) == set(params) | extra
    for name, default in params.items():
        d = default_of(OPTIONS[model].__dataclass_fields__[name])
        assert (tuple(default) if isinstance(default, (list, tuple)) else default) == d, (model, name)


def test_the_robot_table_is_typed_and_round_trips():
    doc = tomllib.loads("""
[robot]
model = "point-mass"
mass = 1
x0 = [0.0, 0.0, 0.1]
[robot.tool]
parts = [[0, 0, 0, 0, 0, 0.02, 0.004]]
""")["robot"]
    r = parse_robot(doc)
    assert isinstance(r, RobotConfig) and r.model == "point-mass" and r.options.mass == 1.0
    assert r.options.x0 == (0.0, 0.0, 0.1) and r.tool.parts == (((0.0, 0.0, 0.0), (0.0, 0.0, 0.02), 0.004),)
    assert parse_robot(r.table()) == r                       # the hosted robot process's plain table
    a, b = robot_from_config(r), robot_from_config(r.table())
    assert (a.measured_cp() == b.measured_cp()).all() and a.mass == b.mass == 1.0
    assert parse_robot({}) == RobotConfig() and RobotConfig().options == OPTIONS["raven2"]()
    assert parse_robot({"model": "none"}).options is None
    with pytest.raises(InputError, match="takes no options"):
        parse_robot({"model": "none", "mass": 1})
    with pytest.raises(InputError, match=r"\[robot\] mass = 'heavy'; expected a finite number"):
        parse_robot({"model": "point-mass", "mass": "heavy"})
    with pytest.raises(InputError, match="'arm' is an option of model 'raven2'"):
        parse_robot({"model": "point-mass", "arm": "left"})
    with pytest.raises(InputError, match="has no robot to build"):
        robot_from_config(parse_robot({"model": "none"}))
    assert make_robot("raven2", **RobotConfig().kwargs()).arm == "right"


def test_a_config_file_gives_a_typed_robot(tmp_path):
    p = tmp_path / "scene.toml"
    p.write_text(config.embedded_defaults().replace("[robot]\n", '[robot]\nmodel = "raven2"\narm = "left"\n'))
    c = config.load(p)
    assert c.robot.model == "raven2" and c.robot.options.arm == "left" and c.robot.tool is None
    assert c.robot.options.mount_tool_down == (0.0, 0.0, 0.25)
    bad = p.read_text().replace('arm = "left"', 'arm = "middle"')
    p.write_text(bad)
    with pytest.raises(InputError, match=re.escape("[robot] arm = 'middle'; expected one of 'right', 'left'")):
        config.load(p)
