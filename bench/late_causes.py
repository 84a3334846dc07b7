"""Why a live loop's late ticks were late: the kernel's scheduler trace beside the loop's ticks.

``pointfence bench loop --late-causes`` (Linux, as root: the kernel's tracefs) records the
scheduler's switch and wake-up events and the interrupts (ftrace, stamped on CLOCK_MONOTONIC, the
clock of ``time.perf_counter`` and so of the loop) over the measured seconds, and sorts every tick that
started more than ``threshold_us`` after its deadline by what the loop's thread did between
its clock's wake-up (``clock.RealClock`` sleeps until ``spin_s`` before the deadline, then
spins) and the tick's start:

* ``lock``: it woke in time, then slept again before the tick: it waited for the interpreter
  lock (or another lock) that a thread of the service's process held. ``lock_holders`` names the
  process's threads that ran on a core while it waited (the holder is among them; ``?``: none
  ran, the holder was itself waiting for a core);
* ``timer``: the wake-up itself came later than ``timer_slack_us`` before the deadline: the
  machine (a halted virtual CPU the host did not run in time, a delayed timer interrupt);
* ``cpu``: it was woken in time but waited more than ``cpu_wait_us`` for a core (a task of
  higher priority, or the core's interrupts);
* ``irq``: it woke in time and ran, and an interrupt, an inter-processor interrupt or a page
  fault hit its core before the tick started late (``irq_events`` names them; traced where the
  kernel has those events: device and soft interrupts everywhere, the timer, IPIs and faults on
  x86);
* ``stall``: it woke in time and ran, with no event at all on its core until the tick started
  late: time the guest never saw (the hypervisor took the virtual CPU);
* ``untraced``: no wake-up of the loop's thread from 0.2 ms before its clock's sleep was to end
  until the start (the trace lost events, or the previous tick overran into this one).

Each cause comes with its ticks' count and mean lateness (us). Only the count of late ticks
depends on the threshold; which cause a tick has does not. The trace costs the loop little
(a few events a context switch or interrupt) but is not free: compare runs that all trace, or
none.
"""
from __future__ import annotations

import os
import re
from typing import Optional

import numpy as np

TRACEFS = ("/sys/kernel/tracing", "/sys/kernel/debug/tracing")
EVENTS = "sched:sched_switch sched:sched_wakeup"
#: what else can take the loop's core without a switch, traced where the kernel has the event:
#: device interrupts, soft interrupts, and on x86 the timer interrupt, the IPIs and page faults
INTERRUPTS = ("irq:irq_handler_entry", "irq:softirq_entry", "irq_vectors:local_timer_entry",
              "irq_vectors:reschedule_entry", "irq_vectors:call_function_entry",
              "irq_vectors:call_function_single_entry", "exceptions:page_fault_user",
              "exceptions:page_fault_kernel")

_LINE = re.compile(r"^\s*(.+?)-(\d+)\s+\[(\d+)\]\s+\S+\s+([\d.]+): (\w+): (.*)$")
_SWITCH = re.compile(r"prev_comm=(.*?) prev_pid=(\d+) prev_prio=\d+ prev_state=(\S+) ==> next_comm=(.*?) next_pid=(\d+)")
_WAKE = re.compile(r"comm=(.*?) pid=(\d+) ")


def tracefs() -> tuple:
    """(path of the kernel's tracefs, None) where this process may trace; (None, why not)."""
    for path in TRACEFS:
        if os.path.exists(os.path.join(path, "set_event")):
            if not os.access(os.path.join(path, "set_event"), os.W_OK):
                return None, f"{path} is not writable: run as root to trace the scheduler"
            return path, None
    return None, ("no tracefs at " + " or ".join(TRACEFS) +
                  " (Linux only; mount it: mount -t tracefs nodev /sys/kernel/tracing)")


