"""Choosing an OpenCL device and building programs for it.

PoCL offers two CPU devices: ``pthread`` (a pool of worker threads, one per core: the frame
pipeline's builds) and ``basic`` (runs each kernel in the thread that enqueues it: the haptic
tick's proxy kernel, see ``inline_device``). Unless ``POCL_DEVICES`` is set, both are enabled
before PoCL is first loaded.
"""
from __future__ import annotations

import os
import threading
import warnings
from importlib import resources

from ..errors import BackendUnavailable, KernelError

# IEEE-correct division and sqrt, no FMA contraction (see the pragma in every .cl file):
# the reference backend reproduces the device's float32 arithmetic to the last bit.
BUILD_OPTIONS = ["-cl-fp32-correctly-rounded-divide-sqrt"]


def _cl():
    os.environ.setdefault("POCL_DEVICES", "pthread basic")
    try:
        import pyopencl as cl
    except ImportError as e:  # pragma: no cover - pyopencl is a hard dependency
        raise BackendUnavailable(
            f"the opencl backend needs pyopencl ({e}); install it with: pip install 'pyopencl[pocl]'"
        ) from None
    return cl


_pool_tids: tuple | None = None


def _native_tids() -> set:
    try:
        return {int(t) for t in os.listdir("/proc/self/task")}
    except OSError:   # not Linux: no per-thread priorities to manage
        return set()


def _get_platforms(cl):
    """``cl.get_platforms()``, noting the threads the OpenCL runtimes start on the first call
    (PoCL's worker pool: ``pool_threads``)."""
    global _pool_tids
    if _pool_tids is not None:
        return cl.get_platforms()
    before = _native_tids()
    try:
        platforms = cl.get_platforms()
        for p in platforms:
            p.get_devices()
    finally:
        py = {t.native_id for t in threading.enumerate()}
        _pool_tids = tuple(sorted(_native_tids() - before - py))
    return platforms


def pool_threads() -> tuple:
    """Native thread ids the OpenCL runtimes started in this process (PoCL's worker pool)."""
    _get_platforms(_cl())
    return _pool_tids or ()


def lower_pool_priority(nice: int, idle: bool = False) -> list:
    """Run PoCL's worker pool below the Python threads of the process: at ``nice`` (0-19), or
    with ``idle`` under ``SCHED_IDLE`` (it runs only on cores no other thread wants).

    A Python thread that holds the interpreter lock and is preempted by a worker keeps the lock
    while it waits for a core, and the haptic loop waits with it. A pool at nice 10 rarely
    preempts the service's threads (measured on a 2-core VM with a build running: loop lateness
    p99 0.45 ms -> 0.2 ms, builds no slower); under SCHED_IDLE it never does (2-core EPYC VM, 4
    proxies, frame threads SCHED_FIFO: deadline misses 12 -> 0 in 8 s, builds no slower).
    Neither needs privilege. Returns the threads changed (those that still exist)."""
    done = []
    for tid in pool_threads():
        try:
            if idle and hasattr(os, "SCHED_IDLE"):
                os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
            else:
                os.setpriority(os.PRIO_PROCESS, tid, int(nice))
            done.append(tid)
        except (OSError, AttributeError):
            pass
    return done


def restore_pool_priority(nice: int = 0) -> list:
    """Put PoCL's worker pool back under the normal scheduler at ``nice`` (undoes
    ``lower_pool_priority(..., idle=True)``: builds then get their share of a busy machine).
    Leaving SCHED_IDLE needs privilege or an ``RLIMIT_NICE`` that allows ``nice``; returns the
    threads changed (none where refused)."""
    done = []
    for tid in pool_threads():
        try:
            if hasattr(os, "SCHED_OTHER"):
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, tid, int(nice))
            done.append(tid)
        except (OSError, AttributeError):
            pass
    return done


def list_devices() -> list:
    """(platform name, device name, device type) of every OpenCL device found."""
    cl = _cl()
    out = []
    try:
        platforms = _get_platforms(cl)
    except cl.Error:
        return out
    for p in platforms:
        for d in p.get_devices():
            out.append((p.name.strip(), d.name.strip(), cl.device_type.to_string(d.type)))
    return out


