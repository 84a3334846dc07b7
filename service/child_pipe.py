"""The control pipe of pointfence's helper processes (the MCAP writer, the ROS 2 telemetry
publisher): length-prefixed pickled tuples on the child's stdin, the first an ``("init", dict)``,
and the end of a child: its stdin closed (the child's cue to finish), a bounded wait, a kill;
for the children steered through shared memory (robot and grasper processes) the end is a stop
flag in their block instead (``stop_by_flag``)."""
from __future__ import annotations

import os
import pickle
import queue
import signal
import struct
import subprocess
import sys
import threading
from typing import Optional

_LEN = struct.Struct("<I")


def send(fh, msg: tuple) -> None:
    """Write control message ``msg`` to the binary stream ``fh`` (and flush it)."""
    data = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
    fh.write(_LEN.pack(len(data)) + data)
    fh.flush()


def receive(fh):
    """The next control message of ``fh``, or None at its end (the other side is gone)."""
    head = fh.read(_LEN.size)
    if len(head) < _LEN.size:
        return None
    data = fh.read(_LEN.unpack(head)[0])
    return pickle.loads(data) if data else None


def control_inbox(fh, name: str) -> "queue.Queue":
    """The child's side: a queue that a daemon thread (named ``name``) fills with the control
    messages of ``fh`` as they come, ending with the ``("close",)`` message or None (the service
    is gone), so that the child's own loop never blocks on its stdin."""
    inbox: queue.Queue = queue.Queue()

    def forward():
        while True:
            msg = receive(fh)
            inbox.put(msg)
            if msg is None or msg[0] == "close":
                return

    threading.Thread(target=forward, name=name, daemon=True).start()
    return inbox


def read_init(fh, child: str, parent: str) -> Optional[dict]:
    """The child's side: the parameters of the first message, which must be ``("init", dict)``;
    None (said on stderr) otherwise. Applies the parameters' ``nice`` to this process."""
    first = receive(fh)
    if first is None or first[0] != "init":
        print(f"{child}: expected an ('init', {{...}}) message on stdin from pointfence's {parent}", file=sys.stderr)
        return None
    p = first[1]
    if p.get("nice"):
        os.nice(int(p["nice"]))
    return p


def end(proc: subprocess.Popen, timeout_s: float) -> bool:
    """The parent's side: close the child's stdin and wait up to ``timeout_s`` for it to finish,
    then kill it. Returns whether it had to be killed."""
    try:
        proc.stdin.close()
    except OSError:
        pass
    try:
        proc.wait(timeout=timeout_s)
        return False
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return True


def stop_by_flag(proc: subprocess.Popen, ctl) -> None:
    """End a child told to stop through shared memory (the robot and grasper processes): it is
    continued first (a stopped child cannot see the request), ``ctl["stop"] = 1`` asks it to
    finish its period (``ctl`` None: its block is gone), then a 2 s wait and a kill."""
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGCONT)
        if ctl is not None:
            ctl["stop"] = 1
    try:
        proc.wait(timeout=2.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=2.0)
