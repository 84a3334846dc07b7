"""Registering the master to the world: ``pointfence calib master``, writing ``[teleop]``
``T_world_master`` and ``scale`` instead of a hand-typed 4x4.

The teleoperation maps a master displacement dx (master device frame, m) to the world (robot
base frame, m) as ``scale * R_world_master dx``, and a master point x to ``scale * R x + p``
(``service/teleop.py``). Two recordings find R (and p, and optionally the scale):

* **pairs** (``calib master pairs.csv``): master positions and the robot tip positions that go
  with them, e.g. the master and the tool tip moved together through the same motion (the robot
  hand-guided or driven along the master's path), or the robot tip touched onto points that the
  master touched. Rows ``master_x,master_y,master_z,robot_x,robot_y,robot_z`` (m; master frame,
  then world frame; a header line and # comments allowed). Solved by Umeyama: rotation and
  translation with ``--scale S`` fixed (default: the configuration's, else 0.5), or the scale
  fitted too with ``--fit-scale``. Residuals are world-frame distances (mm).
* **guided** (``calib master --guided steps.csv``): the operator holds the master at a start
  point and moves it, one step after another, about 5 cm along each prompted world direction
  (``--print-script`` prints the prompts); the recorder logs the master's position after each
  step. Rows ``direction,master_x,master_y,master_z`` with direction ``start`` first, then
  ``+x``, ``-x``, ``+y``, ``-y``, ``+z``, ``-z`` (world = robot base axes) in any order. Each step's
  displacement is paired with its prompted direction and R is the rotation that best turns the
  one onto the other (Kabsch on unit vectors); a hand's motion says nothing about the scale,
  which stays as configured, nor about p, which stays (p matters only without a robot).
  Residuals are each step's angle from its prompt (deg).

Verdict: TRUSTED, or NOT TRUSTED with what to do (too few pairs or steps, motion along a line,
residuals above bounds, an uncertain result by jackknife); a result not trusted is written only
with ``--accept-untrusted`` (exit status 3). A fitted scale outside ``[teleop] scale``'s limits
(``service/limits.py``) is an error. ``--config scene.toml`` merges the keys into ``[teleop]``
(only those keys change, comments and layout stay, earlier versions kept as .bak, .bak.2, ...);
``--out FILE`` writes the ``[teleop]`` snippet.

**live** (``calib master --live [--port P] [--token-file F] [--arm N]``): the guided motion
against a running ``pointfence serve``: the operator is prompted for each step and each
position is the master's raw sample read from the control API (``GET /masters``, with the
run's token as `pointfence ctl` finds it), averaged once the master rests (or on Enter with
``--enter``); ``calib/master_live.py``. Then solved, reported and written as ``--guided``; a step
not captured in ``--step-timeout`` s is left out and named in the verdict (NOT TRUSTED).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

from pointfence.kernels.errors import InputError

from .common import make_T, rotation_angle_deg
from .handeye_solve import Verdict, spread

DIRECTIONS = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
MIN_PAIRS, MIN_SPREAD_M = 8, 0.02          # pairs: fewest pairs; master motion's RMS extent on its 2nd axis
MAX_RMS_MM, MAX_WORST_MM = 2.0, 5.0        # pairs: world-frame residuals
MAX_STEP_RMS_DEG, MAX_STEP_WORST_DEG = 10.0, 20.0   # guided: a hand's steps along prompted directions
MAX_SE_DEG, MAX_SE_SCALE = 0.5, 0.02       # pairs: jackknife standard errors (deg; relative scale)
MAX_SE_DEG_GUIDED = 3.0
MIN_STEP_M = 0.01                          # guided: shorter steps are no motion


@dataclass
class MasterRegistration:
    """``T_world_master`` (4x4, rigid), ``scale``, ``fitted_scale``; ``residuals`` per pair (mm)
    or per step (deg) with ``unit``; ``se_deg``/``se_scale`` jackknife standard errors."""

    T_world_master: np.ndarray
    scale: float
    fitted_scale: bool
    residuals: np.ndarray
    unit: str
    se_deg: float
    se_scale: float = 0.0
    problems: list = field(default_factory=list)

    @property
    def verdict(self) -> Verdict:
        return Verdict(not self.problems, list(self.problems))

    def report(self) -> str:
        r = self.residuals
        lines = [f"master registration from {len(r)} {'pairs' if self.unit == 'mm' else 'steps'}: residuals "
                 f"{np.sqrt(np.mean(r ** 2)):.2f} {self.unit} RMS, {r.max():.2f} {self.unit} max (#{int(np.argmax(r))})",
                 f"rotation master -> world: {rotation_angle_deg(self.T_world_master[:3, :3]):.2f} deg about "
                 + ", ".join(f"{x:.3f}" for x in _axis(self.T_world_master[:3, :3]))
                 + f"; estimated uncertainty (jackknife) {self.se_deg:.3f} deg",
                 f"scale: {self.scale:.4f} " + (f"(fitted, uncertainty {self.se_scale * 100:.2f} %)" if self.fitted_scale else "(kept)"),
                 self.verdict.text()]
        return "\n".join(lines)


def _axis(R) -> np.ndarray:
    rv = Rotation.from_matrix(R).as_rotvec()
    n = np.linalg.norm(rv)
    return rv / n if n > 0 else np.array([0.0, 0.0, 1.0])


def umeyama(X, Y, scale: Optional[float] = None) -> tuple:
    """(R, t, s) minimising sum |Y_i - (s R X_i + t)|^2 over rotations R (det +1) and t, with s
    fitted (``scale`` None; Umeyama 1991) or fixed."""
    X, Y = np.asarray(X, dtype=np.float64), np.asarray(Y, dtype=np.float64)
    mx, my = X.mean(axis=0), Y.mean(axis=0)
    Xc, Yc = X - mx, Y - my
    U, D, Vt = np.linalg.svd(Yc.T @ Xc / len(X))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / np.mean(np.sum(Xc ** 2, axis=1))) if scale is None else float(scale)
    return R, my - s * R @ mx, s


def _check_scale(s: float, how: str) -> None:
    from pointfence.service import limits

    try:
        limits.check("teleop.scale", s, f"the {how} scale")
    except InputError as e:
        raise InputError(f"{e}. The robot moved {s:.3g} times as far as the master: check that both columns are in metres "
                         "and that the pairs belong together") from None


def register_pairs(master, world, scale: Optional[float] = 0.5) -> MasterRegistration:
    """The pairs method (module docstring); ``scale`` None fits it."""
    M, P = _array(master, "master positions"), _array(world, "robot positions")
    if len(M) != len(P):
        raise InputError(f"calib master: {len(M)} master positions but {len(P)} robot positions; they must pair one to one")
    if len(M) < 3:
        raise InputError(f"calib master: {len(M)} pairs; at least 3 are needed to solve and {MIN_PAIRS} to trust it")
    ext = spread(M)
    if ext[1] < 1e-3:
        raise InputError(f"calib master: the master moved along a line (RMS extents {', '.join(f'{e * 100:.2f}' for e in ext)} cm); "
                         "the rotation about that line is undetermined: move it in at least two directions")
    if scale is not None:
        _check_scale(float(scale), "given")
    R, t, s = umeyama(M, P, scale)
    _check_scale(s, "fitted")
    res = np.linalg.norm(P - (s * M @ R.T + t), axis=1) * 1000.0
    jk = [umeyama(M[np.arange(len(M)) != k], P[np.arange(len(M)) != k], scale) for k in range(len(M))]
    se_deg, se_s = _jackknife_rot([r for r, _, _ in jk], R), _jackknife([x for _, _, x in jk]) / s
    reg = MasterRegistration(make_T(R, t), s, scale is None, res, "mm", se_deg, se_s if scale is None else 0.0)
    p = reg.problems
    if len(M) < MIN_PAIRS:
        p.append(f"only {len(M)} pairs; record at least {MIN_PAIRS} (20 or more advised)")
    if ext[1] < MIN_SPREAD_M:
        p.append(f"the master's motion is thin (RMS extents {', '.join(f'{e * 100:.1f}' for e in ext)} cm); move it at least "
                 f"{MIN_SPREAD_M * 100:.0f} cm RMS in two directions, better three")
    rms, worst = float(np.sqrt(np.mean(res ** 2))), float(res.max())
    if rms > MAX_RMS_MM or worst > MAX_WORST_MM:
        p.append(f"residuals {rms:.2f} mm RMS, {worst:.2f} mm max (pair #{int(np.argmax(res))}), above {MAX_RMS_MM} / "
                 f"{MAX_WORST_MM} mm; check that the two positions of each row were taken at the same instant")
    if se_deg > MAX_SE_DEG or (scale is None and reg.se_scale > MAX_SE_SCALE):
        p.append(f"estimated uncertainty {se_deg:.2f} deg, scale {reg.se_scale * 100:.1f} % (bounds {MAX_SE_DEG} deg, "
                 f"{MAX_SE_SCALE * 100:.0f} %); record more pairs over a wider motion")
    return reg


def register_guided(steps, scale: float = 0.5, translation=(0.0, 0.0, 0.0)) -> MasterRegistration:
    """The guided method: ``steps`` [(direction, (x, y, z)), ...] with "start" first."""
    if not steps or steps[0][0] != "start":
        raise InputError("calib master --guided: the first row must be the start position (direction 'start')")
    _check_scale(float(scale), "given")
    pos = _array([p for _, p in steps], "master positions")
    dirs = [d for d, _ in steps[1:]]
    bad = [d for d in dirs if d not in DIRECTIONS]
    if bad:
        raise InputError(f"calib master --guided: direction(s) {bad}; expected one of {', '.join(DIRECTIONS)} after 'start'")
    d = np.diff(pos, axis=0)
    length = np.linalg.norm(d, axis=1)
    short = [f"{dirs[k]} ({length[k] * 100:.1f} cm)" for k in range(len(d)) if length[k] < MIN_STEP_M]
    if short:
        raise InputError(f"calib master --guided: step(s) {', '.join(short)} moved less than {MIN_STEP_M * 100:.0f} cm; "
                         "move the master about 5 cm along each prompted direction")
    E = np.array([DIRECTIONS[x] for x in dirs], dtype=np.float64)
    U = d / length[:, None]
    if np.linalg.matrix_rank(E, tol=1e-6) < 2:
        raise InputError(f"calib master --guided: the steps go along one axis only ({sorted(set(dirs))}); the rotation about "
                         "it is undetermined: follow the prompts for at least two axes (all three advised)")

    def rot(k=None):
        keep = np.arange(len(U)) != k
        return umeyama(np.vstack([U[keep], [0, 0, 0]]), np.vstack([E[keep], [0, 0, 0]]), 1.0)[0]

    R = rot()
    res = np.degrees(np.arccos(np.clip(np.sum((U @ R.T) * E, axis=1), -1.0, 1.0)))
    se = _jackknife_rot([rot(k) for k in range(len(U))], R) if len(U) >= 4 else float("nan")
    reg = MasterRegistration(make_T(R, translation), float(scale), False, res, "deg", se)
    p = reg.problems
    missing = [a for a in ("x", "y", "z") if not any(x.endswith(a) for x in dirs)]
    if missing or len(U) < 6:
        p.append(f"{len(U)} steps{', none along ' + ', '.join(missing) if missing else ''}; follow all six prompts "
                 "(+x, -x, +y, -y, +z, -z), twice for a steadier result")
    rms, worst = float(np.sqrt(np.mean(res ** 2))), float(res.max())
    if rms > MAX_STEP_RMS_DEG or worst > MAX_STEP_WORST_DEG:
        p.append(f"steps off their prompts by {rms:.1f} deg RMS, {worst:.1f} deg max (step #{int(np.argmax(res)) + 1}, "
                 f"{dirs[int(np.argmax(res))]}), above {MAX_STEP_RMS_DEG} / {MAX_STEP_WORST_DEG} deg; repeat, moving straight")
    if np.isfinite(se) and se > MAX_SE_DEG_GUIDED:
        p.append(f"estimated uncertainty {se:.1f} deg (bound {MAX_SE_DEG_GUIDED} deg); repeat the prompts once more")
    return reg


def _array(a, what: str) -> np.ndarray:
    A = np.asarray(a, dtype=np.float64)
    if A.ndim != 2 or A.shape[1] != 3:
        raise InputError(f"calib master: {what} of shape {A.shape}; expected (N, 3) positions in m")
    if not np.all(np.isfinite(A)):
        raise InputError(f"calib master: {what} contain NaN or infinity (row {int(np.argmin(np.all(np.isfinite(A), axis=1)))})")
    return A


def _jackknife(xs) -> float:
    x = np.asarray(xs, dtype=np.float64)
    return float(np.sqrt((len(x) - 1) / len(x) * np.sum((x - x.mean(axis=0)) ** 2)))


def _jackknife_rot(Rs, R) -> float:
    return float(np.degrees(_jackknife([Rotation.from_matrix(R.T @ r).as_rotvec() for r in Rs])))


# -- files ----------------------------------------------------------------------------------
def _rows(path, ncols: int, what: str) -> tuple:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what} file {str(p)!r} not found; see `pointfence calib master --help` for its format")
    rows = []
    for n, line in enumerate(p.read_text().splitlines(), 1):
        s = line.split("#", 1)[0].strip()
        if s:
            rows.append((n, [x for x in re.split(r"[,\s]+", s) if x]))
    out = []
    for k, (n, parts) in enumerate(rows):
        if len(parts) != ncols:
            raise InputError(f"{p}:{n}: {len(parts)} values; expected {ncols} ({what})")
        out.append((n, parts))
    return out, p


def read_pairs(path) -> tuple:
    """(master (N, 3), world (N, 3)) from a pairs CSV (module docstring)."""
    rows, p = _rows(path, 6, "master_x,master_y,master_z,robot_x,robot_y,robot_z in m")
    vals = []
    for k, (n, parts) in enumerate(rows):
        try:
            vals.append([float(x) for x in parts])
        except ValueError:
            if k == 0:
                continue  # the header
            raise InputError(f"{p}:{n}: {','.join(parts)!r}; expected 6 numbers (m)") from None
    a = np.array(vals, dtype=np.float64).reshape(-1, 6)
    return a[:, :3], a[:, 3:]


def read_steps(path) -> list:
    """[(direction, (x, y, z)), ...] from a guided-steps CSV (module docstring)."""
    rows, p = _rows(path, 4, "direction,master_x,master_y,master_z")
    out = []
    for k, (n, parts) in enumerate(rows):
        try:
            out.append((parts[0].lower(), tuple(float(x) for x in parts[1:])))
        except ValueError:
            if k == 0:
                continue
            raise InputError(f"{p}:{n}: {','.join(parts)!r}; expected a direction and 3 numbers (m)") from None
    return out


def script(distance: float = 0.05) -> str:
    """The guided motion's prompts."""
    lines = ["# guided master registration: hold the master still at a comfortable start point and log it as 'start';",
             f"# then move it about {distance * 100:.0f} cm along each world direction below (the robot base's axes, as you",
             "# see them), hold still, and log the master's position with that direction:",
             "direction,master_x,master_y,master_z"]
    return "\n".join(lines + [f"{d},,," for d in ("start", *DIRECTIONS)]) + "\n"


