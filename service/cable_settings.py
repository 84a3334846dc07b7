"""``[cable]``: the cable-driven grasper controller of chapters 4-5 (service/cable/) run by the
service at 1 kHz for one arm's jaw (``cable_grasper.GrasperHost``).

The table is optional: without it the service runs no grasper controller. With it, the jaw angle
the master's grasp asks for (rad, link side) is the controller's setpoint each haptic tick, and its
estimate (motor torque, external link torque, jaw angle, cable tension, alerts) appears in the
status, the metrics and the recording.

Plant: only ``"sim"`` exists, the simulated grasper of ``cable/plant.py`` (eq. 4.4 with "true"
parameters at ``sim_tension_g``, a 2000 counts/rev encoder, torque noise, optional tissue). pointfence
has no driver for a real grasper motor; one would implement ``measure()`` / ``actuate(torque)``
like ``SimulatedPlant`` and be added here as another plant name.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

from pointfence.kernels.errors import InputError

from .schema import setting

#: ceilings of the grasper's safety timeouts (SAFETY.md S7): a grasper loop late by more, or a
#: grasper process silent for longer, must read as a fault
MAX_LATENESS_CEILING_S = 0.1
WATCHDOG_CEILING_S = 0.25


@dataclass(frozen=True)
class CableTable:
    """``[cable]``: the grasper controller (UKF + iLQG MPC, 1 kHz, in its own process)."""

    TABLE = "cable"
    arm: int = setting(0, lo=0, doc="the arm (0-based) whose jaw the grasper controller drives")
    params: str = setting("nominal", doc='controller model: "nominal" (table 4.1, 743 g) or a JSON file of '
                                         'identified parameters (`pointfence cable identify --out FILE`)')
    plant: Literal["sim"] = setting("sim", doc='"sim": the simulated grasper (cable/plant.py); pointfence has no '
                                              'real grasper motor driver')
    sim_tension_g: float = setting(743.0, positive=True, hi=5000.0,
                                   doc="sim plant: its true cable tension (g), which sets its stiffness and friction")
    sim_contact_rad: Optional[float] = setting(None, lo=-1.5, hi=1.5, doc="sim plant: tissue beyond this jaw angle (rad)",
                                               default_doc="no tissue")
    tension: bool = setting(True, doc="estimate the cable stiffness online and the tension from it (chapter 5)")
    tension_curve: Optional[str] = setting(None, doc="tension calibration JSON (`pointfence calib tension --out FILE`)",
                                           default_doc="the sim plant's law as the 1 ms filter sees it (cable/tension.py)")
    tension_min_g: float = setting(600.0, positive=True, doc="alert below this estimated tension (g)")
    tension_max_g: float = setting(1400.0, positive=True, doc="alert above this estimated tension (g)")
    jaw_min: float = setting(-1.2, lo=-1.5, hi=1.5, doc="smallest jaw angle commanded (rad); commands are clamped")
    jaw_max: float = setting(1.2, lo=-1.5, hi=1.5, doc="largest jaw angle commanded (rad); commands are clamped")
    max_lateness_s: float = setting(0.02, positive=True, hi=MAX_LATENESS_CEILING_S,
                                    doc=f"a grasper tick later than this latches a fault, zero torque (s; at most "
                                        f"{MAX_LATENESS_CEILING_S:g})")
    watchdog_s: float = setting(0.05, positive=True, hi=WATCHDOG_CEILING_S,
                                doc=f"grasper process without a tick this long: fault (s; at most {WATCHDOG_CEILING_S:g})")

    def __post_init__(self):
        if not self.jaw_min < self.jaw_max:
            raise InputError(f"[cable] jaw_min = {self.jaw_min} rad is not below jaw_max = {self.jaw_max} rad; give "
                             "the jaw's range as jaw_min < jaw_max (e.g. -1.2 and 1.2)")
        if not self.tension_min_g < self.tension_max_g:
            raise InputError(f"[cable] tension_min_g = {self.tension_min_g} g is not below tension_max_g = "
                             f"{self.tension_max_g} g; give the safe tension range as min < max (e.g. 600 and 1400)")
        if self.params != "nominal":
            load_params(self.params)            # (a missing or malformed file is refused here, at start-up)
        if self.tension_curve is not None:
            if not self.tension:
                raise InputError(f"[cable] tension_curve = {self.tension_curve!r} with tension = false; set "
                                 "tension = true to estimate the tension, or remove tension_curve")
            load_curve(self.tension_curve)

    def check_arms(self, n: int) -> None:
        """InputError unless ``arm`` is one of ``n`` arms."""
        if self.arm >= n:
            raise InputError(f"[cable] arm = {self.arm}; the service has {n} arm(s) (0..{n - 1}); set arm to the "
                             "arm whose jaw the grasper drives")


def load_params(path: str):
    """The grasper parameters of JSON file ``path`` (``{name: value}``, every name of
    ``cable.params.PARAM_NAMES``; what `pointfence cable identify --out` writes)."""
    from .cable.params import PARAM_NAMES, GrasperParams

    p = Path(path)
    try:
        d = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"[cable] params = {path!r}: cannot read it as JSON ({e}); give \"nominal\" or the file "
                         "`pointfence cable identify --out FILE` wrote") from None
    if not isinstance(d, dict):
        raise InputError(f"[cable] params = {path!r}: expected a JSON object of parameter names to numbers")
    missing = [n for n in PARAM_NAMES if n not in d]
    unknown = [k for k in d if k not in PARAM_NAMES]
    if missing or unknown:
        raise InputError(f"[cable] params = {path!r}: " + (f"missing {', '.join(missing)}" if missing else "")
                         + ("; " if missing and unknown else "") + (f"unknown {', '.join(unknown)}" if unknown else "")
                         + f"; expected exactly {', '.join(PARAM_NAMES)}")
    vals = {}
    for n in PARAM_NAMES:
        v = d[n]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InputError(f"[cable] params = {path!r}: {n} = {v!r}; expected a finite number")
        vals[n] = float(v)
    try:
        return GrasperParams(**vals)
    except InputError as e:
        raise InputError(f"[cable] params = {path!r}: {e}") from None


def load_curve(path: str):
    """The tension calibration of JSON file ``path`` (``cable.tension.TensionCurve``)."""
    from .cable.tension import TensionCurve

    try:
        c = TensionCurve.load(path)
    except InputError as e:
        raise InputError(f"[cable] tension_curve = {path!r}: {e}") from None
    if not (math.isfinite(c.a) and math.isfinite(c.b) and c.b > 0):
        raise InputError(f"[cable] tension_curve = {path!r}: a = {c.a}, b = {c.b}; expected finite numbers with b > 0 "
                         "(tension rises with stiffness); redo `pointfence calib tension`")
    return c


def sim_curve():
    """The simulated plant's own tension law (``cable.params.k_e_at_tension`` inverted): tension_g =
    743 + 2000 ln(k_e / 2e4). Exact for the sim plant; real cables need ``tension_curve``."""
    from .cable.params import K_E_LOG_SLOPE_G, NOMINAL_TENSION_G, GrasperParams
    from .cable.tension import TensionCurve

    b = K_E_LOG_SLOPE_G
    return TensionCurve(NOMINAL_TENSION_G - b * math.log(GrasperParams.k_e), b)


__all__ = ["CableTable", "load_params", "load_curve", "sim_curve"]
