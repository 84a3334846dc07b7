"""The settings schema of the scene configuration: one dataclass per TOML table.

Each field is a key of its table, with its type, its default and a one-line doc with units
(``schema.setting``); ``schema.parse_table`` derives the key and type checks from them, and
the hard limits of ``limits.LIMITS`` apply by the key's dotted name (``service.stale_s``). A
default lives in one place: the field here, or, where the key sets a kernel parameter, that
parameter's own dataclass default (``HapticParams``, ``MotionModel``, ``Workspace``,
``RadiusModel``, ``Camera``), which the field reads. The README's settings table is
``markdown()``'s output and a test keeps the two equal; ``defaults.toml`` (the embedded scene)
sets only what differs from these defaults, which a test checks too.

Units: metres, seconds, newtons; transforms are 16 numbers row-major.
``config.parse`` turns the parsed tables into the service's ``SceneConfig``.
"""
from __future__ import annotations

import re
import typing
from dataclasses import dataclass
from typing import Literal, Optional, Tuple, Union

import numpy as np

from pointfence.kernels.camera import Camera, NoiseModel
from pointfence.kernels.errors import InputError
from pointfence.kernels.motion import MotionModel
from pointfence.kernels.params import RadiusModel, Workspace
from pointfence.kernels.params_haptics import HapticParams

from .cable_settings import CableTable
from .robot.settings import RobotConfig, parse_robot, robot_rows
from .schema import parse_table, rows, setting

Vec3 = Tuple[float, float, float]
Vec16 = Tuple[(float,) * 16]
RGB = Tuple[int, int, int]
#: default radius_max - radius with adaptive radii: room for k_sigma * sigma, m
ADAPTIVE_MARGIN = 0.02
#: the proxy's outer band R3 (table 2.1), used for the automatic cell size
DEFAULT_R3 = 0.010


def rigid(v: tuple, label: str) -> np.ndarray:
    """16 numbers (row-major) as a 4x4 rigid transform; InputError unless orthonormal, det +1."""
    T = np.array(v, dtype=float).reshape(4, 4)
    R = T[:3, :3]
    if (np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-6 or np.abs(R.T @ R - np.eye(3)).max() > 1e-6
            or np.linalg.det(R) < 0):
        raise InputError(f"{label} = {T.ravel().tolist()}; expected a rigid transform (orthonormal rotation, "
                         "det +1, last row 0 0 0 1), 16 numbers row-major")
    return T


def _matrix(v: tuple, label: str) -> np.ndarray:
    return np.array(v, dtype=float).reshape(4, 4)


@dataclass(frozen=True)
class WorkspaceTable:
    """``[workspace]``: the world box (robot base frame) the pipeline keeps; points outside are cropped."""

    TABLE = "workspace"
    min: Vec3 = setting(Workspace.min, doc="lower corner of the world box (m)")
    max: Vec3 = setting(Workspace.max, doc="upper corner of the world box (m)")


@dataclass(frozen=True)
class SelectTable:
    """``[fixture] select``: which points are protected (kernels.params.Selection)."""

    TABLE = "select"
    kind: Literal["all", "box", "color", "mask"] = setting(
        "all", doc="all: every point; box: inside min-max; color: RGB in lo-hi; mask: the frame's mask")
    min: Optional[Vec3] = setting(None, doc="box kind: lower corner (m, world frame)", default_doc="required for box")
    max: Optional[Vec3] = setting(None, doc="box kind: upper corner (m, world frame)", default_doc="required for box")
    lo: Optional[RGB] = setting(None, doc="color kind: lowest [R, G, B] (0-255, inclusive)", lo=0, hi=255,
                                default_doc="required for color")
    hi: Optional[RGB] = setting(None, doc="color kind: highest [R, G, B] (0-255, inclusive)", lo=0, hi=255,
                                default_doc="required for color")

    def __post_init__(self):
        need = {"box": ("min", "max"), "color": ("lo", "hi")}.get(self.kind, ())
        for key in need:
            if getattr(self, key) is None:
                raise InputError(f"[fixture] select.{key} missing; kind = {self.kind!r} needs "
                                 + ("min and max, 3 numbers each (m)" if self.kind == "box" else
                                    "lo and hi, [R, G, B] integers 0..255"))


