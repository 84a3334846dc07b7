"""The scene configuration file (TOML): backend, workspace, cameras, fixture settings, haptics,
teleoperation, robot and the real-time service's timing.

The schema is ``settings.py`` (one dataclass per table: keys, types, defaults, docs); this
module reads the file, checks it against the schema (``schema.parse_table``: a misspelt key is
an error that names it and suggests the closest known one, a wrong type names the value and
the expected type, and every value that could weaken safety must lie within its hard limit of
``service/limits.py``, SAFETY.md S7), and builds what the service runs on: the cameras, the
pipeline's and the proxy's parameters. Units: metres, seconds; transforms are 16 numbers,
row-major, ``T_world_cam`` mapping camera coordinates to the world (robot base) frame. See
README.md for the settings table.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Optional

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from pointfence.kernels.camera import Camera, NoiseModel
from pointfence.kernels.errors import InputError
from pointfence.kernels.params import PipelineParams, RadiusModel, Selection, Workspace

from .robot.settings import RobotConfig
from .schema import parse_table
from .settings import (ADAPTIVE_MARGIN, ARCHITECTURES, DEFAULT_R3, CameraTable, Ros2Table, SceneTable, SelectTable,
                       ServiceConfig, TeleopConfig)

__all__ = ["ADAPTIVE_MARGIN", "ARCHITECTURES", "DEFAULT_R3", "CameraConfig", "RobotConfig", "SceneConfig",
           "ServiceConfig", "TeleopConfig", "load", "parse"]

INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "width", "height")


@dataclass
class CameraConfig:
    """One ``[[camera]]`` entry: the camera model and where its frames come from."""

    camera: Camera
    source: str
    rate_hz: float = 30.0
    options: dict = field(default_factory=dict)


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
    robot: RobotConfig = field(default_factory=RobotConfig)
    service: ServiceConfig = field(default_factory=ServiceConfig)
    ros2: Ros2Table = field(default_factory=Ros2Table)     #: [ros2]: telemetry (ros2/telemetry.py)
    cable: Optional[Any] = None            #: [cable]: the grasper controller (cable_settings.CableTable), or None
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
        return self.robot.model != "none" if on is None else bool(on)

    def open_sources(self, **options) -> list:
        """One open depth source per camera, in configuration order."""
        return [self.open_source(c, **options) for c in self.cameras]

    @staticmethod
    def open_source(c, **options):
        """The depth source of camera entry ``c`` (one of ``cameras``), opened; ``options`` add
        to (and override) the entry's own."""
        from pointfence.service.sources import open_source

        return open_source(c.source, c.camera, rate_hz=c.rate_hz, **{**c.options, **options})


def _selection(sel: Optional[SelectTable]) -> Selection:
    if sel is None or sel.kind in ("all", "mask"):
        return Selection("all" if sel is None else sel.kind)
    if sel.kind == "box":
        return Selection("box", box_min=sel.min, box_max=sel.max)
    return Selection("color", color_lo=sel.lo, color_hi=sel.hi)


