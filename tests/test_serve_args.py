"""`pointfence serve`'s command line: values that could weaken safety are held to hard limits
(service/limits.py, S7) before anything starts; a bad key file is a one-line error; --new-key
writes the key atomically, mode 0600, and never replaces a file (S8); an ITP adapter bound
beyond loopback says so on the start-up line, and its packets reach the service through its
receiver thread. Loopback only."""
import argparse
import json
import os
import signal
import socket
import stat
import subprocess
import sys
import threading
import time

import pytest

from pointfence.clients import protocol as P
from pointfence.kernels.errors import InputError
from pointfence.service import serve
from pointfence.service.limits import LIMITS

from service_cases import needs_opencl

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def parse(*argv):
    p = argparse.ArgumentParser()
    serve.add_arguments(p)
    return p.parse_args(list(argv))


def run_cli(*argv, timeout=60):
    return subprocess.run([sys.executable, "-m", "pointfence.service.serve", *argv], env=ENV, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.parametrize("argv, message", [
    (["--timeout-ms", "5000"], r"--timeout-ms = 5000 ms is above its hard limit of 1000 ms .*use a value <= 1000"),
    (["--timeout-ms", "1000000000"], r"--timeout-ms = 1e\+09 ms is above its hard limit of 1000 ms"),
    (["--timeout-ms", "0"], r"--timeout-ms = 0 ms is below its hard limit of 1 ms"),
    (["--timeout-ms", "-50"], r"--timeout-ms = -50 ms is below its hard limit"),
    (["--clients", "0"], r"--clients = 0 is below its hard limit of 1"),
    (["--clients", "100000"], r"--clients = 100000 is above its hard limit of 4096"),
])
def test_values_beyond_their_hard_limit_are_refused_before_anything_starts(argv, message, tmp_path):
    # no key file, no port, no configuration is looked at first: the value itself is the error
    with pytest.raises(InputError, match=message):
        serve.run(parse(*argv, "--key-file", str(tmp_path / "absent.key"), "--config", str(tmp_path / "absent.toml")))


def test_the_client_timeout_limit_is_the_protocols():
    lim = LIMITS["serve.timeout_ms"]
    assert lim.hi == P.MAX_TIMEOUT_MS and lim.lo == 1 and lim.integer
    serve.check_args(parse("--timeout-ms", str(P.MAX_TIMEOUT_MS)))
    serve.check_args(parse("--timeout-ms", "1", "--clients", "4096"))


def test_command_line_errors_are_one_line_without_a_traceback(tmp_path):
    loose = tmp_path / "loose.key"
    loose.write_text("ab" * 32 + "\n")
    loose.chmod(0o644)
    fifo = tmp_path / "fifo.key"
    os.mkfifo(fifo)                        # opening it would wait for a writer that never comes
    cases = [(["--timeout-ms", "60000"], "--timeout-ms = 60000 ms is above its hard limit of 1000 ms"),
             (["--key-file", str(tmp_path / "absent.key")], "not found; create one with `pointfence serve --new-key"),
             (["--key-file", str(loose)], "has mode 0644"),
             (["--key-file", str(fifo)], "is not a regular file"),
             (["--key-file", str(tmp_path)], "is not a regular file"),
             (["--new-key", str(tmp_path / "no" / "such" / "folder" / "pf.key")], "cannot write the key file")]
    for argv, fragment in cases:
        r = run_cli(*argv, "--no-control")
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 1 and len(lines) == 1 and "Traceback" not in r.stderr, (argv, r.stderr)
        assert lines[0].startswith("pointfence serve: error: ") and fragment in lines[0], (argv, lines)


def test_new_key_is_private_and_never_replaces_a_file(tmp_path):
    key = tmp_path / "pf.key"
    old = os.umask(0)                      # even with a permissive umask
    try:
        serve.new_key(key)
    finally:
        os.umask(old)
    assert stat.S_IMODE(key.stat().st_mode) == 0o600 and len(P.load_key(key)) == 32
    first = key.read_bytes()
    with pytest.raises(InputError, match="exists; refusing to overwrite a key"):
        serve.new_key(key)
    assert key.read_bytes() == first
    link = tmp_path / "link.key"           # a dangling symbolic link: writing through it is refused too
    link.symlink_to(tmp_path / "elsewhere.key")
    with pytest.raises(InputError, match="exists; refusing to overwrite a key"):
        serve.new_key(link)
    assert not (tmp_path / "elsewhere.key").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.key", "pf.key"]


def test_new_key_interrupted_half_way_leaves_no_key_file(tmp_path, monkeypatch):
    """A full disk during the write: no partial (empty) key file is left behind, which a later
    --new-key would refuse to replace and every client would fail to load."""
    real_fdopen = os.fdopen

    class FullDisk:
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, data):
            raise OSError(28, "No space left on device")

        def __getattr__(self, name):
            return getattr(self.f, name)

    monkeypatch.setattr(os, "fdopen", lambda *a, **k: FullDisk(real_fdopen(*a, **k)))
    key = tmp_path / "pf.key"
    with pytest.raises(InputError, match="cannot write the key file .*No space left on device"):
        serve.new_key(key)
    assert list(tmp_path.iterdir()) == []


