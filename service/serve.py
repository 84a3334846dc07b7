"""`pointfence serve`: the live service with authenticated UDP clients as its masters.

    pointfence serve --new-key pf.key                      # write a fresh 32-byte key and exit
    pointfence serve --key-file pf.key [--config F] [--clients N] [--port 47800] [--bind 127.0.0.1]
                     [--timeout-ms 50] [--duration S] [--itp 127.0.0.1:36000 --itp-slots 0,1]
                     [--ros2-masters MTMR[,MTML] [--ros2-master-slots 0,1] [--ros2-pedal decouples|couples]]
                     [--control-port 47801 [--control-token FILE] | --no-control] [--record RUN.mcap]

Each client (``pointfence.clients.Client``, the C SDK, ``pointfence device-sim``) opens a
session with a HELLO tagged with the key and then drives one master slot, i.e. one proxy and
one robot, of the haptic loop; ``--clients`` slots exist (default ``[service] proxies``). A
client silent for longer than its timeout is dropped (its robot holds, its force ramps to zero).
Status lines go to stderr every ``--status-every`` s; the final status (sessions, per-reason
rejection counters, loop timing) is printed as JSON on exit and written to ``--stats-file``.
The local HTTP JSON control API (``control_api.py``; ``pointfence ctl``) listens on
127.0.0.1:``--control-port`` (status, metrics, architecture, engage/disengage, radius, selection).
Every request to it needs this run's token, which serve writes (mode 0600) to ``--control-token``
or ``$XDG_RUNTIME_DIR/pointfence/control-<port>.token`` (``ctl_auth.py``); ``pointfence ctl``
finds it there. A UDP or control port that is in use is an error naming it (never a move to
another port). ``--record FILE.mcap`` streams the run to an MCAP file with ROS 2 schemas while it goes on
(``mcap_record``: depth, camera info, poses, wrenches, events, every tick's input and output;
S8), which ``pointfence replay --recording FILE.mcap`` replays exactly; a ``.pfrec`` name
keeps the older format. ``--ros2-masters`` makes CRTK masters on ROS 2 (a dVRK MTM, a ROS 2
haptic-device driver; ros2/crtk_master.py) drive master slots, as ``--itp`` does for Raven II
masters. At the end of an MCAP recording the run's measures (dissertation 6.1:
safety, submittance, tracking) are computed from the recorded depth (``run_measures``), printed
on stderr, stored in the recording (metadata ``pointfence/measures``, written before it closes)
and added to the final status (``measures``).
"""
from __future__ import annotations

import json
import os
import signal
import stat
import sys
import time
from pathlib import Path

from pointfence.clients import protocol as P
from pointfence.kernels.errors import InputError

from . import limits
from .control_api import DEFAULT_CONTROL_PORT
from .run_measures import after_run, before_close
from .files import write_atomic

DEFAULT_PORT = 47800


