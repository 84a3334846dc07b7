"""The soak's judge (bench/soak_check.py) on made-up recordings: it must pass a fault handled as
its contract says and name the invariant of every way to break it (no hold, a late hold, a
robot moving while held, a latched fault that comes back by itself, an attack that holds an arm,
an operator action that moves a robot, a penetration of the region)."""
import numpy as np

from pointfence.bench.soak_check import AVAILABILITY, Recording, judge, penetration
from pointfence.bench.soak_faults import FAULTS, Event
from pointfence.service.holds import INGEST, KERNEL, MASTER, OVERRUN, ROBOT

N = 600


def recording(**parts) -> Recording:
    """Two arms at rest, no hold, master input valid, arm 0 pushing with 2 N; ``parts`` replace."""
    data = {"inputs": np.zeros((N, 8)), "masters": np.ones((N, 2, 5)), "robots": np.zeros((N, 2, 6)),
            "rows": np.zeros((N, 22)), "holds": np.zeros((N, 3))}
    data["inputs"][:, 0] = np.arange(N)
    data["inputs"][:, 4:7] = (3, 1, 1)
    data["rows"][:, 0] = np.arange(N) * 1e-3
    data["rows"][:, 18] = 2.0
    for key, value in parts.items():
        data[key] = value
    return Recording(data, 1000.0)


def kernel_fault(hold_from=100, clear=400, ramp=20, robot_moves=0.0, release=None):
    holds = np.zeros((N, 3))
    holds[hold_from:release or clear, 1:] = KERNEL
    rows = np.zeros((N, 22))
    rows[:, 0] = np.arange(N) * 1e-3
    rows[:hold_from, 18] = 2.0
    rows[hold_from:hold_from + ramp, 18] = np.linspace(2.0, 0.0, ramp, endpoint=False)
    robots = np.zeros((N, 2, 6))
    robots[hold_from + 50:, :, 0] = robot_moves
    rec = recording(holds=holds, rows=rows, robots=robots)
    ev = Event("kernel_exception", inject=100, restore=300, clear=clear, recovered=clear + 10)
    return judge(FAULTS["kernel_exception"], ev, rec, 0.5, 0.05)


def test_a_fault_handled_as_its_contract_says_passes():
    v = kernel_fault()
    assert v["failures"] == [] and v["hold_latency_ms"] == 0.0 and v["force_zero_after_ms"] == 20.0


def test_every_way_to_break_a_fault_contract_is_named():
    late = kernel_fault(hold_from=105)
    assert any(inv == "S3" and "held 5 ms" in what for inv, what in late["failures"])
    slow = kernel_fault(ramp=80)
    assert any("force not zero" in what for _, what in slow["failures"])
    moving = kernel_fault(robot_moves=0.0003)
    assert any("moved 0.300 mm while held" in what for _, what in moving["failures"])
    unlatched = kernel_fault(release=250)
    assert any("not latched" in what for _, what in unlatched["failures"])
    never = recording()
    v = judge(FAULTS["kernel_exception"], Event("kernel_exception", 100, 300, 400, 410), never, 0.5, 0.05)
    assert any("never held" in what for _, what in v["failures"])
    v = judge(FAULTS["kernel_exception"], Event("kernel_exception", 100, 300, 400, None), never, 0.5, 0.05)
    assert any("did not recover" in what for _, what in v["failures"])


def test_a_ramp_is_judged_on_the_ticks_the_loop_ran():
    """The machine did not run the loop for 12 periods at the end of a 50 ms ramp (a hypervisor
    stall): the force is zero at the first tick run after force_ramp_s, so the ramp kept its
    contract (the stall is the loop's misses). A ramp still above zero at that tick fails."""
    keep = np.ones(N, bool)
    keep[147:159] = False                       # periods 147..158 not run
    for ramp, ok in ((47, True), (62, False)):
        holds = np.zeros((N, 3))
        holds[100:400, 1:] = KERNEL
        rows = np.zeros((N, 22))
        rows[:, 0] = np.arange(N) * 1e-3
        rows[:100, 18] = 2.0
        rows[100:100 + ramp, 18] = np.linspace(2.0, 0.0, ramp, endpoint=False) + 0.01
        inputs = np.zeros((N, 8))
        inputs[:, 0] = np.arange(N)
        inputs[:, 4:7] = (3, 1, 1)
        gap = recording(holds=holds[keep], rows=rows[keep], inputs=inputs[keep], masters=np.ones((keep.sum(), 2, 5)),
                        robots=np.zeros((keep.sum(), 2, 6)))
        v = judge(FAULTS["kernel_exception"], Event("kernel_exception", 100, 300, 400, 410), gap, 0.5, 0.05)
        failed = [what for _, what in v["failures"] if "force not zero" in what]
        assert (failed == []) == ok, (ramp, v)
        assert v["force_zero_after_ms"] == (59.0 if ramp == 47 else 62.0)


