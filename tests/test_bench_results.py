"""bench/RESULTS.md opens with one current table that names every benchmark bench/cli.py
registers, each row with its figure, machine, command and date; the history lives in
bench/HISTORY.md, not in RESULTS.md."""
import re
from pathlib import Path

from pointfence.bench.cli import BENCHES

BENCH_DIR = Path(__file__).parents[1] / "bench"
COLUMNS = ["bench", "run", "figure", "value", "target (as recorded)", "machine", "command", "date (stop)"]


def _current_table() -> list[dict]:
    """Rows of the first table under "## Current figures", as {column: cell}."""
    lines = (BENCH_DIR / "RESULTS.md").read_text().splitlines()
    at = next(i for i, l in enumerate(lines) if l.startswith("## Current figures"))
    rows = []
    for line in lines[at + 1:]:
        if line.startswith("## "):
            break
        if line.startswith("|"):
            rows.append([c.strip() for c in line.strip().strip("|").split(" | ")])
        elif rows:
            break   # the table ended
    header, rule, *body = rows
    assert header == COLUMNS and set("".join(rule)) <= set("-|")
    return [dict(zip(header, r, strict=True)) for r in body]


def test_every_registered_benchmark_has_a_row_and_no_row_names_another():
    rows = _current_table()
    named = [r["bench"].strip("`") for r in rows]
    assert set(BENCHES) - set(named) == set(), "benchmarks without a current figure in bench/RESULTS.md"
    assert set(named) - set(BENCHES) == set(), "rows for benchmarks bench/cli.py does not register"


def test_each_row_says_its_figure_machine_command_and_date():
    previous = None
    for r in _current_table():
        name = r["bench"].strip("`")
        assert r["figure"] and r["value"], r
        for col in ("machine", "command"):
            if r[col] == "same":    # "same" repeats the cell above, within one benchmark
                assert previous is not None and previous["bench"] == r["bench"], (col, r)
                r[col] = previous[col]
        assert f"pointfence bench {name}" in r["command"], r
        assert re.match(r"\d{4}-\d\d-\d\d", r["date (stop)"]), r
        previous = r


def test_the_history_is_its_own_file():
    results = (BENCH_DIR / "RESULTS.md").read_text()
    history = (BENCH_DIR / "HISTORY.md").read_text()
    assert "HISTORY.md" in results
    assert len(results.splitlines()) < 150, "RESULTS.md holds the current figures only; runs go to HISTORY.md"
    for name in BENCHES:
        assert f"pointfence bench {name}" in history, name


def test_cpu_usage_splits_busy_idle_and_stolen_time():
    """bench/machine.py: two /proc/stat readings -> busy share of all cores and stolen time."""
    from pointfence.bench.machine import cpu_times, cpu_usage

    before = {"user": 10.0, "nice": 0.0, "system": 2.0, "idle": 20.0, "iowait": 0.0, "irq": 0.0, "softirq": 0.0,
              "steal": 1.0, "wall": 0.0}
    after = dict(before, user=13.0, system=3.0, idle=25.0, steal=1.5, wall=4.5)   # 9.5 s of core time
    u = cpu_usage(before, after)
    assert u == {"busy_pct": round(100 * 4.0 / 9.5, 1), "steal_ms": 500.0, "steal_pct": round(100 * 0.5 / 9.5, 2)}
    assert cpu_usage(None, after) == {} and cpu_usage(before, before) == {}
    now = cpu_times()
    if now is not None:   # Linux
        assert now["idle"] > 0 and set(now) >= {"user", "system", "steal", "wall"}