def _select(v, label: str) -> SelectTable:
    return parse_table(SelectTable, {"kind": v} if isinstance(v, str) else v, label, sep=".")


@dataclass(frozen=True)
class FixtureTable:
    """``[fixture]``: the forbidden regions (dissertation chapter 3) and their radii (6.3)."""

    TABLE = "fixture"
    mode: Literal["fixture", "rendering"] = setting(
        "fixture", doc="fixture: forbidden regions around protected points; rendering: plain haptic rendering")
    radius: float = setting(RadiusModel.r_base, doc="r_base: the fixture sphere radius per protected point (m)", lo=0)
    adaptive: bool = setting(RadiusModel.adaptive, doc="grow each radius by k_sigma times the point's noise sigma")
    k_sigma: float = setting(RadiusModel.k_sigma, doc="adaptive radii: noise sigmas added to r_base", lo=0)
    radius_max: Optional[float] = setting(None, lo=0, doc="ceiling of the adaptive radius (m)",
                                          default_doc=f"radius (+ {ADAPTIVE_MARGIN:g} with adaptive)")
    select: Optional[SelectTable] = setting(
        None, parse=_select, toml=Union[Literal["all", "mask"], SelectTable], doc='protected points: "all" | "mask" | {kind="box", min, max} | {kind="color", lo, hi}',
        default_doc='"all"')


@dataclass(frozen=True)
class HashTable:
    """``[hash]``: the spatial hash of the snapshots."""

    TABLE = "hash"
    cell_size: Optional[float] = setting(None, positive=True, doc="hash cell edge (m); at least the largest query reach",
                                         default_doc="the largest query reach: r3 (+ radius_max in fixture mode)")


@dataclass(frozen=True)
class NoiseTable:
    """``[[camera]] noise``: axial depth noise sigma_z = a + b Z^2 (kernels.camera.NoiseModel)."""

    TABLE = "noise"
    a: float = setting(NoiseModel.a, lo=0, doc="constant term (m)")
    b: float = setting(NoiseModel.b, lo=0, doc="quadratic term (1/m)")


@dataclass(frozen=True)
class CameraTable:
    """One ``[[camera]]`` entry: the camera model and where its frames come from. Intrinsics
    and the camera's other parameters default to the source's (recorded, synthetic, openni2,
    depthai, realsense, ros2), else to ``kernels.camera.Camera``'s."""

    TABLE = "camera"
    source: str = setting(doc='"synthetic:<scene>" | "recorded:<path>" | "openni2:<uri or .oni>" | "depthai:<id>" '
                                '| "realsense:<serial or .bag/.db3>" | "ros2:<namespace or image topic>"')
    name: Optional[str] = setting(None, doc="unique camera name", default_doc='"cam<index>"')
    fx: Optional[float] = setting(None, positive=True, doc="focal length x (px)", default_doc="the source's")
    fy: Optional[float] = setting(None, positive=True, doc="focal length y (px)", default_doc="the source's")
    cx: Optional[float] = setting(None, positive=True, doc="principal point x (px)", default_doc="the source's")
    cy: Optional[float] = setting(None, positive=True, doc="principal point y (px)", default_doc="the source's")
    width: Optional[int] = setting(None, positive=True, doc="image width (px)", default_doc="the source's")
    height: Optional[int] = setting(None, positive=True, doc="image height (px)", default_doc="the source's")
    depth_scale: Optional[float] = setting(None, lo=0, doc="metres per depth unit",
                                           default_doc=f"the source's, else {Camera.depth_scale:g}")
    T_world_cam: Optional[Vec16] = setting(None, convert=_matrix, doc="camera-to-world transform, row-major",
                                           default_doc="the source's, else identity")
    noise: Optional[NoiseTable] = setting(None, doc="depth noise {a, b}: sigma_z = a + b Z^2 (m)",
                                          default_doc=f"{{a = {NoiseModel.a:g}, b = {NoiseModel.b:g}}}")
    dist: Optional[Tuple[(float,) * 5]] = setting(None, doc="Brown-Conrady k1 k2 p1 p2 k3 (OpenCV order)",
                                                  default_doc="the source's, else none")
    z_min: Optional[float] = setting(None, lo=0, doc="nearest valid depth (m)",
                                     default_doc=f"the source's, else {Camera.z_min:g}")
    z_max: Optional[float] = setting(None, lo=0, doc="farthest valid depth (m)",
                                     default_doc=f"the source's, else {Camera.z_max:g}")
    max_code: Optional[int] = setting(None, positive=True, doc="largest valid depth code (0 and max_code are invalid)",
                                      default_doc=f"the source's, else {Camera.max_code}")
    depth_step_inv: float = setting(0.0, lo=0, hi=1.0, doc="a disparity camera's depth step in inverse depth (1/m; "
                                    "Kinect v1 about 0.0029: 9 mm at 1.8 m); 0: readings one code apart")
    near_reading: bool = setting(False, doc="take each reading at the near end of its depth step (half a code or half "
                                 "the disparity step nearer): the sensor's quantisation cannot let the tool in")
    rate_hz: float = setting(30.0, positive=True, doc="frame rate (Hz)")
    options: dict = setting(factory=dict, doc="options of the source (synthetic: seed, dropout, speed, color, ...)")

    def __post_init__(self):
        if self.name is not None and not self.name:
            raise InputError("[[camera]]: name = ''; expected a non-empty string")
        if ":" not in self.source:
            raise InputError(f"[[camera]] {self.name!r}: source = {self.source!r}; expected 'synthetic:<scene>', "
                             "'recorded:<path>', 'openni2:<uri or file.oni>', 'depthai:<device id>' or "
                             "'realsense:<serial or file.db3>' or 'ros2:<namespace or image topic>'")