class _Lines:
    """A child's stderr, read line by line in a thread (a silent child never blocks the test)."""

    def __init__(self, stream):
        self.lines = []
        self.th = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self.th.start()

    def _read(self, stream):
        for line in stream:
            self.lines.append(line)

    def wait_for(self, fragment, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            hit = next((ln for ln in list(self.lines) if fragment in ln), None)
            if hit is not None:
                return hit
            time.sleep(0.05)
        raise AssertionError(f"no line with {fragment!r} in {timeout} s: {''.join(self.lines)[-2000:]}")


@needs_opencl
def test_itp_bound_beyond_loopback_warns_on_the_start_up_line_and_its_packets_arrive(tmp_path):
    from pointfence.bench.e2e import LIGHT_SCENE
    from pointfence.service.itp import pack_itp

    key = tmp_path / "pf.key"
    serve.new_key(key)
    scene = tmp_path / "scene.toml"
    scene.write_text(LIGHT_SCENE + "[service]\nrobot_watchdog_s = 0.1\n")
    ready, stats = tmp_path / "ready.json", tmp_path / "stats.json"
    proc = subprocess.Popen([sys.executable, "-m", "pointfence.service.serve", "--key-file", str(key), "--port", "0",
                             "--no-control", "--config", str(scene), "--clients", "1", "--itp", "0.0.0.0:0",
                             "--timeout-ms", "1000", "--ready-file", str(ready), "--stats-file", str(stats),
                             "--duration", "120", "--status-every", "0", "--prerender", "5"],
                            env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.bind(("127.0.0.1", 0))
    try:
        err = _Lines(proc.stderr)
        line = err.wait_for("master slot(s) on udp://", 120)
        assert "ITP (unauthenticated) on udp://0.0.0.0:" in line
        assert "WARNING: ITP adapter bound to 0.0.0.0" in line and "UNAUTHENTICATED" in line, line
        port = int(line.split("ITP (unauthenticated) on udp://0.0.0.0:")[1].split(";")[0].split()[0])
        end = time.monotonic() + 120
        while not ready.exists() and proc.poll() is None and time.monotonic() < end:
            time.sleep(0.05)
        assert ready.exists(), "".join(err.lines)[-2000:]
        q = [[0, 0, 0, 1], [0, 0, 0, 1]]
        for s in range(1, 301):                          # 0.3 mm down in 1 um steps, pedal down
            tx.sendto(pack_itp(s, [[0, 0, -1], [0, 0, 0]], q, surgeon_mode=1), ("127.0.0.1", port))
            time.sleep(0.001)
        time.sleep(0.3)
    finally:
        tx.close()
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    st = json.loads(stats.read_text())
    itp = st["itp"]
    assert itp["receiver"] == "thread" and itp["exposed"] is True
    assert itp["accepted"] > 0 and itp["locked_to"][0] == "127.0.0.1", itp
    assert st["loop"]["ticks"] > 0
