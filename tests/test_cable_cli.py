"""The `pointfence cable` subcommands that run fast (the demo itself is too long for CI)."""
import argparse
import json

import numpy as np
import pytest

from pointfence.kernels.errors import InputError
from pointfence.service.cable import cli
from pointfence.service.cable.tension import TensionCurve


def _parse(*argv):
    p = argparse.ArgumentParser()
    cli.add_arguments(p)
    return p.parse_args(list(argv))


def test_calib_tension_from_points_file(tmp_path, capsys):
    pts = tmp_path / "pts.csv"
    pts.write_text("450,14000\n900,20500\n1400,25000\n1900,28900\n")
    out = tmp_path / "cal.json"
    assert cli.run(_parse("calib-tension", "--points", str(pts), "--out", str(out))) == 0
    curve = TensionCurve.load(out)
    b, a = np.polyfit(np.log([14000, 20500, 25000, 28900]), [450, 900, 1400, 1900], 1)
    assert curve.b == pytest.approx(b) and curve.a == pytest.approx(a) and curve.b > 0
    assert "ln(k_e)" in capsys.readouterr().out
    bad = tmp_path / "bad.csv"
    bad.write_text("450,14000,3\n")
    with pytest.raises(InputError, match="expected 2"):
        cli.run(_parse("calib-tension", "--points", str(bad), "--out", str(out)))


def test_cable_run_reports_status(capsys):
    assert cli.run(_parse("run", "--seconds", "0.4", "--grasp", "0.2")) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["fault"] is None and s["ticks"] > 300
    assert abs(s["true_link_angle"] - 0.2) < 0.05


def test_bad_tension_list_is_rejected():
    with pytest.raises(SystemExit):
        _parse("calib-tension", "--tensions", "abc")


def test_calib_tension_entry_point_matches_cable_calib_tension(tmp_path):
    from pointfence.service.cable import calib_tension

    p = argparse.ArgumentParser()
    calib_tension.add_arguments(p)
    pts = tmp_path / "pts.csv"
    pts.write_text("450,14000\n900,20500\n1400,25000\n")
    out = tmp_path / "cal.json"
    assert calib_tension.run(p.parse_args(["--points", str(pts), "--out", str(out)])) == 0
    assert TensionCurve.load(out).b > 0


def test_calib_tension_writes_atomically_and_keeps_the_earlier_calibration(tmp_path, monkeypatch):
    from pointfence.service import files

    pts = tmp_path / "pts.csv"
    pts.write_text("450,14000\n900,20500\n1400,25000\n")
    out = tmp_path / "cal.json"
    out.write_text('{"a": 1.0, "b": 2.0}\n')                     # an earlier calibration
    assert cli.run(_parse("calib-tension", "--points", str(pts), "--out", str(out))) == 0
    [bak] = files.backups_of(out)
    assert bak.name == "cal.json.bak" and bak.read_text() == '{"a": 1.0, "b": 2.0}\n'
    first = out.read_text()
    assert TensionCurve.load(out).b > 0
    # a write that fails half-way (disk full) leaves the calibration whole and no temporary file
    real = files._write_temp

    def full_disk(directory, name, data, mode):
        if name == "cal.json" and data != first.encode():
            raise OSError(28, "No space left on device")
        return real(directory, name, data, mode)

    monkeypatch.setattr(files, "_write_temp", full_disk)
    pts.write_text("450,15000\n900,21500\n1400,26000\n")
    with pytest.raises(InputError, match="cal.json: cannot write it .No space left on device"):
        cli.run(_parse("calib-tension", "--points", str(pts), "--out", str(out)))
    assert out.read_text() == first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.json", "cal.json.bak", "cal.json.bak.2", "pts.csv"]
