"""Sorting a live loop's late ticks by cause from the kernel's scheduler trace (bench/late_causes.py),
on a trace written here: one tick of each cause, one on time, one whose lock holder's switch
onto its core the trace lost, and one with an interrupt on the other core (still a stall)."""
import numpy as np
import pytest

from pointfence.bench import late_causes as lc

LOOP, CAM, INGEST, OTHER = (100, "pf-haptic-loop"), (101, "pf-cam-x"), (102, "pf-ingest"), (200, "python")
IDLE0, IDLE1 = (0, "swapper/0"), (0, "swapper/1")
SPIN = 60e-6


def _wake(t, cpu, task, by=(0, "<idle>")):
    return (t, f"{by[1]:>16}-{by[0]:<7} [{cpu:03d}] dNh4. {t:.6f}: sched_wakeup: comm={task[1]} pid={task[0]} "
               f"prio=19 target_cpu={cpu:03d}")


def _switch(t, cpu, prev, nxt, state="S"):
    return (t, f"{prev[1]:>16}-{prev[0]:<7} [{cpu:03d}] d..2. {t:.6f}: sched_switch: prev_comm={prev[1]} "
               f"prev_pid={prev[0]} prev_prio=120 prev_state={state} ==> next_comm={nxt[1]} next_pid={nxt[0]} "
               "next_prio=19")


def _event(t, cpu, task, what):
    return (t, f"{task[1]:>16}-{task[0]:<7} [{cpu:03d}] d.h1. {t:.6f}: {what}")


def _scene():
    """(trace text, starts, lates): ticks due at 10.001 s, 10.002 s, ... ."""
    us = 1e-6
    lines, starts, lates = [_switch(10.0, 1, IDLE1, OTHER, "R")], [], []

    def tick(due, late):
        starts.append(due + late)
        lates.append(late)

    # 1: woke in time, blocked while pf-cam-x held the lock on core 1: 'lock', held by pf-cam-x
    d = 10.001
    lines += [_wake(d - SPIN, 0, LOOP), _switch(d - SPIN + us, 0, IDLE0, LOOP, "R"),
              _switch(d - 100 * us, 1, OTHER, CAM, "R"), _switch(d - 55 * us, 0, LOOP, IDLE0, "S"),
              _switch(d + 40 * us, 1, CAM, OTHER, "S"), _wake(d + 41 * us, 0, LOOP, CAM),
              _switch(d + 42 * us, 0, IDLE0, LOOP, "R")]
    tick(d, 43 * us)
    # 2: the clock's wake-up itself came 20 us after the deadline: 'timer'
    d = 10.002
    lines += [_switch(d - 900 * us, 0, LOOP, IDLE0, "S"), _wake(d + 20 * us, 0, LOOP),
              _switch(d + 21 * us, 0, IDLE0, LOOP, "R")]
    tick(d, 22 * us)
    # 3: woken in time, onto its core 75 us later: 'cpu'
    d = 10.003
    lines += [_switch(d - 900 * us, 0, LOOP, IDLE0, "S"), _wake(d - SPIN, 0, LOOP),
              _switch(d + 15 * us, 0, IDLE0, LOOP, "R")]
    tick(d, 16 * us)
    # 4: woken and running in time, no event until it started 30 us late: 'stall'
    d = 10.004
    lines += [_switch(d - 900 * us, 0, LOOP, IDLE0, "S"), _wake(d - SPIN, 0, LOOP),
              _switch(d - SPIN + us, 0, IDLE0, LOOP, "R")]
    tick(d, 30 * us)
    # 5: on time
    d = 10.005
    lines += [_switch(d - 900 * us, 0, LOOP, IDLE0, "S"), _wake(d - SPIN, 0, LOOP),
              _switch(d - SPIN + us, 0, IDLE0, LOOP, "R")]
    tick(d, 0.2 * us)
    # 6: blocked while pf-ingest held the lock; its switch onto core 1 is missing, its switch
    #    away shows it ran (the other process ran on core 1 before: not a holder)
    d = 10.006
    lines += [_switch(d - 900 * us, 0, LOOP, IDLE0, "S"), _wake(d - SPIN, 0, LOOP),
              _switch(d - SPIN + us, 0, IDLE0, LOOP, "R"), _switch(d - 50 * us, 0, LOOP, IDLE0, "S"),
              _switch(d + 60 * us, 1, INGEST, OTHER, "S"), _wake(d + 61 * us, 0, LOOP, INGEST),
              _switch(d + 62 * us, 0, IDLE0, LOOP, "R")]
    tick(d, 63 * us)
    # 7: woken and running in time, a timer interrupt on its core before it started 12 us late: 'irq'
    d = 10.007
    lines += [_switch(d - 900 * us, 0, LOOP, IDLE0, "S"), _wake(d - SPIN, 0, LOOP),
              _switch(d - SPIN + us, 0, IDLE0, LOOP, "R"), _event(d + 5 * us, 0, LOOP, "local_timer_entry: vector=236")]
    tick(d, 12 * us)
    # 8: the same with the interrupt on the other core: 'stall'
    d = 10.008
    lines += [_switch(d - 900 * us, 0, LOOP, IDLE0, "S"), _wake(d - SPIN, 0, LOOP),
              _switch(d - SPIN + us, 0, IDLE0, LOOP, "R"), _event(d + 5 * us, 1, OTHER, "local_timer_entry: vector=236")]
    tick(d, 12 * us)
    lines += [_switch(10.0089, 0, LOOP, IDLE0, "S"), _switch(10.009, 1, OTHER, IDLE1, "S")]
    text = "# tracer: nop\n" + "\n".join(line for _, line in sorted(lines, key=lambda x: x[0])) + "\n"
    return text, np.array(starts), np.array(lates)