def test_a_frame_fault_is_timed_from_the_tick_the_frames_became_too_old():
    inputs = np.zeros((N, 8))
    inputs[:, 0] = np.arange(N)
    inputs[:, 4:7] = (3, 1, 1)
    inputs[:, 3] = np.clip((np.arange(N) - 100) * 1e-3, 0, 0.3)          # ageing from the injection...
    inputs[250:, 3] = 0.6                                                  # ... too old from tick 250
    holds = np.zeros((N, 3))
    holds[250:450, 1:] = INGEST
    rows = np.zeros((N, 22))
    rows[:250, 18] = 2.0
    rec = recording(inputs=inputs, holds=holds, rows=rows)
    v = judge(FAULTS["ingest_exception"], Event("ingest_exception", 100, 300, None, 460), rec, 0.5, 0.05)
    assert v["failures"] == [] and v["hold_latency_ms"] == 0.0
    holds[250:252, 1:] = 0                                                 # two ticks late
    v = judge(FAULTS["ingest_exception"], Event("ingest_exception", 100, 300, None, 460),
              recording(inputs=inputs, holds=holds, rows=rows), 0.5, 0.05)
    assert any(inv == "S3" and "held 2 ms" in what for inv, what in v["failures"])


def test_attacks_and_actions_change_nothing():
    holds = np.zeros((N, 3))
    holds[150:160, 1] = KERNEL
    v = judge(FAULTS["forged_flood"], Event("forged_flood", 100, 300, None, 310), recording(holds=holds), 0.5, 0.05)
    assert any(inv == "S6" and "held at tick 150" in what for inv, what in v["failures"])
    holds[:] = 0
    holds[150:160, 1] = OVERRUN                # a late tick: counted, not held against the attack
    v = judge(FAULTS["forged_flood"], Event("forged_flood", 100, 300, None, 310), recording(holds=holds), 0.5, 0.05)
    assert v["failures"] == [] and v["timing_holds"] == 10
    masters = np.ones((N, 2, 5))
    masters[200:260, 1, 4] = 0                  # a device's session lost: availability, not the contract
    holds[:] = 0
    holds[200:300, 2] = MASTER
    v = judge(FAULTS["replayed_flood"], Event("replayed_flood", 100, 300, None, 310),
              recording(holds=holds, masters=masters), 0.5, 0.05)
    assert v["failures"] == [(AVAILABILITY, "replayed_flood: a device's input was lost at tick 200 (60 ticks)")]
    inputs = np.zeros((N, 8))
    inputs[:, 0] = np.arange(N)
    inputs[:, 4:7] = (3, 1, 1)
    inputs[120:, 4] = 1                         # the switch applied at tick 120
    robots = np.zeros((N, 2, 6))
    robots[110:, 0, 3] = 0.0002                 # moved before the switch applied: not the switch
    robots[150:, 0, 0] = 0.0003                 # the arm settling onto an unmoved command: not either
    a = FAULTS["architecture_switch_while_pushing"]
    assert judge(a, Event(a.name, 100, 300, None, 310), recording(inputs=inputs, robots=robots), 0.5, 0.05)["failures"] == []
    robots[200:, 1, 5] = 0.0002                 # the command moved after it: the switch moved a robot
    v = judge(a, Event(a.name, 100, 300, None, 310), recording(inputs=inputs, robots=robots), 0.5, 0.05)
    assert any(inv == "S1" and "command 0.200 mm" in what for inv, what in v["failures"])