def select_device(spec: str | None = None):
    """The OpenCL device for ``spec``.

    ``spec`` None or "" picks PoCL's CPU device (installed by pip with pyopencl[pocl]); else
    it is matched case-insensitively against "<platform> <device>" (e.g. "nvidia", "H100"),
    where PoCL's platform ("Portable Computing Language") also answers to "pocl"; "#k" at the
    end picks the k-th match. PoCL's in-thread ``basic`` device comes after every other match
    unless ``spec`` names it.
    """
    cl = _cl()
    try:
        platforms = _get_platforms(cl)
    except cl.Error as e:
        platforms = []
        err = str(e)
    else:
        err = ""
    devices = [(p, d) for p in platforms for d in p.get_devices()]
    spec = (spec or os.environ.get("POINTFENCE_OPENCL_DEVICE") or "").strip()
    which = 0
    if "#" in spec:
        spec, k = spec.rsplit("#", 1)
        which = int(k)
    if not spec:
        matches = [(p, d) for p, d in devices if "portable computing language" in p.name.lower() or "pocl" in p.name.lower()]
        matches = [m for m in matches if m[1].type & cl.device_type.CPU] or matches
        matches = _working_pocl_first(matches)
    else:
        needle = spec.lower()
        matches = [(p, d) for p, d in devices if needle in _names(p, d)]
    if "basic" not in spec.lower():
        matches.sort(key=lambda m: _is_pocl_basic(m[1]))
    if len(matches) <= which:
        found = "; ".join(f"{p.name.strip()}: {d.name.strip()}" for p, d in devices) or f"none ({err or 'no OpenCL platform'})"
        want = repr(spec) if spec else "PoCL's CPU device"
        raise BackendUnavailable(
            f"no OpenCL device matches {want}{f' #{which}' if which else ''}. Found: {found}. "
            "PoCL comes with: pip install 'pyopencl[pocl]'; for NVIDIA GPUs install the driver's OpenCL ICD"
        )
    return matches[which][1]


_compiles: dict = {}


def _compiler_works(platform, device) -> bool:
    """Whether ``platform``'s compiler builds a small kernel for ``device`` with pointfence's
    options (once per platform and process). PoCL 3.0's LLVM 14, the one pyopencl's wheel
    brings, does not know CPUs newer than it (AMD Zen 5: "unknown target CPU 'generic'") and
    fails every build there, while a newer PoCL beside it works."""
    key = (platform.name, platform.version)
    if key not in _compiles:
        cl = _cl()
        src = "__kernel void pf_probe(__global float *a) { a[get_global_id(0)] = sqrt(a[get_global_id(0)]); }"
        try:
            with _BUILD_LOCK, warnings.catch_warnings():
                warnings.simplefilter("ignore", cl.CompilerWarning)
                cl.Program(cl.Context([device]), src).build(options=BUILD_OPTIONS)
            _compiles[key] = True
        except cl.Error:
            _compiles[key] = False
    return _compiles[key]


def _working_pocl_first(matches: list) -> list:
    """PoCL's CPU devices for the default choice, ordered: where several PoCL installations are
    found (pyopencl's own and a distribution's), a release build before a build with
    assertions (its compiler is slower), and a platform whose compiler works on this CPU
    (``_compiler_works``) before one whose does not. With one PoCL nothing is probed: a failing
    build then says what to do (``build_source``)."""
    if len({p.int_ptr for p, _ in matches}) < 2:
        return matches
    ranked = sorted(matches, key=lambda m: "release" not in m[0].version.lower())
    for p, d in ranked:                     # (probed in order, up to the first platform that works)
        if _compiler_works(p, d):
            return [m for m in ranked if m[0].int_ptr == p.int_ptr] + [m for m in ranked if m[0].int_ptr != p.int_ptr]
    return ranked


def _names(platform, device) -> str:
    """What a device spec is matched against: "<platform> <device>", lower case, and "pocl" for
    PoCL's devices (its platform is "Portable Computing Language")."""
    names = f"{platform.name} {device.name}".lower()
    return names + " pocl" if "portable computing language" in names else names