def _camera(t: CameraTable) -> CameraConfig:
    """The camera of entry ``t``: intrinsics given in full, or from the source."""
    where = f"[[camera]] {t.name!r}"
    kw: dict = {k: getattr(t, k) for k in ("depth_scale", "z_min", "z_max", "max_code", "dist", "T_world_cam")
                if getattr(t, k) is not None}
    if t.depth_step_inv or t.near_reading:
        kw.update(depth_step_inv=float(t.depth_step_inv), near_reading=bool(t.near_reading))
    if t.noise is not None:
        kw["noise"] = NoiseModel(t.noise.a, t.noise.b)
    given = [k for k in INTRINSIC_KEYS if getattr(t, k) is not None]
    scheme = t.source.split(":", 1)[0]
    if len(given) == len(INTRINSIC_KEYS):
        camera = Camera(name=t.name, **{k: getattr(t, k) for k in INTRINSIC_KEYS}, **kw)
    elif scheme == "recorded" and not given:
        from pointfence.service.sources import camera_from_recording

        target = t.source.split(":", 1)[1].split("?", 1)[0]
        base = camera_from_recording(target, name=t.name)
        camera = base if not kw else Camera(**{**base.__dict__, **kw})
    elif scheme in ("openni2", "depthai", "ros2", "realsense") and not given:
        from pointfence.service.sources import open_source

        with open_source(t.source, **dict(t.options)) as probe:  # the device, recording or CameraInfo reports its intrinsics
            base = probe.camera
        camera = Camera(**{**base.__dict__, "name": t.name, **kw})
    elif scheme == "synthetic" and not given:
        from pointfence.service.sources import default_camera

        pose = kw.pop("T_world_cam", None)  # default_camera sets its own look-at pose
        camera = default_camera(t.name, **kw)
        if pose is not None:
            camera = Camera(**{**camera.__dict__, "T_world_cam": pose})
    else:
        missing = [k for k in INTRINSIC_KEYS if getattr(t, k) is None]
        raise InputError(f"{where}: intrinsics incomplete, missing {', '.join(missing)}; give all of "
                         f"{', '.join(INTRINSIC_KEYS)} (recorded, synthetic, openni2, depthai, realsense and ros2 sources may omit all of them)")
    return CameraConfig(camera, t.source, t.rate_hz, dict(t.options))


def parse(doc: dict, path: Optional[str] = None) -> SceneConfig:
    """Validate a configuration already read from TOML (``settings.SceneTable``) and build the
    service's SceneConfig from it."""
    where = path or "config"
    t = parse_table(SceneTable, doc, where)
    fx, mode = t.fixture, t.fixture.mode
    radius = RadiusModel(r_base=fx.radius, adaptive=fx.adaptive, k_sigma=fx.k_sigma,
                         r_max=fx.radius_max if fx.radius_max is not None
                         else fx.radius + (ADAPTIVE_MARGIN if fx.adaptive else 0.0))
    haptics = t.haptics.params(mode)
    reach = PipelineParams.reach(max(DEFAULT_R3, haptics.r3), radius if mode == "fixture" else None)
    cell = t.hash.cell_size if t.hash.cell_size is not None else reach
    if cell < reach:
        raise InputError(f"[hash] cell_size = {cell} m is below the largest query reach {reach} m "
                         f"(R3 {'+ radius_max ' if mode == 'fixture' else ''}); use >= {reach}")
    try:
        workspace = Workspace(t.workspace.min, t.workspace.max)
    except InputError as e:
        raise InputError(f"[workspace]: {e}") from None
    pipeline = PipelineParams(workspace=workspace, selection=_selection(fx.select), radius=radius, cell_size=cell,
                              motion=t.motion.model())
    if not t.camera:
        raise InputError(f"{where}: no [[camera]] entries; at least one camera is needed")
    names = [c.name for c in t.camera]
    if len(set(names)) != len(names):
        raise InputError(f"{where}: camera names must be unique, got {names}")
    cameras = [_camera(c) for c in t.camera]
    if t.service.self_filter and t.robot.model == "none":
        raise InputError('[service] self_filter = true needs a robot model with kinematics ([robot] model "raven2" or '
                         '"point-mass"); the ideal robot ("none") has no tool to filter')
    return SceneConfig(backend=t.backend, device=t.device or None, mode=mode, pipeline=pipeline, cameras=cameras,
                       path=path, haptics=haptics, teleop=t.teleop, robot=t.robot, service=t.service,
                       ros2=t.ros2, cable=t.cable, cell_size_given=t.hash.cell_size is not None)


def load(path=None) -> SceneConfig:
    """Read and validate a configuration file; ``None`` loads the embedded defaults."""
    if path is None:
        return parse(tomllib.loads(embedded_defaults()), "embedded defaults")
    p = Path(path)
    if not p.is_file():
        raise InputError(f"configuration file {str(p)!r} not found; pass an existing .toml file (see README.md)")
    try:
        doc = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{p}: not valid TOML: {e}") from None
    return parse(doc, str(p))


def embedded_defaults() -> str:
    """The embedded scene (``defaults.toml``): what it sets beside the schema's defaults."""
    return resources.files("pointfence.service").joinpath("defaults.toml").read_text()
