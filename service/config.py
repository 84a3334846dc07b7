"""The scene configuration file (TOML): backend, workspace, cameras, fixture settings, haptics,
teleoperation, robot and the real-time service's timing.

Every key is checked: a misspelt key is an error that names it and suggests the closest
known one, and every value that could weaken safety must lie within its hard limit of
``service/limits.py`` (SAFETY.md S7). Units: metres, seconds; transforms are 16 numbers, row-major, ``T_world_cam``
mapping camera coordinates to the world (robot base) frame. See README.md for the schema.
"""
from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Optional

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

import numpy as np

from pointfence.kernels.camera import Camera, NoiseModel
from pointfence.kernels.errors import InputError
from pointfence.kernels.params import PipelineParams, RadiusModel, Selection, Workspace

from . import limits

TOP_KEYS = {"backend", "device", "workspace", "fixture", "hash", "camera", "haptics", "teleop", "robot", "service",
            "motion"}
WORKSPACE_KEYS = {"min", "max"}
FIXTURE_KEYS = {"mode", "radius", "adaptive", "k_sigma", "radius_max", "select"}
SELECT_KEYS = {"kind", "min", "max", "lo", "hi"}
HASH_KEYS = {"cell_size"}
CAMERA_KEYS = {"name", "source", "fx", "fy", "cx", "cy", "width", "height", "depth_scale", "T_world_cam",
               "noise", "dist", "z_min", "z_max", "max_code", "rate_hz", "options"}
NOISE_KEYS = {"a", "b"}
HAPTICS_KEYS = {"r1", "r2", "r3", "step", "k_spring", "damping", "fir_taps", "max_force", "max_steps"}
TELEOP_KEYS = {"architecture", "scale", "max_robot_speed", "T_world_master", "haptics", "teleop"}
ARCHITECTURES = ("I", "II", "III")
ROBOT_MODELS = ("raven2", "point-mass", "none")
SERVICE_KEYS = {"rate_hz", "proxies", "stale_s", "max_frame_age_s", "force_ramp_s", "max_lateness_s", "recover_s",
                "self_filter", "self_filter_margin", "rt_priority", "frames_rt_priority", "build_nice", "build_idle",
                "robot_process", "robot_watchdog_s"}
#: ``[motion]``: kernels.motion.MotionModel's fields (motion estimation and fixture prediction)
MOTION_KEYS = {"enabled", "latency", "max_age", "capture", "cell", "min_points", "planarity", "count_ratio", "v_min",
               "v_max", "max_gap"}
INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "width", "height")
#: default radius_max - radius with adaptive radii: room for k_sigma * sigma, m
ADAPTIVE_MARGIN = 0.02
#: the proxy's outer band R3 (table 2.1), used for the automatic cell size
DEFAULT_R3 = 0.010


@dataclass
class CameraConfig:
    """One ``[[camera]]`` entry: the camera model and where its frames come from."""

    camera: Camera
    source: str
    rate_hz: float = 30.0
    options: dict = field(default_factory=dict)


@dataclass
class TeleopConfig:
    """``[teleop]``: the fixture architecture (eqs. 3.1-3.3), motion scaling, the robot's speed
    limit and the master-to-world registration; ``haptics`` / ``teleop``: engaged at start."""

    architecture: str = "III"
    scale: float = 0.5
    max_robot_speed: float = 0.05
    T_world_master: np.ndarray = field(default_factory=lambda: np.eye(4))
    haptics: bool = True
    teleop: bool = True