class SchedTrace:
    """The scheduler's switch and wake-up events between ``start()`` and ``stop()`` (which
    returns the trace's text), stamped on CLOCK_MONOTONIC. Tracing is the machine's (one trace
    at a time); ``stop`` leaves the tracer as it found it (its events, clock, buffer size and
    on/off), its buffer emptied.
    ``buffer_kb``: per-core buffer (a 2-core machine writes about 5 MB a second of loop)."""

    def __init__(self, buffer_kb: int = 65536):
        self.path, self.problem = tracefs()
        self.buffer_kb = int(buffer_kb)
        self._saved: dict = {}
        self.started = False

    def _write(self, name: str, value: str) -> None:
        with open(os.path.join(self.path, name), "w") as fh:
            fh.write(value)

    def _read(self, name: str) -> str:
        with open(os.path.join(self.path, name)) as fh:
            return fh.read()

    def start(self) -> None:
        if self.path is None:
            raise RuntimeError(f"cannot trace the scheduler: {self.problem}")
        self._saved = {"tracing_on": self._read("tracing_on").strip(),
                       "trace_clock": re.search(r"\[(\w+)\]", self._read("trace_clock")).group(1),
                       "buffer_size_kb": self._read("buffer_size_kb").split()[0],
                       "set_event": " ".join(self._read("set_event").split())}
        self._write("tracing_on", "0")
        self._write("trace_clock", "mono")
        self._write("buffer_size_kb", str(self.buffer_kb))
        self._write("trace", "")
        have = set(self._read("available_events").split())
        self._write("set_event", " ".join([EVENTS] + [e for e in INTERRUPTS if e in have]))
        self.started = True
        self._write("tracing_on", "1")

    def pause(self) -> None:
        """Stop recording events (what was recorded stays for ``stop``)."""
        self._write("tracing_on", "0")

    def stop(self) -> str:
        self._write("tracing_on", "0")
        self.started = False
        try:
            return self._read("trace")
        finally:       # the tracer as it was (the events it had, on or off), the buffer emptied
            self._write("set_event", "")
            self._write("trace", "")
            for name in ("trace_clock", "buffer_size_kb", "set_event", "tracing_on"):
                if self._saved.get(name):
                    self._write(name, self._saved[name])


def parse(text: str) -> tuple:
    """The trace's events as (times s, cpus, kinds: 0 switch / 1 wake-up / 2 other, a, b,
    prev_state): for a switch a = the task that ran until it, b = the task after it; for a
    wake-up a = b = the task woken; tasks as (pid, comm); for another event (an interrupt) a = the
    task it interrupted, b = the event's name."""
    rows = []
    for line in text.splitlines():
        m = _LINE.match(line)
        if m is None:
            continue
        event, fields = m.group(5), m.group(6)
        if event == "sched_switch":
            s = _SWITCH.search(fields)
            if s is None:
                continue
            row = (0, (int(s.group(2)), s.group(1)), (int(s.group(5)), s.group(4)), s.group(3))
        elif event == "sched_wakeup":
            w = _WAKE.search(fields)
            if w is None:
                continue
            task = (int(w.group(2)), w.group(1))
            row = (1, task, task, "")
        else:
            row = (2, (int(m.group(2)), m.group(1).strip()), event, "")
        rows.append((float(m.group(4)), int(m.group(3))) + row)
    t, cpu, kind, a, b, st = zip(*rows) if rows else ((),) * 6
    return np.array(t, float), np.array(cpu, int), np.array(kind, int), list(a), list(b), list(st)


def _ran_between(events: tuple, lo: float, hi: float) -> set:
    """Tasks (pid, comm) that held a core at some time in [lo, hi]: on each core, the task a
    switch after ``lo`` switched away from (it ran from before), and every task switched to
    within [lo, hi] (a lost switch-in still shows as the next switch's ``prev``)."""
    t, cpu, kind, a, b, _ = events
    ran = set()
    for c in np.unique(cpu):
        sw = np.nonzero((cpu == c) & (kind == 0))[0]
        if sw.size == 0:
            continue
        ts = t[sw]
        j = int(np.searchsorted(ts, lo))
        if j < sw.size:
            ran.add(a[sw[j]])
        elif j > 0:
            ran.add(b[sw[j - 1]])
        k = j
        while k < sw.size and ts[k] <= hi:
            ran.add(b[sw[k]])
            k += 1
    return ran


