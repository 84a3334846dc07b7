"""`pointfence bench soak` in its short version (every fault kind once, about two minutes): the
live service at 1 kHz with two devices over UDP, two hosted Raven II arms and the control API,
each injected fault judged against SAFETY.md on the streamed recording (bench/soak_check.py;
its judgement itself is tested in test_soak_judge.py). Timing figures (loop misses, latencies in
ms, the devices' sessions lost under load) are the benchmark's to report, not asserted here;
what is asserted is the contract: every fault handled, nothing lost from the recording, no robot
in the fixture."""
import json
import subprocess
import sys

from pointfence.bench.soak_faults import FAULTS

from service_cases import needs_opencl

pytestmark = needs_opencl


def test_every_fault_once_keeps_the_safety_contract(tmp_path):
    out = subprocess.run([sys.executable, "-m", "pointfence.cli", "bench", "soak", "--json", "--out", str(tmp_path)],
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["faults_injected"] == len(FAULTS) == 16
    # the safety contract in kind, every fault: held, latched, cleared, recovered, refused. The
    # measured bounds (hold latency, motion, ramp time) and the link's availability vary with the
    # 2-core machine's load: the benchmark reports them (bench/RESULTS.md), they are not asserted
    contract = [f for f in r["faults_failed"] if f["class"] == "contract"]
    assert contract == [] and r["contract_failures"] == 0, json.dumps(contract, indent=1)
    assert r["ticks_lost"] == 0 and r["ticks_recorded"] > 15000          # about 20 s at 1 kHz
    assert r["max_penetration_mm"] is not None and r["max_penetration_mm"] <= 1.0
    assert r["torn_bytes"] == 0
    verdicts = json.loads((tmp_path / "events.json").read_text())
    assert {v["fault"] for v in verdicts} == set(FAULTS)
    # the injected hang's stalled periods are split from the loop's own misses, never more than them
    assert 0 < r["loop_missed_periods_in_injected_hangs"] <= r["loop"]["misses"]
    assert r["loop_miss_ratio_outside_injected_hangs"] <= r["loop_miss_ratio"]


def test_a_hung_calls_periods_are_its_own_gap_and_tick_and_no_more():
    """``hung_periods``: the gap that opens within 10 ticks of an injected hang, up to the hang's
    length + 2 periods, and the hung tick; gaps elsewhere and the rest of a longer gap are not."""
    import numpy as np

    from pointfence.bench.soak import hung_periods

    k = np.r_[0:100, 130:200, 201:300, 400:500]          # gaps: 30 at 100, 1 at 200, 100 at 300
    assert hung_periods(k, [98], 30) == 31               # 30 skipped + the hung tick
    assert hung_periods(k, [98, 199], 30) == 31 + 2      # a one-period gap after an injection
    assert hung_periods(k, [150], 30) == 0               # no gap within 10 ticks
    assert hung_periods(k, [298], 30) == 33              # capped at 32 + the tick: the rest is the loop's
    assert hung_periods(k, [None], 30) == 0 and hung_periods(k[:1], [0], 30) == 0