def test_each_late_tick_gets_its_cause_and_the_lock_its_holder():
    text, starts, lates = _scene()
    ev = lc.parse(text)
    got = lc.attribute(ev, starts, lates, LOOP[0], {LOOP[0], CAM[0], INGEST[0], 1}, SPIN, threshold_us=5.0)
    assert got["ticks"] == 8 and got["late_ticks"] == 7
    assert (got["lock_ticks"], got["timer_ticks"], got["cpu_ticks"], got["irq_ticks"], got["stall_ticks"],
            got["untraced_ticks"]) == (2, 1, 1, 1, 2, 0)
    assert got["lock_holders"] == {"pf-cam-x": 1, "pf-ingest": 1}     # another process is never a holder
    assert got["irq_events"] == {"local_timer_entry": 1}
    assert got["lock_late_us_mean"] == pytest.approx(53.0) and got["stall_late_us_mean"] == pytest.approx(21.0)


def test_the_threshold_counts_late_ticks_without_changing_their_causes():
    text, starts, lates = _scene()
    got = lc.attribute(lc.parse(text), starts, lates, LOOP[0], {CAM[0], INGEST[0]}, SPIN, threshold_us=25.0)
    assert got["late_ticks"] == 3 and (got["lock_ticks"], got["stall_ticks"], got["timer_ticks"]) == (2, 1, 0)


def test_a_tick_without_the_loops_wakeup_in_the_trace_is_untraced_not_guessed():
    text, starts, lates = _scene()
    kept = "\n".join(line for line in text.splitlines() if "sched_wakeup" not in line)
    got = lc.attribute(lc.parse(kept), starts, lates, LOOP[0], {CAM[0]}, SPIN)
    assert got["untraced_ticks"] == 7 and got["lock_ticks"] == 0


def test_without_tracefs_a_run_trace_says_why_and_the_run_goes_on(monkeypatch):
    monkeypatch.setattr(lc, "tracefs", lambda: (None, "no tracefs here"))
    trace = lc.RunTrace(run=None)
    trace.begin()                                      # nothing to start: the run is not touched
    trace.end()
    assert trace.result() == {"error": "not traced: no tracefs here"}


def test_a_real_trace_sees_this_threads_switches_and_leaves_the_tracer_as_it_was():
    import threading
    import time

    path, why = lc.tracefs()
    if path is None:
        pytest.skip(why)

    def state():
        return {name: open(f"{path}/{name}").read() for name in ("set_event", "trace_clock", "buffer_size_kb",
                                                                  "tracing_on")}

    before = state()
    trace = lc.SchedTrace(buffer_kb=4096)
    trace.start()
    try:
        for _ in range(20):
            time.sleep(0.001)                   # each sleep: a switch away and a wake-up
    finally:
        text = trace.stop()
    assert state() == before
    me = threading.get_native_id()
    t, cpu, kind, a, b, st = lc.parse(text)
    assert ((kind == 1) & np.array([p[0] == me for p in a])).sum() >= 10
    assert sum(1 for k, p, s in zip(kind, a, st) if k == 0 and p[0] == me and s.startswith("S")) >= 10