def attribute(events: tuple, starts: np.ndarray, lates: np.ndarray, loop_pid: int, process_pids: set,
              spin_s: float, threshold_us: float = 5.0, timer_slack_us: float = 10.0, cpu_wait_us: float = 5.0) -> dict:
    """Each tick later than ``threshold_us`` (``starts``: the ticks' start on CLOCK_MONOTONIC, s;
    ``lates``: their lateness, s) sorted by cause (see the module docstring). ``loop_pid``: the
    loop thread's id; ``process_pids``: the ids of the service process's threads (the lock's
    possible holders); ``spin_s``: how long before the deadline the clock's sleep ends."""
    t, kind, state = events[0], events[2], events[5]
    pid_a = np.array([p[0] for p in events[3]], int)                       # the task of each event
    pid_b = np.array([p[0] if k != 2 else -1 for k, p in zip(kind, events[4])], int)   # a switch's next
    mine = (kind == 1) & (pid_a == loop_pid)        # the loop's wake-ups
    loop_in = (kind == 0) & (pid_b == loop_pid)     # switches onto the loop
    loop_out = (kind == 0) & (pid_a == loop_pid)    # switches away from it
    wake_t, in_t, out_t = t[mine], t[loop_in], t[loop_out]
    in_cpu = events[1][loop_in]
    out_state = [state[i] for i in np.nonzero(loop_out)[0]]
    other = np.nonzero(kind == 2)[0]
    o_t, o_cpu = t[other], events[1][other]
    counts = {c: 0 for c in ("lock", "timer", "cpu", "irq", "stall", "untraced")}
    late_sum = {c: 0.0 for c in counts}
    holders: dict = {}
    irqs: dict = {}
    span = (t[0], t[-1]) if len(t) else (0.0, -1.0)
    sel = (lates * 1e6 > threshold_us) & (starts > span[0]) & (starts < span[1])
    for start, late in zip(starts[sel], lates[sel]):
        due = start - late
        # the loop's wake-ups from 0.2 ms before its clock's sleep was to end: the first is that
        # sleep's end, any later one the end of a wait for a lock
        w = wake_t[(wake_t >= due - spin_s - 200e-6) & (wake_t <= start)]
        if w.size == 0:
            cause = "untraced"
        elif w[0] > due - spin_s + timer_slack_us * 1e-6:
            cause = "timer"
        else:
            outs = np.nonzero((out_t > w[0]) & (out_t < start))[0]
            blocked = [i for i in outs if out_state[i].startswith(("S", "D"))]
            if blocked:
                cause = "lock"
                t_block = out_t[blocked[0]]
                later = w[w > t_block]
                t_free = later[-1] if later.size else start
                names = sorted({f"{comm}" for pid, comm in _ran_between(events, t_block, t_free)
                                if pid in process_pids and pid != loop_pid}) or ["?"]
                key = " + ".join(names)
                holders[key] = holders.get(key, 0) + 1
            else:
                ins = in_t[(in_t >= w[0]) & (in_t <= start)]
                waited = (ins[0] - w[0]) if ins.size else 0.0
                cause = "cpu" if waited > cpu_wait_us * 1e-6 else "stall"
                j = int(np.searchsorted(in_t, start)) - 1      # the core the loop ran on
                if cause == "stall" and j >= 0:
                    hit = other[(o_t > w[0]) & (o_t <= start) & (o_cpu == in_cpu[j])]
                    if hit.size:
                        cause = "irq"
                        key = " + ".join(sorted({events[4][i] for i in hit}))
                        irqs[key] = irqs.get(key, 0) + 1
        counts[cause] += 1
        late_sum[cause] += float(late)
    n = int(sel.sum())
    return {"threshold_us": threshold_us, "late_ticks": n, "ticks": int(((starts > span[0]) & (starts < span[1])).sum()),
            **{f"{c}_ticks": counts[c] for c in counts},
            **{f"{c}_late_us_mean": round(late_sum[c] / counts[c] * 1e6, 1) for c in counts if counts[c]},
            "lock_holders": dict(sorted(holders.items(), key=lambda kv: -kv[1])),
            "irq_events": dict(sorted(irqs.items(), key=lambda kv: -kv[1]))}


def thread_ids() -> dict:
    """This process's threads: {thread id: name as the kernel knows it}."""
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/comm") as fh:
                out[int(tid)] = fh.read().strip()
        except OSError:
            continue
    return out


class RunTrace:
    """The scheduler trace of a ``runner.LiveRun``'s measured seconds: ``begin()`` right after the
    run's ``mark()``, ``end()`` (stops tracing: cheap) before its ``timing()``, while its threads
    live; ``result()`` once the run has stopped (reading and sorting the trace is seconds of
    Python, which would make the run's own ticks late) gives ``attribute``'s figures for the
    loop's ticks between ``begin`` and ``end``, or {"error": why} where the machine cannot be
    traced (the run goes on untraced)."""

    def __init__(self, run, threshold_us: float = 5.0):
        self.run = run
        self.threshold_us = float(threshold_us)
        self.trace = SchedTrace()
        self._since = 0
        self._taken: Optional[tuple] = None

    def begin(self) -> None:
        if self.trace.path is None:
            return
        self._since = self.run.loop.ticks
        self.trace.start()

    def end(self) -> None:
        if self.trace.path is None:
            return
        self.trace.pause()
        loop = self.run.loop
        starts, lates = loop.periodic.recent_starts(self._since)
        self._taken = (starts, lates, loop.thread_id, set(thread_ids()), getattr(loop.clock, "spin_s", 0.0))

    def abort(self) -> None:
        """Leave the machine's tracer as it was if the run failed between ``begin`` and ``result``."""
        if self.trace.path is not None and self.trace.started:
            self.trace.stop()

    def result(self) -> dict:
        if self.trace.path is None:
            return {"error": f"not traced: {self.trace.problem}"}
        if self._taken is None:
            raise RuntimeError("RunTrace.result() before end()")
        starts, lates, loop_id, pids, spin = self._taken
        text = self.trace.stop()
        return attribute(parse(text), starts, lates, loop_id, pids, spin, self.threshold_us)