@dataclass
class ServiceConfig:
    """``[service]``: the haptic loop's rate and its degraded-mode thresholds (s)."""

    rate_hz: float = 1000.0
    proxies: int = 1
    stale_s: float = 0.1
    max_frame_age_s: float = 0.5
    force_ramp_s: float = 0.05
    max_lateness_s: float = 0.003
    recover_s: float = 0.1
    #: drop the robot's own tool from every frame (at the frame's capture time) before ingest;
    #: None: on when a robot model is configured ([robot] model other than "none")
    self_filter: Optional[bool] = None
    self_filter_margin: float = 0.003
    #: SCHED_FIFO priority (1-99) of the haptic loop thread where the OS allows it; 0: normal
    rt_priority: int = 80
    #: SCHED_FIFO priority (1-99, below rt_priority) of the frame threads (camera readers, ingest)
    #: where the OS allows it; 0: normal. They take Python's interpreter lock: a holder preempted
    #: by a build would keep the loop waiting for a core's time slice (milliseconds)
    frames_rt_priority: int = 50
    #: nice value (0-19) of PoCL's worker pool, which builds the snapshots (opencl backend)
    build_nice: int = 10
    #: PoCL's worker pool runs SCHED_IDLE: builds use only the CPU time no service thread wants
    build_idle: bool = True
    #: live runs step simulated robots in their own process on their own 1 kHz clock, as a real
    #: arm's controller runs (robot/hosted.py); false: in the haptic tick (offline runs always do)
    robot_process: bool = True
    #: the hosted robot process's watchdog (``robot_process``): silent or unread for longer, every
    #: arm reads FAULT (s; at most 0.25, ``limits.LIMITS``; robot/hosted.py ``RobotHost(timeout_s=...)``)
    robot_watchdog_s: float = 0.05


@dataclass
class SceneConfig:
    """A parsed, validated configuration file."""

    backend: str = "opencl"
    device: Optional[str] = None
    mode: str = "fixture"
    pipeline: PipelineParams = field(default_factory=PipelineParams)
    cameras: list = field(default_factory=list)
    path: Optional[str] = None
    haptics: Optional[Any] = None          #: HapticParams (mode from [fixture] mode)
    teleop: TeleopConfig = field(default_factory=TeleopConfig)
    robot: dict = field(default_factory=lambda: {"model": "raven2"})
    service: ServiceConfig = field(default_factory=ServiceConfig)
    cell_size_given: bool = False

    @property
    def motion(self):
        """``[motion]`` as a ``kernels.motion.MotionModel`` (the pipeline's motion settings)."""
        return self.pipeline.motion

    @property
    def self_filter(self) -> bool:
        """Whether the frame feeder drops the robot's tool from the frames (``[service] self_filter``,
        default: on when a robot model is configured)."""
        on = self.service.self_filter
        return self.robot.get("model", "raven2") != "none" if on is None else bool(on)

    def open_sources(self, **options) -> list:
        """One open depth source per camera, in configuration order."""
        return [self.open_source(c, **options) for c in self.cameras]

    @staticmethod
    def open_source(c, **options):
        """The depth source of camera entry ``c`` (one of ``cameras``), opened; ``options`` add
        to (and override) the entry's own."""
        from pointfence.service.sources import open_source

        return open_source(c.source, c.camera, rate_hz=c.rate_hz, **{**c.options, **options})