def add_arguments(p):
    p.add_argument("--config", default=None, help="scene configuration (TOML); default: the embedded defaults")
    p.add_argument("--key-file", default=os.environ.get("POINTFENCE_KEY_FILE"),
                   help="pre-shared key file (hex on the first line); default $POINTFENCE_KEY_FILE")
    p.add_argument("--new-key", metavar="FILE", default=None,
                   help="write a new random 32-byte key to FILE (mode 600, atomically; an existing FILE is never "
                        "replaced) and exit")
    p.add_argument("--bind", default="127.0.0.1", help="address to listen on (default 127.0.0.1, loopback only)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"UDP port (default {DEFAULT_PORT}; 0: any free port)")
    p.add_argument("--clients", type=int, default=None, help="master slots = proxies (default: [service] proxies)")
    p.add_argument("--timeout-ms", type=int, default=P.DEFAULT_TIMEOUT_MS,
                   help=f"drop a client (and an ITP arm) silent this long (default {P.DEFAULT_TIMEOUT_MS} ms, at most "
                        f"{P.MAX_TIMEOUT_MS}: service/limits.py; clients may ask for less)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: until Ctrl-C)")
    p.add_argument("--status-every", type=float, default=5.0, help="status line period on stderr, s (0: none)")
    p.add_argument("--stats-file", default=None, help="write the final status JSON here")
    p.add_argument("--ready-file", default=None, help="write the bound address here once the loop runs")
    p.add_argument("--architecture", choices=("I", "II", "III"), default=None, help="override [teleop] architecture")
    p.add_argument("--backend", default=None, help="override the configured backend (numpy, opencl, warp)")
    p.add_argument("--device", default=None, help="override the configured device")
    p.add_argument("--itp", default=None, metavar="[HOST:]PORT",
                   help="also accept Raven II ITP master packets here (UNAUTHENTICATED; default off; host defaults to 127.0.0.1)")
    p.add_argument("--itp-slots", default="0", help="master slots the ITP arms 0 and 1 drive, e.g. '0,1' (default '0')")
    p.add_argument("--control-port", type=int, default=DEFAULT_CONTROL_PORT,
                   help=f"local HTTP JSON control API port (default {DEFAULT_CONTROL_PORT}; in use: serve fails; "
                        "0: any free port, see stderr and --ready-file); `pointfence ctl` uses it")
    p.add_argument("--control-token", metavar="FILE", default=None,
                   help="write the control API's per-run token here (mode 0600; default "
                        "$XDG_RUNTIME_DIR/pointfence/control-PORT.token, or /tmp/pointfence-UID/ without "
                        "XDG_RUNTIME_DIR); pass the same FILE to `pointfence ctl --token-file`")
    p.add_argument("--control-bind", default="127.0.0.1", help="control API address: loopback only (default 127.0.0.1)")
    p.add_argument("--no-control", action="store_true", help="no control API")
    p.add_argument("--record", default=None, metavar="FILE.mcap",
                   help="stream the run to this MCAP recording (ROS 2 schemas: depth, poses, forces, events, every "
                        "tick) while it goes on (a crash or kill -9 loses at most the last 0.25 s); `pointfence replay "
                        "--recording FILE.mcap` replays it exactly (a .pfrec FILE: the older format)")
    p.add_argument("--ros2-telemetry", action="store_true",
                   help="publish ROS 2 telemetry for RViz and Foxglove while serving (poses, forces, fixture cloud, "
                        "markers, status on /pointfence/...; [ros2] table; needs pointfence[ros2])")
    p.add_argument("--prerender", type=int, default=0, metavar="FRAMES",
                   help="render this many frames of each synthetic camera before starting and serve them in a loop at "
                        "the camera's rate (rendering live holds Python's interpreter lock for milliseconds a frame, "
                        "which a real camera's driver does not; default 0: render live)")
    p.add_argument("--itp-checksum", choices=("raven", "sum", "none"), default="raven",
                   help="ITP checksum rule: raven (the Raven II's UDPChecksum, default), sum (bytes 0..119), none "
                        "(service/itp.py)")
    p.add_argument("--ros2-masters", default=None, metavar="NS[,NS...]",
                   help="CRTK masters on ROS 2 (pose from NS/measured_cp, force on NS/body/servo_cf), e.g. MTMR,MTML; "
                        "default off (needs pointfence[ros2]; the DDS environment is ROS 2's own)")
    p.add_argument("--ros2-master-slots", default=None, help="master slots the ROS 2 masters drive, in order (default 0,1,...)")
    p.add_argument("--ros2-clutch-topic", default="/footpedals/clutch",
                   help="the foot pedal's sensor_msgs/Joy topic (default /footpedals/clutch)")
    p.add_argument("--ros2-clutch-button", type=int, default=0, help="the pedal's index in the Joy buttons (default 0)")
    p.add_argument("--ros2-pedal", choices=("decouples", "couples"), default="decouples",
                   help="decouples: a clutch pedal, the master drives the robot while it is released (the dVRK's "
                        "/footpedals/clutch; default); couples: while it is pressed (a dead-man pedal)")


def new_key(path) -> None:
    """Write a fresh random 32-byte key (64 hex digits and a newline) to ``path``, mode 0600,
    atomically (``files.write_atomic``: a crash leaves no partial key). An existing file is
    never replaced: that is refused, and should one appear between the check and the write,
    write_atomic keeps it as ``<path>.bak`` (S8)."""
    p = Path(path)
    if p.exists() or p.is_symlink():
        raise InputError(f"{p} exists; refusing to overwrite a key (delete it first, or choose another FILE)")
    try:
        write_atomic(p, os.urandom(32).hex() + "\n", mode=0o600)
    except OSError as e:
        raise InputError(f"cannot write the key file {str(p)!r} ({e.strerror or e}); choose a FILE in an existing "
                         "folder you may write to") from None


def check_args(args) -> None:
    """The command-line values that could weaken safety, against their hard limits
    (``limits.LIMITS``, S7), before anything starts: an InputError names the option."""
    limits.check("serve.timeout_ms", args.timeout_ms, "--timeout-ms")
    if args.clients is not None:
        limits.check("service.proxies", args.clients, "--clients")
    if args.prerender < 0:
        raise InputError(f"--prerender {args.prerender}; expected a number of frames >= 0 (0: render live)")


def load_key(path) -> bytes:
    """The pre-shared key in ``path`` (``clients/keyfile.py``); any failure to read it is an
    InputError naming the file (the command prints it as one line). Only a regular file is
    opened: opening a FIFO nobody writes to would wait for ever."""
    try:
        st = os.stat(path)
    except OSError:
        st = None                        # P.load_key names what is wrong (not found, no access)
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise InputError(f"key file {str(path)!r} is not a regular file; pass the key file that "
                         "`pointfence serve --new-key FILE` wrote")
    try:
        return P.load_key(path)
    except OSError as e:
        raise InputError(f"key file {str(path)!r} cannot be read ({e.strerror or e}); check the file, or make a "
                         "new one with `pointfence serve --new-key FILE`") from None


def _itp_address(spec: str):
    host, _, port = spec.rpartition(":")
    try:
        return (host or "127.0.0.1"), int(port)
    except ValueError:
        raise InputError(f"--itp {spec!r}; expected [HOST:]PORT, e.g. 127.0.0.1:36000") from None


def run(args) -> int:
    check_args(args)
    if args.new_key:
        new_key(args.new_key)
        print(f"pointfence serve: wrote a new 32-byte key to {args.new_key}; give the same file to every client")
        return 0
    if not args.key_file:
        raise InputError("no key: pass --key-file FILE (or set POINTFENCE_KEY_FILE); make one with --new-key FILE")
    psk = load_key(args.key_file)
    from . import config as config_mod
    from .runner import LiveRun
    from .udp_server import UdpHub

    cfg = config_mod.load(args.config)
    slots = args.clients if args.clients is not None else cfg.service.proxies
    max_force = cfg.haptics.max_force if cfg.haptics is not None else 10.0
    try:
        hub = UdpHub(psk, slots, args.bind, args.port, args.timeout_ms, cfg.service.rate_hz, max_force)
    except OSError as e:
        raise InputError(f"cannot listen on udp://{args.bind}:{args.port}: {e}; stop what holds that port, or choose "
                         "another with --port N (0: any free port)") from None
    masters: list = list(hub.masters)
    itp = None
    if args.itp:
        from .itp import ItpReceiver

        host, port = _itp_address(args.itp)
        idx = [int(s) for s in args.itp_slots.split(",") if s.strip()]
        if not 1 <= len(idx) <= 2 or any(not 0 <= i < slots for i in idx) or len(set(idx)) != len(idx):
            hub.close()
            raise InputError(f"--itp-slots {args.itp_slots!r}; expected one or two distinct slots in 0..{slots - 1}")
        try:
            itp = ItpReceiver(host, port, timeout_ms=args.timeout_ms, checksum=args.itp_checksum)
        except OSError as e:
            hub.close()
            raise InputError(f"cannot listen for ITP on udp://{host}:{port}: {e}; choose another --itp [HOST:]PORT") from None
        for arm, i in enumerate(idx):   # the ITP arm replaces the UDP slot i (the hub keeps the rest)
            masters[i] = itp.arm_master(arm, poll_also=hub)
            hub.masters[i].session = _Reserved()
    ros2 = None
    if args.ros2_masters:
        try:
            ros2 = _ros2_masters(args, slots, masters, hub, taken=idx if itp is not None else [])
        except BaseException:
            if itp is not None:
                itp.close()
            hub.close()
            raise
    sources = None
    if args.prerender:
        from .canned import live_sources

        sources = live_sources(cfg, args.prerender)
    try:
        run_ = LiveRun(cfg, masters, architecture=args.architecture, backend=args.backend, device=args.device,
                       sources=sources, record_path=args.record, ros2_telemetry=args.ros2_telemetry or None)
    except BaseException:
        if itp is not None:
            itp.close()
        if ros2 is not None:
            ros2.close()
        hub.close()
        raise
    hub.attach(run_.service)
    stop = {"now": False}

    def on_signal(sig, frame):
        stop["now"] = True

    old = signal.signal(signal.SIGTERM, on_signal)
    itp_warning = itp.status()["warning"] if itp is not None else None   # bound beyond loopback: said at start-up
    print(f"pointfence serve: {slots} master slot(s) on udp://{hub.address[0]}:{hub.address[1]} "
          f"(timeout {args.timeout_ms} ms), backend {run_.service.backend.name} on {run_.service.backend.device_name}"
          + (f"; ITP (unauthenticated) on udp://{itp.address[0]}:{itp.address[1]}" if itp else "")
          + (f"; WARNING: {itp_warning}" if itp_warning else "")
          + (f"; ROS 2 masters {', '.join(d.namespace for d in ros2.devices)}" if ros2 else ""), file=sys.stderr)
    t_start = time.monotonic()
    control = None
    try:
        if not args.no_control:   # bound first: a port in use fails the run before the loop starts
            from .control_api import Controller, ControlServer

            extras = {"clients": hub.status, **({"itp": itp.status} if itp is not None else {}),
                      **({"ros2_masters": ros2.status} if ros2 is not None else {})}
            controller = Controller(run_.service, run_.loop, extras=extras)
            control = ControlServer(controller, args.control_bind, args.control_port, args.control_token).start()
            tok = f" --token-file {control.token_file}" if args.control_token else ""
            print(f"pointfence serve: control API on {control.url}, control token in {control.token_file} "
                  f"(pointfence ctl --port {control.address[1]}{tok} status)", file=sys.stderr)
        run_.start()
        run_.wait_ticks(10)
        run_.mark()
        if args.ready_file:
            ready = {"host": hub.address[0], "port": hub.address[1]}
            if control is not None:
                ready["control_port"] = control.address[1]
                ready["control_token_file"] = str(control.token_file)
            dest = Path(args.ready_file)   # written whole, then renamed: a reader never sees it half-written
            part = dest.with_name(dest.name + ".part")
            part.write_text(json.dumps(ready) + "\n")
            os.replace(part, dest)
        last = time.monotonic()
        while not stop["now"]:
            now = time.monotonic()
            if args.duration is not None and now - t_start >= args.duration:
                break
            # this thread wakes at most twice a second (a SIGTERM's stop is noticed within the nap,
            # the loop's end at once): each wake takes the interpreter lock, which a tick that is
            # due then waits for (runner.LiveRun.wait)
            nap = 0.5
            if args.duration is not None:
                nap = min(nap, t_start + args.duration - now)
            if args.status_every:
                nap = min(nap, last + args.status_every - now)
            if run_.loop.finished.wait(max(0.0, nap)) or not run_.loop.running:
                raise RuntimeError(f"haptic loop thread ended: {run_.loop.error}")
            if args.status_every and time.monotonic() - last >= args.status_every:
                last = time.monotonic()
                st = hub.status()
                lt = run_.timing()
                print(f"[serve] sessions {len(st['sessions'])}/{slots}, accepted {st['accepted']}, "
                      f"rejected {st['rejected_total']}, timeouts {st['sessions_timed_out']}, "
                      f"tick p99 {lt.compute_us_p99:.0f} us, misses {lt.misses}", file=sys.stderr)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, old)
        if control is not None:
            control.close()
        mcap = bool(args.record) and str(args.record).endswith(".mcap")
        log = lambda s: print(f"pointfence serve: {s}", file=sys.stderr)   # noqa: E731
        measured: dict = {}       # the 6.1 measures from the recorded depth, stored in the recording before it closes
        run_.stop(before_close=(lambda rec: measured.update(before_close(args.record, rec, log) or {})) if mcap else None)
        status = {"udp": hub.status(), "loop": run_.timing().as_dict(), "service": _jsonable(run_.service.status())}
        if control is not None:
            status["control"] = control.controller.counters()
        if itp is not None:
            status["itp"] = itp.status()
            itp.close()
        if ros2 is not None:
            status["ros2_masters"] = ros2.status()
            ros2.close()
        hub.close()
        if mcap:                  # (a writer gone before the end: measured now, kept beside the file)
            status["measures"] = measured or after_run(args.record, log=log)
        text = json.dumps(status)
        if args.stats_file:
            Path(args.stats_file).write_text(text + "\n")
        print(text)
        sys.stdout.flush()
    return 0