def test_a_robot_watchdog_after_a_stall_of_the_loop_is_availability_during_an_attack():
    """The machine did not run the loop for 95 periods during a flood: the robot's command
    watchdog (100 ms) stopped the arms (ROBOT with the masters' timeout), as S9 wants. That is
    the machine's availability, not the attack's doing; the same ROBOT hold without the stall is
    the contract broken (S6)."""
    keep = np.ones(N, bool)
    keep[150:245] = False                       # periods 150..244 not run
    holds = np.zeros((N, 3))
    holds[245:290, 1:] = ROBOT | MASTER
    masters = np.ones((N, 2, 5))
    masters[245:290, :, 4] = 0
    inputs = np.zeros((N, 8))
    inputs[:, 0] = np.arange(N)
    inputs[:, 4:7] = (3, 1, 1)
    ev = Event("replayed_flood", 100, 300, None, 310)
    stalled = recording(holds=holds[keep], masters=masters[keep], inputs=inputs[keep], rows=np.zeros((keep.sum(), 22)),
                        robots=np.zeros((keep.sum(), 2, 6)))
    v = judge(FAULTS["replayed_flood"], ev, stalled, 0.5, 0.05, robot_watchdog_s=0.1)
    assert [inv for inv, _ in v["failures"]] == [AVAILABILITY, AVAILABILITY], v["failures"]
    assert "after the loop did not run for 95 ms" in v["failures"][1][1]
    v = judge(FAULTS["replayed_flood"], ev, recording(holds=holds, masters=masters), 0.5, 0.05, robot_watchdog_s=0.1)
    assert any(inv == "S6" and "held at tick 245" in what for inv, what in v["failures"]), v["failures"]


def test_penetration_is_the_deepest_any_arm_went():
    robots = np.zeros((N, 2, 6))
    robots[:, 1, 2] = np.linspace(0.0, -0.004, N)
    region = lambda x, t: x[:, 2] + 0.001      # noqa: E731 -- the region below z = -1 mm
    assert abs(penetration(recording(robots=robots), region, every=1) - 0.003) < 1e-9


def test_failures_are_classed():
    from pointfence.bench.soak_check import failure_class

    assert failure_class("S3", "kernel_exception: arm 0 never held for it") == "contract"
    assert failure_class("S3", "kernel_exception: arm 0 came back before the fault was cleared (not latched)") == "contract"
    assert failure_class("S4", "unauthenticated POST /haptics answered 200, not 401/403") == "contract"
    assert failure_class("S3", "kernel_exception: arm 0 moved 0.300 mm while held (after its stop)") == "bound"
    assert failure_class("S3", "x: arm 1 held 5 ms after the fault was detectable (bound 1 ms)") == "bound"
    assert failure_class(AVAILABILITY, "forged_flood: a device's input was lost at tick 3 (4 ticks)") == "availability"


def test_a_run_that_does_not_come_back_is_load_only_when_only_load_holds():
    """Not recovered within the wait: an overloaded machine (late ticks, a device link lost) is
    availability; a fault still latched after its clear, or any other reason, breaks the contract."""
    never = recording()

    def unrecovered(left):
        ev = Event("kernel_exception", 100, 300, 400, None, notes={"unrecovered": left})
        return judge(FAULTS["kernel_exception"], ev, never, 0.5, 0.05)["failures"]

    load = unrecovered({"hold": ["overrun"], "latched": [], "coupled": [True, False],
                        "arms_holding": [["overrun"], ["overrun", "master input invalid"]]})
    assert (AVAILABILITY, ) == tuple({inv for inv, what in load if "did not recover" in what})
    latched = unrecovered({"hold": ["kernel failure"], "latched": ["kernel failure"], "coupled": [False, False],
                           "arms_holding": [["kernel failure"], ["kernel failure"]]})
    assert any(inv == "S3" and "did not recover" in what and "kernel failure" in what for inv, what in latched)
    other = unrecovered({"hold": [], "latched": [], "coupled": [False, True],
                         "arms_holding": [["robot fault or rejected command"], []]})
    assert any(inv == "S3" and "did not recover" in what for inv, what in other)


def test_a_status_holds_for_load_only_without_latched_faults_and_other_reasons():
    from pointfence.bench.soak_check import load_only

    assert load_only({"hold": ["overrun"], "arms_holding": [["overrun"], ["master input invalid"]], "latched_faults": []})
    assert load_only({"hold": [], "arms_holding": [[], []], "latched_faults": []})       # a device not coupled
    assert not load_only({"hold": [], "arms_holding": [["kernel failure"], []], "latched_faults": ["kernel failure"]})
    assert not load_only({"hold": [], "arms_holding": [["robot fault or rejected command"], []], "latched_faults": []})