def parse_cameras(entries, label: str = "[[camera]]") -> tuple:
    """The ``[[camera]]`` array: one CameraTable per entry (named ``cam<i>`` where unnamed)."""
    if not isinstance(entries, list):
        raise InputError(f"[[camera]] = {entries!r}; expected an array of tables ([[camera]] entries)")
    out = []
    for i, e in enumerate(entries):
        name = e.get("name", f"cam{i}") if isinstance(e, dict) else None
        where = f"[[camera]] {name!r}" if isinstance(name, str) and name else f"[[camera]] #{i + 1}"
        t = parse_table(CameraTable, e, where, sep=".")
        out.append(t if t.name is not None else CameraTable(**{**t.__dict__, "name": f"cam{i}"}))
    return tuple(out)


@dataclass(frozen=True)
class HapticsTable:
    """``[haptics]``: the proxy and the force (dissertation table 2.1; kernels.params_haptics.HapticParams)."""

    TABLE = "haptics"
    r1: float = setting(HapticParams.r1, positive=True, doc="proxy radius (m)")
    r2: float = setting(HapticParams.r2, positive=True, doc="contact radius (m), above r1")
    r3: float = setting(HapticParams.r3, positive=True, doc="normal-estimation radius (m), above r2")
    step: float = setting(HapticParams.step, positive=True, doc="proxy step length (m), at most r3 - r1")
    k_spring: Optional[float] = setting(None, lo=0, doc="stiffness (N/m): k_s in fixture mode, k in rendering mode",
                                        default_doc=f"{HapticParams.k_s:g} (fixture), {HapticParams.k:g} (rendering)")
    damping: float = setting(HapticParams.b, lo=0, doc="damping during contact (N s/m)")
    fir_taps: int = setting(HapticParams.fir_taps, doc="length of the force low-pass FIR (1: off)")
    max_force: float = setting(HapticParams.max_force, positive=True, doc="saturation of the force magnitude (N)")
    max_steps: int = setting(HapticParams.max_steps, doc="proxy steps per haptic tick")

    def params(self, mode: str) -> HapticParams:
        """The kernel's HapticParams in ``mode`` ("fixture" | "rendering")."""
        kw = dict(r1=self.r1, r2=self.r2, r3=self.r3, step=self.step, b=self.damping, fir_taps=self.fir_taps,
                  max_force=self.max_force, max_steps=self.max_steps, mode=mode)
        if self.k_spring is not None:
            kw["k" if mode == "rendering" else "k_s"] = self.k_spring
        try:
            return HapticParams(**kw)
        except InputError as e:
            raise InputError(f"[haptics]: {e}") from None