def _check_keys(table: dict, known: set, where: str) -> None:
    if not isinstance(table, dict):
        raise InputError(f"{where}: expected a table, got {type(table).__name__}")
    for key in table:
        if key not in known:
            near = difflib.get_close_matches(key, sorted(known), n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            raise InputError(f"{where}: unknown key {key!r}{hint} Known keys: {', '.join(sorted(known))}")


def _num(v: Any, where: str, positive: bool = False, minimum: Optional[float] = None,
         limit: Optional[str] = None) -> float:
    """``v`` as a finite float; ``limit``: the key of its hard limit in ``limits.LIMITS``."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"{where} = {v!r}; expected a finite number")
    if positive and v <= 0:
        raise InputError(f"{where} = {v!r}; expected a number > 0")
    if minimum is not None and v < minimum:
        raise InputError(f"{where} = {v!r}; expected >= {minimum}")
    return float(v) if limit is None else float(limits.check(limit, v, where))


def _int(v: Any, where: str, limit: str) -> int:
    """``v`` as an integer within its hard limit ``limits.LIMITS[limit]``."""
    if isinstance(v, bool) or not isinstance(v, int):
        lim = limits.LIMITS[limit]
        raise InputError(f"{where} = {v!r}; expected an integer >= {lim.lo:g} (at most {lim.hi:g})")
    return int(limits.check(limit, v, where))


def _vec(v: Any, n: int, where: str, limit: Optional[str] = None) -> list:
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise InputError(f"{where} = {v!r}; expected a list of {n} numbers")
    return [_num(x, f"{where}[{i}]", limit=limit) for i, x in enumerate(v)]


def _selection(sel: Any, where: str) -> Selection:
    if sel is None:
        return Selection("all")
    if isinstance(sel, str):
        sel = {"kind": sel}
    _check_keys(sel, SELECT_KEYS, where)
    kind = sel.get("kind", "all")
    if kind == "box":
        return Selection("box", box_min=tuple(_vec(sel.get("min"), 3, f"{where}.min")),
                         box_max=tuple(_vec(sel.get("max"), 3, f"{where}.max")))
    if kind == "color":
        lo, hi = sel.get("lo"), sel.get("hi")
        for name, c in (("lo", lo), ("hi", hi)):
            if not isinstance(c, list) or len(c) != 3 or not all(isinstance(x, int) and 0 <= x <= 255 for x in c):
                raise InputError(f"{where}.{name} = {c!r}; expected [R, G, B] integers 0..255")
        return Selection("color", color_lo=tuple(lo), color_hi=tuple(hi))
    if kind in ("mask", "all"):
        return Selection(kind)
    raise InputError(f"{where}.kind = {kind!r}; expected one of all, box, color, mask")


def _camera(entry: dict, i: int) -> CameraConfig:
    where = f"[[camera]] #{i + 1}"
    _check_keys(entry, CAMERA_KEYS, where)
    name = entry.get("name", f"cam{i}")
    if not isinstance(name, str) or not name:
        raise InputError(f"{where}: name = {name!r}; expected a non-empty string")
    where = f"[[camera]] {name!r}"
    source = entry.get("source")
    if not isinstance(source, str) or ":" not in source:
        raise InputError(f"{where}: source = {source!r}; expected 'synthetic:<scene>', 'recorded:<path>', "
                         "'openni2:<uri or file.oni>' or 'depthai:<device id>'")
    kw: dict = {}
    if "noise" in entry:
        _check_keys(entry["noise"], NOISE_KEYS, f"{where}.noise")
        kw["noise"] = NoiseModel(*(_num(entry["noise"].get(k, d), f"{where}.noise.{k}", minimum=0)
                                   for k, d in (("a", 0.0), ("b", 1.42e-3))))
    for key in ("depth_scale", "z_min", "z_max"):
        if key in entry:
            kw[key] = _num(entry[key], f"{where}.{key}", minimum=0, limit=f"camera.{key}")
    if "max_code" in entry:
        kw["max_code"] = int(_num(entry["max_code"], f"{where}.max_code", positive=True, limit="camera.max_code"))
    if "dist" in entry:
        kw["dist"] = tuple(_vec(entry["dist"], 5, f"{where}.dist"))
    if "T_world_cam" in entry:
        kw["T_world_cam"] = np.array(_vec(entry["T_world_cam"], 16, f"{where}.T_world_cam")).reshape(4, 4)

    given = [k for k in INTRINSIC_KEYS if k in entry]
    scheme = source.split(":", 1)[0]
    if len(given) == len(INTRINSIC_KEYS):
        intr = {k: _num(entry[k], f"{where}.{k}", positive=True, limit=f"camera.{k}" if k in ("width", "height") else None)
                for k in INTRINSIC_KEYS}
        intr["width"], intr["height"] = int(intr["width"]), int(intr["height"])
        camera = Camera(name=name, **intr, **kw)
    elif scheme == "recorded" and not given:
        from pointfence.service.sources import camera_from_recording

        target = source.split(":", 1)[1].split("?", 1)[0]
        base = camera_from_recording(target, name=name)
        camera = base if not kw else Camera(**{**base.__dict__, **kw})
    elif scheme in ("openni2", "depthai") and not given:
        from pointfence.service.sources import open_source

        with open_source(source) as probe:  # the device (or recording) reports its intrinsics
            base = probe.camera
        camera = Camera(**{**base.__dict__, "name": name, **kw})
    elif scheme == "synthetic" and not given:
        from pointfence.service.sources import default_camera

        pose = kw.pop("T_world_cam", None)  # default_camera sets its own look-at pose
        camera = default_camera(name, **kw)
        if pose is not None:
            camera = Camera(**{**camera.__dict__, "T_world_cam": pose})
    else:
        missing = [k for k in INTRINSIC_KEYS if k not in entry]
        raise InputError(f"{where}: intrinsics incomplete, missing {', '.join(missing)}; give all of "
                         f"{', '.join(INTRINSIC_KEYS)} (recorded, synthetic, openni2 and depthai sources may omit all of them)")
    options = entry.get("options", {})
    if not isinstance(options, dict):
        raise InputError(f"{where}.options = {options!r}; expected a table of source options")
    rate = _num(entry.get("rate_hz", 30.0), f"{where}.rate_hz", positive=True, limit="camera.rate_hz")
    return CameraConfig(camera, source, rate, dict(options))


def _haptics(tbl: Any, mode: str):
    from pointfence.kernels.params_haptics import HapticParams

    _check_keys(tbl, HAPTICS_KEYS, "[haptics]")
    kw: dict = {"mode": mode}
    for key in ("r1", "r2", "r3", "step", "max_force"):
        if key in tbl:
            lim = f"haptics.{key}" if f"haptics.{key}" in limits.LIMITS else None  # r1 < r2 < r3 bounds r1, r2
            kw[key] = _num(tbl[key], f"[haptics] {key}", positive=True, limit=lim)
    if "damping" in tbl:
        kw["b"] = _num(tbl["damping"], "[haptics] damping", minimum=0, limit="haptics.damping")
    if "k_spring" in tbl:  # the stiffness of the configured mode: k (rendering) or k_s (fixture)
        kw["k" if mode == "rendering" else "k_s"] = _num(tbl["k_spring"], "[haptics] k_spring", minimum=0,
                                                         limit="haptics.k_spring")
    for key in ("fir_taps", "max_steps"):
        if key in tbl:
            kw[key] = _int(tbl[key], f"[haptics] {key}", f"haptics.{key}")
    try:
        return HapticParams(**kw)
    except InputError as e:
        raise InputError(f"[haptics]: {e}") from None


def _teleop(tbl: Any) -> TeleopConfig:
    _check_keys(tbl, TELEOP_KEYS, "[teleop]")
    arch = tbl.get("architecture", "III")
    if arch not in ARCHITECTURES:
        raise InputError(f"[teleop] architecture = {arch!r}; expected one of {', '.join(repr(a) for a in ARCHITECTURES)}")
    T = np.eye(4)
    if "T_world_master" in tbl:
        T = np.array(_vec(tbl["T_world_master"], 16, "[teleop] T_world_master")).reshape(4, 4)
        R = T[:3, :3]
        if (np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-6 or np.abs(R.T @ R - np.eye(3)).max() > 1e-6
                or np.linalg.det(R) < 0):
            raise InputError(f"[teleop] T_world_master = {T.ravel().tolist()}; expected a rigid transform "
                             "(orthonormal rotation, det +1, last row 0 0 0 1), 16 numbers row-major")
    flags = {}
    for key in ("haptics", "teleop"):
        v = tbl.get(key, True)
        if not isinstance(v, bool):
            raise InputError(f"[teleop] {key} = {v!r}; expected true or false (engaged at start)")
        flags[key] = v
    return TeleopConfig(architecture=arch,
                        scale=_num(tbl.get("scale", 0.5), "[teleop] scale", positive=True, limit="teleop.scale"),
                        max_robot_speed=_num(tbl.get("max_robot_speed", 0.05), "[teleop] max_robot_speed", positive=True,
                                             limit="teleop.max_robot_speed"),
                        T_world_master=T, **flags)


def _robot(tbl: Any) -> dict:
    if not isinstance(tbl, dict):
        raise InputError(f"[robot]: expected a table, got {type(tbl).__name__}")
    model = tbl.get("model", "raven2")
    if model not in ROBOT_MODELS:
        near = difflib.get_close_matches(str(model), ROBOT_MODELS, n=1)
        hint = f"; did you mean {near[0]!r}?" if near else ""
        raise InputError(f"[robot] model = {model!r}{hint} Expected one of {', '.join(repr(m) for m in ROBOT_MODELS)}")
    return {**tbl, "model": model}


def _service(tbl: Any) -> ServiceConfig:
    _check_keys(tbl, SERVICE_KEYS, "[service]")
    d = ServiceConfig()
    kw = {k: _num(tbl.get(k, getattr(d, k)), f"[service] {k}", positive=True, limit=f"service.{k}")
          for k in SERVICE_KEYS - {"proxies", "self_filter", "self_filter_margin", "rt_priority", "frames_rt_priority",
                                   "build_nice", "build_idle", "robot_process"}}
    sf = tbl.get("self_filter")
    if sf is not None and not isinstance(sf, bool):
        raise InputError(f"[service] self_filter = {sf!r}; expected true or false (default: true when a robot model "
                         "is configured)")
    kw["self_filter"] = sf
    kw["self_filter_margin"] = _num(tbl.get("self_filter_margin", d.self_filter_margin), "[service] self_filter_margin",
                                    minimum=0, limit="service.self_filter_margin")
    rt = tbl.get("rt_priority", d.rt_priority)
    if isinstance(rt, bool) or not isinstance(rt, int) or not 0 <= rt <= 99:
        raise InputError(f"[service] rt_priority = {rt!r}; expected an integer 0-99 (SCHED_FIFO priority of the "
                         "haptic loop thread; 0 runs it at normal priority)")
    kw["rt_priority"] = rt
    frt = tbl.get("frames_rt_priority", d.frames_rt_priority)
    if isinstance(frt, bool) or not isinstance(frt, int) or not 0 <= frt <= 99:
        raise InputError(f"[service] frames_rt_priority = {frt!r}; expected an integer 0-99 (SCHED_FIFO priority of the "
                         "camera reader and ingest threads; 0 runs them at normal priority)")
    if frt and rt and frt >= rt:
        raise InputError(f"[service] frames_rt_priority = {frt} is not below rt_priority = {rt}; the frame threads "
                         "must never preempt the haptic loop (e.g. frames_rt_priority = 50, rt_priority = 80)")
    kw["frames_rt_priority"] = frt
    bn = tbl.get("build_nice", d.build_nice)
    if isinstance(bn, bool) or not isinstance(bn, int) or not 0 <= bn <= 19:
        raise InputError(f"[service] build_nice = {bn!r}; expected an integer 0-19 (nice value of PoCL's worker "
                         "threads that build the snapshots; 0 leaves them at normal priority)")
    kw["build_nice"] = bn
    bi = tbl.get("build_idle", d.build_idle)
    if not isinstance(bi, bool):
        raise InputError(f"[service] build_idle = {bi!r}; expected true or false (PoCL's worker threads at SCHED_IDLE; "
                         "false: at nice build_nice)")
    kw["build_idle"] = bi
    rp = tbl.get("robot_process", d.robot_process)
    if not isinstance(rp, bool):
        raise InputError(f"[service] robot_process = {rp!r}; expected true or false (live runs step simulated robots "
                         "in their own process; false: in the haptic tick)")
    kw["robot_process"] = rp
    proxies = _int(tbl.get("proxies", 1), "[service] proxies", "service.proxies")
    if kw["max_frame_age_s"] < kw["stale_s"]:
        raise InputError(f"[service] max_frame_age_s = {kw['max_frame_age_s']} s is below stale_s = {kw['stale_s']} s; "
                         "a camera is reported stale first, then the robot holds")
    return ServiceConfig(proxies=proxies, **kw)


def _motion(tbl: Any):
    from pointfence.kernels.motion import MotionModel

    _check_keys(tbl, MOTION_KEYS, "[motion]")
    kw: dict = {}
    for key, v in tbl.items():
        if key == "enabled":
            if not isinstance(v, bool):
                raise InputError(f"[motion] enabled = {v!r}; expected true or false")
            kw[key] = v
        elif key == "min_points":
            kw[key] = _int(v, "[motion] min_points", "motion.min_points")
        else:
            kw[key] = _num(v, f"[motion] {key}", minimum=0)
    try:
        model = MotionModel(**kw)
    except InputError as e:
        raise InputError(f"[motion]: {e}") from None
    for key, v in kw.items():  # after the model's own relations (v_min <= v_max), which say more
        if f"motion.{key}" in limits.LIMITS:
            limits.check(f"motion.{key}", v, f"[motion] {key}")
    return model


def parse(doc: dict, path: Optional[str] = None) -> SceneConfig:
    """Validate a configuration already read from TOML."""
    where = path or "config"
    _check_keys(doc, TOP_KEYS, where)
    backend = doc.get("backend", "opencl")
    if not isinstance(backend, str):
        raise InputError(f"{where}: backend = {backend!r}; expected a name such as 'opencl' or 'numpy'")
    device = doc.get("device") or None

    ws = doc.get("workspace", {})
    _check_keys(ws, WORKSPACE_KEYS, "[workspace]")
    workspace = Workspace(tuple(_vec(ws.get("min", [-0.5] * 3), 3, "[workspace] min", limit="workspace.min")),
                          tuple(_vec(ws.get("max", [0.5] * 3), 3, "[workspace] max", limit="workspace.max")))

    fx = doc.get("fixture", {})
    _check_keys(fx, FIXTURE_KEYS, "[fixture]")
    mode = fx.get("mode", "fixture")
    if mode not in ("fixture", "rendering"):
        raise InputError(f"[fixture] mode = {mode!r}; expected 'fixture' or 'rendering'")
    r_base = _num(fx.get("radius", 0.02), "[fixture] radius", minimum=0, limit="fixture.radius")
    adaptive = fx.get("adaptive", False)
    if not isinstance(adaptive, bool):
        raise InputError(f"[fixture] adaptive = {adaptive!r}; expected true or false")
    radius = RadiusModel(r_base=r_base, adaptive=adaptive,
                         k_sigma=_num(fx.get("k_sigma", 3.0), "[fixture] k_sigma", minimum=0, limit="fixture.k_sigma"),
                         r_max=_num(fx.get("radius_max", r_base + (ADAPTIVE_MARGIN if adaptive else 0.0)),
                                    "[fixture] radius_max", minimum=0, limit="fixture.radius_max"))
    selection = _selection(fx.get("select"), "[fixture] select")

    haptics = _haptics(doc.get("haptics", {}), mode)
    hs = doc.get("hash", {})
    _check_keys(hs, HASH_KEYS, "[hash]")
    reach = PipelineParams.reach(max(DEFAULT_R3, haptics.r3), radius if mode == "fixture" else None)
    cell = _num(hs.get("cell_size", reach), "[hash] cell_size", positive=True, limit="hash.cell_size")
    if cell < reach:
        raise InputError(f"[hash] cell_size = {cell} m is below the largest query reach {reach} m "
                         f"(R3 {'+ radius_max ' if mode == 'fixture' else ''}); use >= {reach}")
    pipeline = PipelineParams(workspace=workspace, selection=selection, radius=radius, cell_size=cell,
                              motion=_motion(doc.get("motion", {})))

    entries = doc.get("camera", [])
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{where}: no [[camera]] entries; at least one camera is needed")
    cameras = [_camera(e, i) for i, e in enumerate(entries)]
    names = [c.camera.name for c in cameras]
    if len(set(names)) != len(names):
        raise InputError(f"{where}: camera names must be unique, got {names}")
    robot = _robot(doc.get("robot", {}))
    service = _service(doc.get("service", {}))
    if service.self_filter and robot["model"] == "none":
        raise InputError('[service] self_filter = true needs a robot model with kinematics ([robot] model "raven2" or '
                         '"point-mass"); the ideal robot ("none") has no tool to filter')
    return SceneConfig(backend=backend, device=device, mode=mode, pipeline=pipeline, cameras=cameras, path=path,
                       haptics=haptics, teleop=_teleop(doc.get("teleop", {})), robot=robot,
                       service=service, cell_size_given="cell_size" in hs)


def load(path=None) -> SceneConfig:
    """Read and validate a configuration file; ``None`` loads the embedded defaults."""
    if path is None:
        text = resources.files("pointfence.service").joinpath("defaults.toml").read_text()
        return parse(tomllib.loads(text), "embedded defaults")
    p = Path(path)
    if not p.is_file():
        raise InputError(f"configuration file {str(p)!r} not found; pass an existing .toml file (see README.md)")
    try:
        doc = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{p}: not valid TOML: {e}") from None
    return parse(doc, str(p))