def teleop_snippet(reg: MasterRegistration, comment: str) -> str:
    T = [float(x) for x in reg.T_world_master.ravel()]
    rows = ",\n    ".join(", ".join(repr(x) for x in T[i:i + 4]) for i in range(0, 16, 4))
    return f"# {comment}\n[teleop]\nscale = {reg.scale!r}\nT_world_master = [\n    {rows},\n]\n"


def update_teleop(path, reg: MasterRegistration) -> Optional[Path]:
    """Set ``[teleop]`` scale and T_world_master in the configuration ``path`` (created when
    missing), changing only those keys; checked by ``service.config.parse``; the file replaced
    atomically with the previous version kept as a numbered backup (returned)."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    from pointfence.service import config
    from pointfence.service.files import write_atomic

    from .toml_edit import set_keys

    p = Path(path)
    text = p.read_text() if p.exists() else ""
    body = teleop_snippet(reg, "").split("[teleop]\n", 1)[1]
    stmts = {"scale": body.split("\n", 1)[0], "T_world_master": body.split("\n", 1)[1].rstrip("\n")}
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{p}: not valid TOML ({e}); fix it or write the snippet elsewhere with --out") from None
    if "teleop" in doc:
        edited = set_keys(text, "teleop", None, stmts)
    else:
        sep = "" if not text or text.endswith("\n\n") else "\n" if text.endswith("\n") else "\n\n"
        edited = text + sep + "[teleop]\n" + body
    new = tomllib.loads(edited)
    t = new.get("teleop", {})
    if t.get("scale") != reg.scale or not np.allclose(t.get("T_world_master"), reg.T_world_master.ravel()):
        raise InputError(f"{p}: the [teleop] table could not be edited in place; set scale and T_world_master by hand "
                         "from the snippet above")
    config.parse(new, str(p))  # refuse to write a file the service would reject
    return write_atomic(p, edited)


def simulate_pairs(n: int = 24, R=None, scale: float = 0.4, t=(0.02, -0.01, 0.12), noise: float = 3e-4, seed: int = 0) -> tuple:
    """(master (n, 3), world (n, 3), true T_world_master, true scale): master points in a 12 cm box
    (master frame), the robot tip at scale R x + t with ``noise`` (m, per axis) on both."""
    rng = np.random.default_rng(seed)
    R = Rotation.from_euler("zyx", [35, -20, 10], degrees=True).as_matrix() if R is None else np.asarray(R)
    M = rng.uniform(-0.06, 0.06, (n, 3))
    P = scale * M @ R.T + np.asarray(t) + rng.normal(0.0, noise, (n, 3))
    return M + rng.normal(0.0, noise, (n, 3)), P, make_T(R, t), scale


def simulate_steps(R=None, distance: float = 0.05, wobble_deg: float = 5.0, seed: int = 0) -> tuple:
    """(steps, true R): a hand following the six prompts, each step off its direction by about
    ``wobble_deg`` and 0.8-1.2 times ``distance`` long (master frame = R^T world)."""
    rng = np.random.default_rng(seed)
    R = Rotation.from_euler("zyx", [35, -20, 10], degrees=True).as_matrix() if R is None else np.asarray(R)
    pos = np.array([0.01, 0.02, 0.03])
    steps = [("start", tuple(pos))]
    for d, e in DIRECTIONS.items():
        wob = Rotation.from_rotvec(np.radians(wobble_deg) * rng.normal(size=3) / np.sqrt(3)).as_matrix()
        pos = pos + distance * rng.uniform(0.8, 1.2) * (R.T @ wob @ np.asarray(e, dtype=np.float64))
        steps.append((d, tuple(pos)))
    return steps, R


# -- CLI ------------------------------------------------------------------------------------
def add_arguments(p) -> None:
    p.add_argument("pairs", nargs="?", help="CSV of master_x,master_y,master_z,robot_x,robot_y,robot_z (m)")
    p.add_argument("--guided", metavar="STEPS", help="CSV of direction,master_x,master_y,master_z from the guided motion")
    p.add_argument("--print-script", action="store_true", help="print the guided motion's prompts as a CSV to fill in")
    p.add_argument("--fit-scale", action="store_true", help="pairs: fit the scale too (default: keep --scale)")
    p.add_argument("--scale", type=float, help="motion scale to keep (default: the --config's [teleop] scale, else 0.5)")
    p.add_argument("--accept-untrusted", action="store_true", help="write the result even when the verdict is NOT TRUSTED")
    p.add_argument("--simulate", nargs="?", const="pairs", choices=("pairs", "guided"),
                   help="register synthetic pairs (default) or guided steps with a known answer")
    p.add_argument("--out", help="also write the [teleop] snippet to this file")
    p.add_argument("--config", help="merge scale and T_world_master into this scene's [teleop] (earlier versions kept as .bak, ...)")
    from .master_live import add_arguments as live_arguments

    live_arguments(p)


def run(args, prompt=None, say=None, wait_enter=None) -> int:
    """``pointfence calib master``; ``prompt``/``say``/``wait_enter``: the live mode's operator
    hooks (``master_live.GuidedCapture``; default print and input)."""
    if args.print_script:
        print(script(), end="")
        return 0
    cfg = None
    if args.config and Path(args.config).exists():
        from pointfence.service import config

        cfg = config.load(args.config).teleop
    scale = args.scale if args.scale is not None else (cfg.scale if cfg is not None else 0.5)
    truth = None
    if args.live:
        if args.pairs or args.guided or args.simulate:
            raise InputError("calib master --live captures the guided motion itself; drop the pairs CSV, --guided and --simulate")
        from .master_live import capture_from_args

        cap = capture_from_args(args, list(DIRECTIONS), prompt=prompt, say=say, wait_enter=wait_enter)
        p0 = cfg.T_world_master[:3, 3] if cfg is not None else np.zeros(3)
        return _live_result(args, cap, scale, p0)
    if args.guided or args.simulate == "guided":
        if args.simulate:
            steps, R_true = simulate_steps()
            truth = (make_T(R_true, np.zeros(3)), scale)
        else:
            steps = read_steps(args.guided)
        p0 = cfg.T_world_master[:3, 3] if cfg is not None else np.zeros(3)
        reg = register_guided(steps, scale, p0)
        how = f"guided motion, {len(steps) - 1} steps"
    else:
        if args.simulate:
            M, P, T_true, s_true = simulate_pairs()
            truth = (T_true, s_true)
        elif not args.pairs:
            raise InputError("calib master: pass a pairs CSV, --guided STEPS.csv, --print-script or --simulate")
        else:
            M, P = read_pairs(args.pairs)
        reg = register_pairs(M, P, None if args.fit_scale else scale)
        how = f"{len(M)} master/robot pairs"
    print(reg.report())
    if truth is not None:
        err = rotation_angle_deg(truth[0][:3, :3].T @ reg.T_world_master[:3, :3])
        print(f"# simulate: rotation error {err:.3f} deg, scale {reg.scale:.4f} (true {truth[1]:.4f})")
    return _finish(args, reg, how)


def _live_result(args, cap, scale: float, p0) -> int:
    """Solve the live capture (``master_live.Capture``) as ``--guided``, its left-out steps
    among the verdict's problems; too few steps to solve at all: NOT TRUSTED, nothing written."""
    dirs = [d for d, _ in cap.steps[1:]]
    axes = {d[1] for d in dirs}
    if len(axes) < 2:
        print(Verdict(False, list(cap.problems) + [
            f"{len(dirs)} of {len(DIRECTIONS)} steps captured ({', '.join(dirs) or 'none'}); at least two axes are needed "
            "to solve and all six steps to trust it: repeat `calib master --live`, following each prompt"]).text())
        if args.out or args.config:
            print("# not written: no registration could be solved")
        return 3
    reg = register_guided(cap.steps, scale, p0)
    reg.problems[:0] = cap.problems
    print(reg.report())
    return _finish(args, reg, f"live guided motion, arm {args.arm}, {len(dirs)} steps")


def _finish(args, reg: MasterRegistration, how: str) -> int:
    """Print the ``[teleop]`` snippet; write ``--out``/``--config`` unless the verdict is NOT
    TRUSTED (then exit status 3, unless ``--accept-untrusted``)."""
    from .output import write_snippet

    r = reg.residuals
    comment = (f"pointfence calib master ({how}): residuals {np.sqrt(np.mean(r ** 2)):.2f} {reg.unit} RMS, "
               f"{'trusted' if reg.verdict.trusted else 'NOT TRUSTED'}")
    snippet = teleop_snippet(reg, comment)
    print(snippet, end="")
    if not reg.verdict.trusted and not args.accept_untrusted:
        if args.out or args.config:
            print("# not written: the verdict is NOT TRUSTED; fix the problems above and record again, "
                  "or pass --accept-untrusted to write it anyway")
        return 3
    if args.out:
        print(f"# {write_snippet(args.out, snippet)}")
    if args.config:
        backup = update_teleop(args.config, reg)
        print(f"# updated [teleop] in {args.config}" + (f"; previous version kept in {backup}" if backup else ""))
    return 0