@dataclass
class TeleopConfig:
    """``[teleop]``: the fixture architecture (eqs. 3.1-3.3), motion scaling, the robot's speed
    limits (position, orientation, jaw) and the master-to-world registration; ``haptics`` / ``teleop``: engaged at start."""

    TABLE = "teleop"
    architecture: Literal["I", "II", "III"] = setting("III", doc="fixture architecture (eqs. 3.1-3.3); switchable while running")
    scale: float = setting(0.5, positive=True, doc="robot motion per master motion")
    max_robot_speed: float = setting(0.05, positive=True, doc="bound on every command increment (m/s)")
    max_angular_speed: float = setting(3.0, positive=True, doc="bound on the commanded tool orientation's angular speed (rad/s)")
    max_jaw_speed: float = setting(3.0, positive=True, doc="bound on the jaw command's speed (rad/s)")
    slip_lift: bool = setting(True, doc="III: while the proxy slips sideways over a noisy cloud, raise the robot's goal along "
                              "the surface normal by up to the fixture radius (min(L^2 / r_f, r_f), L the command's "
                              "sideways distance to the proxy), so the command does not cut through the bumps between")
    T_world_master: np.ndarray = setting(factory=lambda: np.eye(4), toml=Vec16, convert=rigid, default_doc="identity",
                                         doc="master-to-world registration, rigid, row-major")
    haptics: bool = setting(True, doc="haptics engaged at start", hint="engaged at start")
    teleop: bool = setting(True, doc="teleoperation engaged at start", hint="engaged at start")


#: the fixture architectures (``[teleop] architecture``)
ARCHITECTURES = typing.get_args(typing.get_type_hints(TeleopConfig)["architecture"])


@dataclass
class ServiceConfig:
    """``[service]``: the haptic loop's rate, its degraded-mode thresholds (s) and its threads."""

    TABLE = "service"
    rate_hz: float = setting(1000.0, positive=True, doc="haptic loop rate (Hz)")
    proxies: int = setting(1, doc="proxies (arms) the batch renders")
    stale_s: float = setting(0.1, positive=True, doc="a camera without a new frame for this long is reported stale (s)")
    max_frame_age_s: float = setting(0.5, positive=True,
                                     doc="newest snapshot older than this: the robot holds; its fixtures stay (s)")
    force_ramp_s: float = setting(0.05, positive=True, doc="degraded mode: the force ramps to zero within this (s)")
    max_lateness_s: float = setting(0.003, positive=True, doc="a tick starting later than this is an overrun (s)")
    recover_s: float = setting(0.1, positive=True, doc="a condition must be clear this long before an arm re-couples (s)")
    self_filter: Optional[bool] = setting(
        None, doc="drop the robot's own tool from every frame (at its capture time) before ingest; true needs a known tool",
        default_doc="on where the robot's tool is known")
    self_filter_margin: float = setting(0.003, lo=0, doc="clearance around the tool's capsules (m)")
    rt_priority: int = setting(80, lo=0, hi=99, doc="SCHED_FIFO priority of the haptic loop thread where allowed; 0: normal",
                               hint="SCHED_FIFO priority of the haptic loop thread; 0 runs it at normal priority")
    frames_rt_priority: int = setting(
        50, lo=0, hi=99, doc="SCHED_FIFO priority of the camera reader and ingest threads, below rt_priority; 0: normal",
        hint="SCHED_FIFO priority of the camera reader and ingest threads; 0 runs them at normal priority")
    build_nice: int = setting(10, lo=0, hi=19, doc="nice value of PoCL's worker threads (snapshot builds); 0: normal",
                              hint="nice value of PoCL's worker threads that build the snapshots; 0 leaves them at "
                                   "normal priority")
    build_idle: bool = setting(True, doc="PoCL's worker threads run SCHED_IDLE, back under the normal scheduler while "
                                         "a build starves (false: at nice build_nice)",
                               hint="PoCL's worker threads at SCHED_IDLE; false: at nice build_nice")
    robot_process: bool = setting(True, doc="live runs step simulated robots in their own process (false: in the tick)",
                                  hint="live runs step simulated robots in their own process; false: in the haptic tick")
    robot_watchdog_s: float = setting(0.05, positive=True,
                                      doc="robot process silent or unread this long: every arm FAULT (s; at most 0.25)")

    def __post_init__(self):
        frt, rt = self.frames_rt_priority, self.rt_priority
        if frt and rt and frt >= rt:
            raise InputError(f"[service] frames_rt_priority = {frt} is not below rt_priority = {rt}; the frame threads "
                             "must never preempt the haptic loop (e.g. frames_rt_priority = 50, rt_priority = 80)")
        if self.max_frame_age_s < self.stale_s:
            raise InputError(f"[service] max_frame_age_s = {self.max_frame_age_s} s is below stale_s = {self.stale_s} s; "
                             "a camera is reported stale first, then the robot holds")