def _is_pocl(device) -> bool:
    name = device.platform.name.lower()
    return "portable computing language" in name or "pocl" in name


def _is_pocl_basic(device) -> bool:
    return _is_pocl(device) and device.name.strip().lower().startswith("basic")


def inline_device(device):
    """PoCL's ``basic`` device when ``device`` is PoCL's ``pthread`` CPU device, else None.

    ``basic`` runs a kernel in the calling thread: a haptic tick's proxy kernel then never waits
    for a worker thread that a frame build keeps busy, and skips the hand-off to the pool (the
    launch + wait costs about 80 us instead of 200 us on a 2-core VM). Both devices address the
    same host memory, so buffers created with ``USE_HOST_PTR`` over one host array are shared
    without copies (``OpenCLPipeline`` checks this once per backend)."""
    cl = _cl()
    if not (_is_pocl(device) and device.type & cl.device_type.CPU) or _is_pocl_basic(device):
        return None
    for d in device.platform.get_devices():
        if _is_pocl_basic(d):
            return d
    return None


def compiler_output_wanted() -> bool:
    """Whether successful builds show the compiler's log: ``PYOPENCL_COMPILER_OUTPUT`` set to a
    true value (pyopencl's own switch; ``pointfence --verbose`` sets it)."""
    return os.environ.get("PYOPENCL_COMPILER_OUTPUT", "").strip().lower() in ("1", "true", "yes", "on", "y", "t")


# ``warnings.catch_warnings`` swaps the process-wide filter list: builds in two threads at once
# would restore each other's lists, so one build at a time changes it.
_BUILD_LOCK = threading.Lock()


def build(ctx, *names: str, verbose: bool | None = None):
    """Compile the named .cl files of this package into one program (see ``build_source``)."""
    src = "\n".join(resources.files(__package__).joinpath(n).read_text() for n in names)
    return build_source(ctx, src, "+".join(names), BUILD_OPTIONS, verbose=verbose)


def build_source(ctx, src: str, label: str, options=(), verbose: bool | None = None):
    """Compile OpenCL C ``src`` (called ``label`` in messages) for the devices of ``ctx``.

    A successful build is quiet: the compiler's notes (PoCL logs ABI remarks on every build) stay
    in the program, ``build_log(program)``, and are shown as a ``pyopencl.CompilerWarning`` only
    when ``verbose`` (None: ``compiler_output_wanted()``). A failed build raises ``KernelError``
    whose message holds the compiler's log."""
    cl = _cl()
    if verbose is None:
        verbose = compiler_output_wanted()
    with _BUILD_LOCK, warnings.catch_warnings():
        warnings.simplefilter("ignore", cl.CompilerWarning)
        try:
            prg = cl.Program(ctx, src).build(options=list(options))
        except cl.Error as e:
            devices = ", ".join(d.name.strip() for d in ctx.devices)
            if "unknown target CPU" in str(e) and any(_is_pocl(d) for d in ctx.devices):
                raise KernelError(
                    f"building the OpenCL program {label} for {devices} failed: this PoCL's compiler does not know "
                    f"this CPU ({e}). Install a newer PoCL beside it, for example your distribution's "
                    "(Debian/Ubuntu: apt install pocl-opencl-icd); pointfence then picks the one that works"
                ) from None
            raise KernelError(
                f"building the OpenCL program {label} for {devices} failed (options {' '.join(options) or 'none'}); "
                f"the compiler said:\n{e}\nThe device's OpenCL compiler rejected pointfence's kernels: choose another "
                "device (POINTFENCE_OPENCL_DEVICE, `pointfence backends` lists them) and report this message"
            ) from None
    if verbose:
        log = build_log(prg)
        if log:
            warnings.warn(f"OpenCL program {label} built; the compiler said:\n{log}", cl.CompilerWarning, stacklevel=3)
    return prg


def build_log(program) -> str:
    """The compiler's log of every device ``program`` was built for ("" when all were silent)."""
    cl = _cl()
    logs = []
    for d in program.devices:
        log = (program.get_build_info(d, cl.program_build_info.LOG) or "").strip()
        if log:
            logs.append(f"{d.name.strip()}:\n{log}")
    return "\n".join(logs)
