"""`pointfence demo`'s chapter-2 surface probes (figs. 2.12-2.15, rendering mode) and its report
folder (PNG plots, table.md, table.json with the pop-through column). The chapter-3 runs go
through the demo on the simulated clock (--offline) with the small balloon scene."""
import argparse
import json

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service import demo, probes, report

from service_cases import balloon_config, needs_opencl

pytestmark = needs_opencl
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def probe_results():
    return probes.run_all(backend="opencl")


def test_probes_measure_the_chapter_2_figures(probe_results):
    push, surf, ledge, plane = probe_results
    assert [p["figure"] for p in probe_results] == ["2.12", "2.13", "2.14", "2.15"]
    # fig. 2.12: the proxy stays on the plane (noise aside) while the force rises with depth
    assert push["penetration_m"] < 0.001
    assert push["force_at_2cm_N"] == pytest.approx(push["k"] * (0.02 + 0.0049 - 0.00505), rel=0.08)
    down = push["force_z"][300:500:10]
    assert np.all(np.diff(down) > 0)
    # fig. 2.13: every surface followed within the sensor noise
    assert len(surf["runs"]) == 4 and all(r["penetration_m"] < 0.0015 and r["max_gap_m"] < 0.002 for r in surf["runs"])
    # fig. 2.14: upper level, then the lower one
    assert ledge["upper_z"] == pytest.approx(0.005 + ledge["r1"], abs=0.0008)
    assert ledge["lower_z"] == pytest.approx(ledge["r1"], abs=0.0008)
    # fig. 2.15: slow planes hold the proxy; some speed in the list pops it through
    assert plane["runs"][0]["speed"] == 0.03 and not plane["runs"][0]["popped"]
    v = plane["popthrough_speed"]
    assert v is not None and v in probes.PLANE_SPEEDS and plane["runs"][-1]["popped"]
    assert all(not r["popped"] for r in plane["runs"][:-1]) and plane["max_speed_held"] < v


def test_report_rows_and_markdown(probe_results):
    rows = [report.row_for_probe(p) for p in probe_results]
    assert [r["mode"] for r in rows] == ["rendering"] * 4
    assert rows[3]["popthrough_m_s"] == probe_results[3]["popthrough_speed"] and rows[0]["popthrough_m_s"] is None
    md = report.markdown_table(rows)
    assert md.splitlines()[0].startswith("| scenario | fig. | arch | mode | safety (mm)") and "pop-through (m/s)" in md
    assert len(md.splitlines()) == 2 + 4


def test_demo_writes_the_report_folder(tmp_path, capsys):
    cfg_path = tmp_path / "scene.toml"
    balloon_config(tmp_path)   # writes scene.toml: the 160x120 balloon scene
    assert cfg_path.exists()
    p = argparse.ArgumentParser()
    demo.add_arguments(p)
    out = tmp_path / "report"
    args = p.parse_args(["--config", str(cfg_path), "--offline", "--only", "balloon", "--report", str(out)])
    assert demo.run(args) == 0
    text = capsys.readouterr().out
    assert "popthr" in text and "fig. 2.15" in text and f"report: 5 plots, table.md and table.json in {out}" in text
    names = {"fig_2_12_push_plane.png", "fig_2_13_surfaces.png", "fig_2_14_ledge.png",
             "fig_2_15_translating_plane.png", "fig_3_9_balloon.png", "table.md", "table.json"}
    assert names <= {f.name for f in out.iterdir()}
    for f in out.glob("*.png"):
        assert f.read_bytes()[:8] == PNG and f.stat().st_size > 5000
    table = json.loads((out / "table.json").read_text())
    rows = table["rows"]
    assert [(r["scenario"], r["arch"]) for r in rows[:3]] == [("balloon", "I"), ("balloon", "II"), ("balloon", "III")]
    assert [r["figure"] for r in rows[3:]] == ["2.12", "2.13", "2.14", "2.15"]
    assert rows[2]["safety_mm"] <= 1.0 < rows[0]["safety_mm"]          # III keeps the robot out, I lets it in
    assert rows[6]["popthrough_m_s"] in probes.PLANE_SPEEDS
    assert table["meta"]["clock"] == "simulated"
    md = (out / "table.md").read_text()
    assert "pop-through (m/s)" in md and "![fig_3_9_balloon](fig_3_9_balloon.png)" in md


def test_demo_report_can_be_turned_off(tmp_path, capsys, monkeypatch):
    balloon_config(tmp_path)
    monkeypatch.chdir(tmp_path)
    p = argparse.ArgumentParser()
    demo.add_arguments(p)
    args = p.parse_args(["--config", str(tmp_path / "scene.toml"), "--offline", "--only", "balloon", "--report", "",
                         "--no-probes"])
    assert demo.run(args) == 0
    assert "report:" not in capsys.readouterr().out and not (tmp_path / "out").exists()


def _demo_args(*argv):
    p = argparse.ArgumentParser()
    demo.add_arguments(p)
    return p.parse_args(["--backend", "numpy", "--offline", "--no-probes", "--no-dynamic", "--report", "", *argv])


@pytest.mark.parametrize("value, message", [
    ("5", r"--max-lateness = 5 s is above its hard limit of 1 s .*use a value <= 1"),
    ("1e9", r"--max-lateness = 1e\+09 s is above its hard limit of 1 s"),
    ("0", r"--max-lateness = 0 s is below its hard limit of 0.0005 s"),
    ("-1", r"--max-lateness = -1 s is below its hard limit"),
    ("nan", r"--max-lateness = nan; expected a finite number"),
    ("inf", r"--max-lateness = inf; expected a finite number"),
])
def test_demo_max_lateness_is_held_to_the_configurations_hard_limit(value, message, monkeypatch):
    """--max-lateness overrides [service] max_lateness_s: a value that would switch the lateness
    hold off (a huge, infinite or NaN lateness) is refused before any run starts (S7)."""
    monkeypatch.setattr(demo, "_run", lambda *a: pytest.fail(f"the demo ran with --max-lateness {value}"))
    with pytest.raises(InputError, match=message):
        demo.run(_demo_args("--max-lateness", value))


def test_demo_max_lateness_within_the_limit_reaches_the_runs(monkeypatch):
    seen = {}

    def fake_run(args, cfg, backend, viewer):
        seen["max_lateness_s"] = cfg.service.max_lateness_s
        return 0

    monkeypatch.setattr(demo, "_run", fake_run)
    assert demo.run(_demo_args("--max-lateness", "0.5")) == 0
    assert seen["max_lateness_s"] == 0.5