@dataclass(frozen=True)
class MotionTable:
    """``[motion]``: motion estimation and fixture prediction (chapter 6; kernels.motion.MotionModel)."""

    TABLE = "motion"
    RELATIONS_FIRST = True     # the model's own relations (v_min <= v_max) say more than the limits
    enabled: bool = setting(MotionModel.enabled, doc="estimate velocities and predict the fixtures")
    latency: float = setting(MotionModel.latency, lo=0, doc="camera latency not in the frame timestamps (s)")
    max_age: float = setting(MotionModel.max_age, lo=0, doc="how far past its timestamp a snapshot is extrapolated (s)")
    capture: float = setting(MotionModel.capture, lo=0, doc="longest displacement measured between two snapshots (m)")
    cell: float = setting(MotionModel.cell, lo=0, doc="motion grid cell (m)")
    min_points: int = setting(MotionModel.min_points, lo=1, doc="fewest points per block for an estimate")
    planarity: float = setting(MotionModel.planarity, lo=0, doc="eigenvalue ratio below which a block is a surface patch")
    count_ratio: float = setting(MotionModel.count_ratio, lo=0, doc="largest ratio of a block's point counts")
    v_min: float = setting(MotionModel.v_min, lo=0, doc="slower is depth noise: 0 (m/s)")
    v_max: float = setting(MotionModel.v_max, lo=0, doc="faster estimates are discarded (m/s)")
    max_gap: float = setting(MotionModel.max_gap, lo=0, doc="snapshots further apart give no estimate (s)")
    min_neighbours: int = setting(MotionModel.min_neighbours, lo=0,
                                  doc="an unmeasured cell takes the velocity of at least this many agreeing measured neighbours (0: never)")
    coherence: float = setting(MotionModel.coherence, lo=0, doc="neighbours agree within this fraction of their mean speed")
    w_max: float = setting(MotionModel.w_max, lo=0, doc="blocks whose surface turns faster are discarded (rad/s)")
    smoothing: float = setting(MotionModel.smoothing, lo=0, hi=1,
                               doc="weight of a cell's new estimate against its previous one (1: none)")
    smooth_gate: float = setting(MotionModel.smooth_gate, lo=0,
                                 doc="estimates differing by more than this fraction of the speed are not averaged")

    def __post_init__(self):
        self.model()

    def model(self) -> MotionModel:
        """The kernel's MotionModel."""
        try:
            return MotionModel(**{k: getattr(self, k) for k in self.__dataclass_fields__})
        except InputError as e:
            raise InputError(f"[motion]: {e}") from None


#: a ROS 2 name segment: letters, digits, underscores, not starting with a digit
_ROS_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


@dataclass(frozen=True)
class Ros2Table:
    """``[ros2]``: ROS 2 telemetry for RViz and Foxglove (``service/ros2/telemetry.py``, in its
    own process): poses, forces, the fixture cloud, markers and status on the recording's topics
    (``/pointfence/...``) under ``namespace``."""

    TABLE = "ros2"
    telemetry: bool = setting(False, doc="publish telemetry while the service runs (serve|demo --ros2-telemetry)")
    telemetry_rate_hz: float = setting(60.0, positive=True, hi=1000.0,
                                       doc="poses, forces and markers per second (Hz; at most the loop rate)")
    cloud_rate_hz: float = setting(5.0, positive=True, hi=30.0, doc="fixture clouds per second (Hz)")
    cloud_max_points: int = setting(20000, lo=1, hi=1000000, doc="most points of one fixture cloud (downsampled)")
    frame_id: str = setting("world", doc="frame id of the world frame (the robot base) in every header")
    namespace: str = setting("", doc='ROS namespace of the telemetry topics ("": /pointfence/...; "/rig2": '
                                     '/rig2/pointfence/...)')
    force_arrow_m_per_n: float = setting(0.01, positive=True, hi=1.0, doc="length of a force marker arrow (m per N)")

    def __post_init__(self):
        if not _ROS_NAME.fullmatch(self.frame_id):
            raise InputError(f"[ros2] frame_id = {self.frame_id!r}; expected a ROS frame name: letters, digits and "
                             "underscores, not starting with a digit (e.g. 'world')")
        ns = self.namespace
        if ns and not (ns.startswith("/") and all(_ROS_NAME.fullmatch(p) for p in ns[1:].split("/"))):
            raise InputError(f"[ros2] namespace = {ns!r}; expected '' or an absolute ROS namespace such as '/rig2' "
                             "(segments of letters, digits and underscores, not starting with a digit)")


