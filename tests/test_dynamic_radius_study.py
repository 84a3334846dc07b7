"""Adaptive vs fixed fixture radius (dissertation 6.3): the safety / submittance trade-off."""
from pointfence.service.dynamic_scenes import radius_run, write_radius_study


def test_adaptive_radius_trades_submittance_for_safety(tmp_path):
    """At 1 m with twice the Kinect noise and a 2-sigma systematic error, the fixed 2 cm fixture
    lets the proxy into the nominal region; r_f = r_base + 3 sigma keeps it out but holds it
    further away, also when there is no systematic error (the price in submittance)."""
    rows = [radius_run(1.0, 2.0, adaptive, bias_sigma=b, width=240) for b in (0.0, 2.0) for adaptive in (False, True)]
    fixed0, adapt0, fixed2, adapt2 = rows
    print("\n" + "\n".join(str(r) for r in rows))
    assert fixed2["safety_penetration_mm"] > 2.0 and adapt2["safety_penetration_mm"] == 0.0
    assert adapt0["safety_penetration_mm"] == 0.0
    assert adapt0["submittance_gap_mm"] > fixed0["submittance_gap_mm"] + 5.0
    files = write_radius_study(rows, tmp_path)
    assert (tmp_path / "radius_study.png").stat().st_size > 1000
    assert "| 2 | 1 | 2 |" in (tmp_path / "radius_study.md").read_text()
    assert files["csv"].endswith("radius_study.csv")