def _ros2_masters(args, slots: int, masters: list, hub, taken):
    """The CRTK masters of ``--ros2-masters`` (one bridge process for all), each replacing the UDP
    slot ``--ros2-master-slots`` gives it (the hub keeps the rest); ``taken``: the ITP's slots."""
    from .ros2.crtk_device import CrtkDevice
    from .ros2.crtk_master import CrtkMasterHost

    names = [s.strip() for s in args.ros2_masters.split(",") if s.strip()]
    spec = args.ros2_master_slots
    try:
        idx = [int(s) for s in spec.split(",") if s.strip()] if spec else list(range(len(names)))
    except ValueError:
        idx = []
    if (not names or len(idx) != len(names) or len(set(idx)) != len(idx)
            or any(not 0 <= i < slots or i in taken for i in idx)):
        raise InputError(f"--ros2-masters {args.ros2_masters!r} --ros2-master-slots {spec!r}: expected one distinct "
                         f"slot in 0..{slots - 1} per namespace" + (f", none of the ITP's {list(taken)}" if taken else ""))
    devices = [CrtkDevice(namespace=ns, clutch_topic=args.ros2_clutch_topic, clutch_button=args.ros2_clutch_button,
                          pedal=args.ros2_pedal, timeout_ms=args.timeout_ms) for ns in names]
    host = CrtkMasterHost(devices)
    for i, m in zip(idx, host.masters):   # the ROS 2 master replaces the UDP slot i
        m.poll_also = hub
        masters[i] = m
        hub.masters[i].session = _Reserved()
    return host


class _Reserved:
    """Marks a UDP slot taken by the ITP adapter or a ROS 2 master (never a real session)."""

    id = -1
    has_state = False


def _jsonable(d):
    return json.loads(json.dumps(d, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def main(argv=None) -> int:
    """``python -m pointfence.service.serve`` (the same as ``pointfence serve``)."""
    import sys

    from pointfence.cli import main as pointfence_main

    return pointfence_main(["serve", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
