"""Hard limits on the configuration values that could weaken safety (SAFETY.md S7).

Every number of the scene configuration that bounds an age, a lateness, a timeout, a speed, a
scale, a force, a stiffness, a ramp, a radius, a rate or a size has a floor and a ceiling here,
each with the reason for its value. ``service.config`` checks every such key against this
table; a value outside it (or NaN, or infinite) is an ``InputError`` that names the key, the
value, the limit, why, and what to do. The limits are deliberately generous for valid set-ups
(every configuration shipped or tested sits inside them) and close any door to switching a
safeguard off by a huge or tiny number. Other modules that take such values from elsewhere
(command line, control API) check them with ``check(key, value)``.

Keys are the configuration's dotted paths: ``service.max_frame_age_s``, ``camera.rate_hz``
(every ``[[camera]]``), ``workspace.min`` (every coordinate). Command-line values that are no
configuration key have keys of their own command: ``serve.timeout_ms`` (``CLI_PREFIXES``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from pointfence.kernels.errors import InputError


@dataclass(frozen=True)
class Limit:
    """Allowed range ``lo <= value <= hi`` (inclusive) of one key, its unit and why."""

    lo: float
    hi: float
    unit: str
    why: str
    integer: bool = False


LIMITS: dict = {
    # -- [service]: the degraded-mode thresholds -------------------------------------------
    "service.rate_hz": Limit(250.0, 10000.0, "Hz",
                             "below 250 Hz stiff fixtures go unstable and a fault holds the arm only a tick of "
                             "4 ms or more later; above 10 kHz no tick fits its kernel launch"),
    "service.stale_s": Limit(0.001, 1.0, "s", "a camera silent for a second is stale whatever its rate"),
    "service.max_frame_age_s": Limit(0.001, 1.0, "s",
                                     "tissue moves (breathing, the instrument's push) by up to a centimetre a "
                                     "second: a snapshot older than 1 s no longer shows where it is (S2)"),
    "service.force_ramp_s": Limit(0.001, 0.5, "s",
                                  "a faulted arm's force must be gone within half a second (S3); below one "
                                  "1 kHz tick the ramp is a step that jolts the operator's hand"),
    "service.max_lateness_s": Limit(0.0005, 1.0, "s",
                                    "a tick that starts a second late is a stalled loop and must hold the arm "
                                    "on any machine, however loaded; below half a tick every tick is late"),
    "service.recover_s": Limit(0.01, 10.0, "s",
                               "a fault must stay clear for 10 ticks at least before the arm re-couples, or a "
                               "flapping condition re-couples on one good sample; beyond 10 s recovery never "
                               "comes in practice"),
    "service.self_filter_margin": Limit(0.0, 0.01, "m",
                                        "the margin is cut around the robot's own tool: more than 1 cm erases "
                                        "protected surface in front of the tool (S5)"),
    "service.proxies": Limit(1, 4096, "", "the most proxies one batch renders (the warp backend's cap)", True),
    "service.robot_watchdog_s": Limit(0.002, 0.25, "s",
                                      "how long the hosted robot process may stay silent before every arm reads "
                                      "FAULT (S9): an arm moving at 2 m/s goes half a metre in 0.25 s "
                                      "(robot/hosted.py WATCHDOG_MAX_S); below two of its 1 kHz steps any "
                                      "scheduling hiccup faults every arm"),
    "robot.measured_timeout_s": Limit(0.002, 0.25, "s",
                                      "how long a CRTK arm may go without a fresh measured_cp before it reads FAULT "
                                      "(S9): as robot_watchdog_s, an arm moving at 2 m/s goes half a metre in 0.25 s; "
                                      "below two 1 kHz samples one lost message faults the arm"),
    # -- [teleop] ------------------------------------------------------------------------------
    "teleop.scale": Limit(1e-3, 1.0, "",
                          "robot motion per master motion: a surgical robot scales the hand's motion down; "
                          "above 1 it amplifies tremor and every error of the operator"),
    "teleop.max_robot_speed": Limit(1e-4, 2.0, "m/s",
                                    "the bound on every command increment: 2 m/s is above any surgeon's hand "
                                    "(peaks near 1 m/s) at scale 1; beyond it the bound bounds nothing"),
    "teleop.max_angular_speed": Limit(1e-3, 10.0, "rad/s",
                                      "the bound on every orientation command increment: a surgeon's wrist turns "
                                      "at up to a few rad/s; beyond 10 rad/s a tool swings its jaws faster than "
                                      "anyone can watch and the bound bounds nothing"),
    "teleop.max_jaw_speed": Limit(1e-3, 20.0, "rad/s",
                                  "the bound on every jaw command increment: a grasp closes in a few tenths of a "
                                  "second (a few rad/s); beyond 20 rad/s the jaw snaps shut on tissue"),
    # -- [haptics] -----------------------------------------------------------------------------
    "haptics.max_force": Limit(1e-3, 20.0, "N",
                               "the force saturation on the operator's hand: 20 N is above the peak of the "
                               "strongest commercial haptic masters (Phantom Premium 22 N peak, omega.x 12 N)"),
    "haptics.k_spring": Limit(0.0, 10000.0, "N/m",
                              "the fixture/rendering stiffness: 10 kN/m is the stiffest commercial masters "
                              "render; stiffer walls are not passive at 1 kHz and buzz or go unstable"),
    "haptics.damping": Limit(0.0, 50.0, "N s/m", "above 50 N s/m the virtual damper is no longer passive at 1 kHz"),
    "haptics.step": Limit(1e-6, 0.01, "m",
                          "the proxy's largest move per iteration: longer steps jump through a fixture shell"),
    "haptics.r3": Limit(0.001, 0.05, "m", "the proxy's outer band, which bounds r1 < r2 < r3: a proxy of "
                                         "centimetres no longer follows an instrument tip; it also sets the hash reach"),
    "haptics.fir_taps": Limit(1, 256, "", "the force filter's length: 256 taps at 1 kHz delay the force by 128 ms, "
                                          "more lags the contact it renders", True),
    "haptics.max_steps": Limit(1, 1000, "", "proxy iterations per tick: more cannot finish within a 1 ms tick", True),
    # -- [fixture] and [hash] ------------------------------------------------------------------
    "fixture.radius": Limit(0.001, 0.1, "m",
                            "below 1 mm the forbidden region is thinner than the depth noise (sigma about "
                            "1.4 mm at 1 m); above 10 cm it hides the anatomy it protects and fills the hash"),
    "fixture.radius_max": Limit(0.001, 0.1, "m", "the adaptive radius's ceiling (see radius)"),
    "fixture.k_sigma": Limit(0.0, 10.0, "", "radius grown by k_sigma noise sigmas: 10 sigma covers any real noise"),
    "hash.cell_size": Limit(1e-4, 0.5, "m", "a half-metre cell puts the whole workspace in a few cells and every "
                                            "query visits every point: ticks overrun"),
    # -- [workspace] -----------------------------------------------------------------------------
    "workspace.min": Limit(-5.0, 5.0, "m", "a surgical robot's workspace lies within 5 m of its base"),
    "workspace.max": Limit(-5.0, 5.0, "m", "a surgical robot's workspace lies within 5 m of its base"),
    # -- [[camera]] ------------------------------------------------------------------------------
    "camera.rate_hz": Limit(0.1, 1000.0, "Hz", "no depth camera delivers more than 1000 frames a second"),
    "camera.width": Limit(1, 16384, "px", "no depth camera has a side of more than 16384 pixels", True),
    "camera.height": Limit(1, 16384, "px", "no depth camera has a side of more than 16384 pixels", True),
    "camera.depth_scale": Limit(1e-6, 0.1, "m/unit", "depth units finer than a micrometre or coarser than 10 cm are no depth camera's"),
    "camera.z_min": Limit(0.0, 20.0, "m", "depth cameras measure at most about 20 m"),
    "camera.z_max": Limit(0.0, 20.0, "m", "depth cameras measure at most about 20 m"),
    "camera.max_code": Limit(1, 65535, "", "depth images are 16-bit", True),
    # -- [motion]: fixture prediction ------------------------------------------------------------
    "motion.latency": Limit(0.0, 0.5, "s", "a camera latency over 0.5 s is a stalled camera, not one to predict"),
    "motion.max_age": Limit(0.0, 1.0, "s", "extrapolating a snapshot more than 1 s ahead (max_frame_age_s's "
                                           "ceiling) invents the scene"),
    "motion.capture": Limit(0.0, 0.5, "m", "a 50 cm displacement between two snapshots is not one surface moving"),
    "motion.cell": Limit(0.0, 0.5, "m", "see [hash] cell_size"),
    "motion.v_min": Limit(0.0, 0.1, "m/s", "speeds below v_min are taken as noise and zeroed: above 10 cm/s that "
                                           "would freeze real tissue motion"),
    "motion.v_max": Limit(0.0, 10.0, "m/s", "no tissue or instrument in the scene moves at 10 m/s"),
    "motion.max_gap": Limit(0.0, 1.0, "s", "two snapshots more than 1 s apart give no velocity"),
    "motion.planarity": Limit(0.0, 1.0, "", "a ratio of covariance eigenvalues"),
    "motion.count_ratio": Limit(1.0, 100.0, "", "blocks whose point counts differ 100-fold are not one surface"),
    "motion.min_points": Limit(1, 100000, "", "no block holds more points than a frame", True),
    # -- command-line values of `pointfence serve` (no configuration key) -----------------------
    "serve.timeout_ms": Limit(1, 1000, "ms",
                              "a master silent for longer is dropped and its arm holds: beyond 1 s (the "
                              "protocol's MAX_TIMEOUT_MS) the arm follows a hand that may have let go; "
                              "below one 1 kHz tick every client times out", True),
}

#: key prefixes of ``LIMITS`` entries that bound command-line values, not configuration keys
CLI_PREFIXES = ("serve.",)


def check(key: str, value, where: str = "") -> float:
    """``value`` of configuration key ``key`` (a ``LIMITS`` key), checked against its limit;
    ``where`` names it in the message (default: ``key``). Returns it as float (int for integer
    keys); InputError when it is not a finite number or lies outside the limit."""
    lim = LIMITS[key]
    where = where or key
    unit = f" {lim.unit}" if lim.unit else ""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{where} = {value!r}; expected a finite number ({lim.lo:g}..{lim.hi:g}{unit})")
    if lim.integer and value != int(value):
        raise InputError(f"{where} = {value!r}; expected an integer {lim.lo:g}..{lim.hi:g}")
    if value > lim.hi:
        raise InputError(f"{where} = {value:g}{unit} is above its hard limit of {lim.hi:g}{unit} ({lim.why}); "
                         f"use a value <= {lim.hi:g}")
    if value < lim.lo:
        raise InputError(f"{where} = {value:g}{unit} is below its hard limit of {lim.lo:g}{unit} ({lim.why}); "
                         f"use a value >= {lim.lo:g}")
    return int(value) if lim.integer else float(value)
