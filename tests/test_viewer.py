"""`pointfence demo --viewer-save FILE.rrd` (service/viewer.py): the balloon experiments on the
simulated clock written to a rerun recording, read back and checked against the runs' own
ticks.csv; and the error when rerun-sdk is missing."""
import sys

import numpy as np
import pytest

from pointfence import cli
from pointfence.service import viewer
from pointfence.service.record import read_ticks_csv

from service_cases import balloon_config, needs_opencl

ARCHS = ("I", "II", "III")


def _read(path) -> dict:
    """entity path (without the leading '/') -> {column name: list of row values}; timeline
    values in seconds."""
    rr = pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install 'pointfence[viewer]')")
    reader = getattr(getattr(rr, "chunk", None), "RrdReader", None)
    if reader is None:
        pytest.skip(f"rerun-sdk {rr.__version__} has no rerun.chunk.RrdReader (0.41 or later reads .rrd files back)")
    out: dict = {}
    for chunk in reader(str(path)).stream():
        batch = chunk.to_record_batch()
        cols = out.setdefault(chunk.entity_path.lstrip("/"), {})
        for name in batch.schema.names:
            col = batch.column(name)
            if str(col.type).startswith("duration"):    # timeline values: seconds
                col = col.cast("int64").to_numpy() * 1e-9
            cols.setdefault(name, []).extend(list(col) if isinstance(col, np.ndarray) else col.to_pylist())
    return out


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install 'pointfence[viewer]')")
    d = tmp_path_factory.mktemp("viewer")
    cfg = balloon_config(d)
    rrd, runs = d / "rec" / "demo.rrd", d / "runs"
    rc = cli.main(["demo", "--config", str(d / "scene.toml"), "--offline", "--only", "balloon", "--report", "",
                   "--no-probes", "--no-dynamic", "--out", str(runs), "--viewer-save", str(rrd)])
    assert rc == 0 and rrd.is_file()
    return _read(rrd), runs, cfg


@needs_opencl
def test_every_experiment_has_its_own_entities(saved):
    data, _, _ = saved
    for arch in ARCHS:
        pre = f"demo/balloon_{arch}"
        for e in ("cloud/protected", "cloud/other", "proxy", "hip", "master", "force", "force_N", "robot/tool",
                  "robot/command", "robot/path", "summary"):
            assert f"{pre}/{e}" in data, f"{pre}/{e} missing; entities: {sorted(data)}"
        text = data[f"{pre}/summary"]["TextDocument:text"][0][0]
        assert f"architecture: {arch}\n" in text and "safety (max penetration): " in text and " mm" in text
    # soft fixture (I) lets the pushed robot into the balloon's fixture, the hard one (III) does not
    low = {a: min(p[2] for p in data[f"demo/balloon_{a}/robot/path"]["LineStrips3D:strips"][0][0]) for a in ARCHS}
    assert low["I"] < low["III"] - 0.01


@needs_opencl
def test_point_cloud_protected_points_apart(saved):
    data, _, _ = saved
    prot, other = data["demo/balloon_III/cloud/protected"], data["demo/balloon_III/cloud/other"]
    pp, po = np.array(prot["Points3D:positions"][0]), np.array(other["Points3D:positions"][0])
    assert pp.shape[0] > 100 and po.shape[0] > 100 and pp.shape[1] == 3
    assert np.all(np.isfinite(pp)) and np.all(np.isfinite(po))
    # the red balloon (6 cm, on the table) is protected; the table is not
    assert pp[:, 2].max() == pytest.approx(0.12, abs=0.01) and np.abs(po[:, 2]).max() < 0.01
    assert prot["Points3D:colors"] != other["Points3D:colors"]


@needs_opencl
@pytest.mark.parametrize("arch", ARCHS)
def test_streams_match_the_recorded_ticks(saved, arch):
    data, runs, cfg = saved
    pre = f"demo/balloon_{arch}"
    ticks = read_ticks_csv(runs / f"balloon_{arch}" / "ticks.csv")
    every = int(round(cfg.service.rate_hz / 100.0))
    rows = ticks[::every]
    proxy = data[f"{pre}/proxy"]
    t = np.array(proxy["loop_time"])
    assert t.size == rows.shape[0] > 100
    np.testing.assert_allclose(t, rows[:, 0], atol=1e-6)
    # proxy centre and HIP as recorded (float32 in the recording), proxy radius r1
    np.testing.assert_allclose(np.array(proxy["Points3D:positions"])[:, 0], rows[:, 7:10], atol=1e-6)
    np.testing.assert_allclose(np.array(data[f"{pre}/hip"]["Points3D:positions"])[:, 0], rows[:, 4:7], atol=1e-6)
    assert np.allclose(np.array(proxy["Points3D:radii"]), cfg.haptics.r1)
    # force arrows: from the HIP, finite, FORCE_SCALE m per N, within the device's maximum force
    arrows = data[f"{pre}/force"]
    vec = np.array(arrows["Arrows3D:vectors"])[:, 0]
    np.testing.assert_allclose(np.array(arrows["Arrows3D:origins"])[:, 0], rows[:, 4:7], atol=1e-6)
    assert np.all(np.isfinite(vec))
    f = vec / viewer.FORCE_SCALE
    np.testing.assert_allclose(f, rows[:, 16:19], atol=1e-4)
    assert np.linalg.norm(f, axis=1).max() <= cfg.haptics.max_force + 1e-4
    assert np.linalg.norm(f, axis=1).max() > 0.5          # the push met the fixture
    np.testing.assert_allclose(np.array(data[f"{pre}/force_N"]["Scalars:scalars"])[:, 0],
                               np.linalg.norm(rows[:, 16:19], axis=1), atol=1e-5)
    # the robot's measured tool path: one line strip through every logged tool position
    tool = np.array(data[f"{pre}/robot/tool"]["Points3D:positions"])[:, 0]
    np.testing.assert_allclose(tool, rows[:, 13:16], atol=1e-6)
    path = np.array(data[f"{pre}/robot/path"]["LineStrips3D:strips"][0][0])
    assert path.shape == tool.shape and path.shape[0] > 0
    np.testing.assert_allclose(path, tool, atol=1e-6)


def test_missing_rerun_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)      # `import rerun` raises ImportError
    with pytest.raises(viewer.ViewerUnavailable, match=r"rerun-sdk.*pip install 'pointfence\[viewer\]'"):
        viewer.Viewer(save="x.rrd")


@needs_opencl
def test_demo_fails_before_running_without_rerun(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "rerun", None)
    balloon_config(tmp_path)
    rrd = tmp_path / "demo.rrd"
    rc = cli.main(["demo", "--config", str(tmp_path / "scene.toml"), "--offline", "--only", "balloon", "--report", "",
                   "--no-probes", "--no-dynamic", "--viewer-save", str(rrd)])
    out, err = capsys.readouterr()
    assert rc == 1 and not rrd.exists() and "balloon" not in out
    assert "pointfence demo: error:" in err and "rerun-sdk" in err and "pip install 'pointfence[viewer]'" in err


def test_viewer_needs_a_target():
    with pytest.raises(viewer.InputError, match="nothing to stream to"):
        viewer.Viewer()