def test_a_clear_the_link_never_let_happen_is_availability():
    """The devices' pedals never read up (the link behind under load): no clear was tried, so
    "never cleared" and "did not recover" are the link's availability, not a broken contract."""
    rec = kernel_fault(release=600)["failures"]          # (the same fault, held to the end)
    assert not any("never cleared" in what for _, what in rec)
    holds = np.zeros((N, 3))
    holds[100:, 1:] = KERNEL
    ev = Event("kernel_exception", 100, 300, None, None, notes={"pedals_unread": True})
    fails = judge(FAULTS["kernel_exception"], ev, recording(holds=holds), 0.5, 0.05)["failures"]
    assert {inv for inv, what in fails if "never cleared" in what or "did not recover" in what} == {AVAILABILITY}
    ev = Event("kernel_exception", 100, 300, None, None)
    fails = judge(FAULTS["kernel_exception"], ev, recording(holds=holds), 0.5, 0.05)["failures"]
    assert any(inv == "S3" and "never cleared" in what for inv, what in fails)


def test_the_hold_bound_counts_the_ticks_the_loop_ran_not_the_periods_it_missed():
    """A robot stall (detectable 110 ms after the injection: the robot watchdog's 100 ms and its
    10 ms) held at the first tick the loop ran after a 19 ms gap of the machine is held in time;
    held a tick later than that, it is not. Before, the gap's periods counted: 'held 123 ms after
    the fault was detectable (bound 111 ms)'."""
    from pointfence.service.holds import ROBOT

    def stall(hold_row, gap=True):
        keep = np.r_[0:204, 223:N] if gap else np.arange(N)    # periods 204..222 not run (a 19 ms gap)
        holds = np.zeros((N, 3))
        holds[:, 1:][np.arange(N) >= hold_row] = ROBOT
        data = {"inputs": np.zeros((N, 8)), "masters": np.ones((N, 2, 5)), "robots": np.zeros((N, 2, 6)),
                "rows": np.zeros((N, 22)), "holds": holds}
        data["inputs"][:, 0] = np.arange(N)
        data["inputs"][:, 4:7] = (3, 1, 1)
        data["rows"][:, 0] = np.arange(N) * 1e-3
        data["rows"][:hold_row, 18] = 2.0
        data = {k: v[keep] for k, v in data.items()}
        rec = Recording(data, 1000.0)
        ev = Event("robot_process_stall", inject=100, restore=400, clear=450, recovered=460)
        return judge(FAULTS["robot_process_stall"], ev, rec, 0.5, 0.05, robot_watchdog_s=0.1)

    for k in (223, 224):          # the first tick run after the gap (past the 110 ms), or the next
        on_time = stall(k)
        assert not [w for _, w in on_time["failures"] if "held" in w], on_time["failures"]
    assert on_time["detection_ms"] == 124.0
    late = stall(225)             # one more tick run later
    assert any(inv == "S3" and "held 125 ms" in w and "1 ticks run after" in w for inv, w in late["failures"])
    assert not [w for _, w in stall(211, gap=False)["failures"] if "held" in w]   # no gap: as before,
    assert any("held 112 ms" in w for _, w in stall(212, gap=False)["failures"])  # periods are ticks


def test_a_fault_injected_while_its_arms_already_held_for_it_is_availability_not_handled():
    """Snapshots already too old when the ingest thread is killed (a loaded machine): the hold
    that follows cannot be told from the one before, so the event is the run's availability (a
    failure, not handled), never a broken latch. Before: 'came back before the fault was cleared
    (not latched)' when the earlier hold ended."""
    holds = np.zeros((N, 3))
    holds[90:180, 1:] = INGEST          # held for old snapshots from before the injection (100)
    holds[200:420, 1:] = INGEST         # the death's latched hold
    age = np.zeros((N, 8))
    age[:, 0] = np.arange(N)
    age[:, 4:7] = (3, 1, 1)
    age[90:180, 3] = 0.6
    age[200:420, 3] = 0.6
    rec = recording(holds=holds, inputs=age)
    ev = Event("ingest_thread_death", inject=100, restore=300, clear=400, recovered=430)
    v = judge(FAULTS["ingest_thread_death"], ev, rec, 0.5, 0.05)
    assert [inv for inv, _ in v["failures"]] == [AVAILABILITY]
    assert "already held" in v["failures"][0][1]
    clean = holds.copy()
    clean[90:180] = 0                   # the same death on a steady run: judged, and handled
    age[90:180, 3] = 0.0
    rows = np.zeros((N, 22))
    rows[:, 0] = np.arange(N) * 1e-3
    rows[:200, 18] = 2.0                # the force is zero from the hold on
    v = judge(FAULTS["ingest_thread_death"], Event("ingest_thread_death", 100, 300, 400, 430),
              recording(holds=clean, inputs=age, rows=rows), 0.5, 0.05)
    assert v["failures"] == [], v["failures"]