def _table(cls, name: str):
    return lambda v, label: parse_table(cls, v, f"[{name}]")


@dataclass(frozen=True)
class SceneTable:
    """The whole file: top-level keys and one field per table."""

    TABLE = ""
    backend: str = setting("opencl", doc='compute backend: "opencl" | "numpy" | "warp"',
                           hint="a name such as 'opencl' or 'numpy'")
    device: Optional[str] = setting(None, doc="device of the backend (e.g. an OpenCL device name)",
                                    default_doc="the backend's first")
    workspace: WorkspaceTable = setting(factory=WorkspaceTable, parse=_table(WorkspaceTable, "workspace"),
                                        doc="[workspace]")
    fixture: FixtureTable = setting(factory=FixtureTable, parse=_table(FixtureTable, "fixture"), doc="[fixture]")
    hash: HashTable = setting(factory=HashTable, parse=_table(HashTable, "hash"), doc="[hash]")
    camera: tuple = setting(factory=tuple, parse=parse_cameras, doc="[[camera]] entries, one at least")
    haptics: HapticsTable = setting(factory=HapticsTable, parse=_table(HapticsTable, "haptics"), doc="[haptics]")
    teleop: TeleopConfig = setting(factory=TeleopConfig, parse=_table(TeleopConfig, "teleop"), doc="[teleop]")
    robot: RobotConfig = setting(factory=RobotConfig, parse=lambda v, label: parse_robot(v), doc="[robot]")
    service: ServiceConfig = setting(factory=ServiceConfig, parse=_table(ServiceConfig, "service"), doc="[service]")
    motion: MotionTable = setting(factory=MotionTable, parse=_table(MotionTable, "motion"), doc="[motion]")
    ros2: Ros2Table = setting(factory=Ros2Table, parse=_table(Ros2Table, "ros2"), doc="[ros2]")
    cable: Optional[CableTable] = setting(None, parse=_table(CableTable, "cable"), doc="[cable]",
                                          default_doc="none: no grasper controller")


#: the tables of the README's settings table, in its order: (label, dataclass)
TABLES = (("top level", SceneTable), ("[workspace]", WorkspaceTable), ("[fixture]", FixtureTable),
          ("[fixture] select", SelectTable), ("[hash]", HashTable), ("[[camera]]", CameraTable),
          ("[[camera]] noise", NoiseTable), ("[haptics]", HapticsTable), ("[teleop]", TeleopConfig),
          ("[service]", ServiceConfig), ("[motion]", MotionTable), ("[ros2]", Ros2Table),
          ("[cable]", CableTable))


def table_rows() -> list:
    """(table, key, type, default, doc) of every key of every table (the README's settings table);
    ``[robot]``, its models' options and ``[robot.tool]`` follow ``[teleop]``."""
    out = []
    for label, cls in TABLES:
        for key, tp, default, doc in rows(cls, ("backend", "device") if cls is SceneTable else None):
            out.append((label, key, tp, default, doc))
            if label == "[teleop]" and key == "teleop":
                out += robot_rows()      # [robot] after [teleop], as in the file
    return out


def markdown() -> str:
    """The README's settings table (``python -m pointfence.service.settings`` prints it)."""
    lines = ["| table | key | type | default | meaning |", "|---|---|---|---|---|"]
    for table, key, tp, default, doc in table_rows():
        lines.append(f"| `{table}` | `{key}` | {tp} | {default.replace('|', '&#124;')} | {doc.replace('|', '&#124;')} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(markdown(), end="")
