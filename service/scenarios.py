"""The dissertation's chapter-3 experiments as scripted runs on synthetic scenes.

Each scenario is a configuration (the given one with its cameras pointed at a synthetic scene)
and a scripted master trajectory (master frame, scale 0.5 to the robot). The robot starts at
its home pose, tip at (0, 0, 0.167) m with the default mount.

* ``inclined_plane`` (fig. 3.8): a plane through (0, 0, 0.09) tilted 20 deg, protected (red)
  around its anchor; the tool is brought to (0.04, 0, 0.12) and then driven horizontally 12 cm
  towards -x, 2 cm into the 2 cm fixture.
* ``balloon`` (fig. 3.9): the red balloon (6 cm, on the table); the master pushes straight down
  ever deeper, 3.3 cm into the fixture at the end.
* ``rocking_platform`` (fig. 3.10): a platform through (0, 0, 0.08) rocking +/-10 deg about y
  with a 3 s period; the master takes the tool 5 cm off the rocking axis and 2 cm into the
  fixture and stays there while the platform moves (+/-9 mm under the tool).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .config import CameraConfig
from .masters import ScriptedMaster

SCENES = {
    "inclined_plane": ("synthetic:inclined_plane", {"position": [0.0, 0.0, 0.09], "angle_deg": 20.0, "disc_radius": 0.15}),
    "balloon": ("synthetic:sphere", {}),
    "rocking_platform": ("synthetic:rocking_platform", {"position": [0.0, 0.0, 0.08], "disc_radius": 0.15}),
}
NAMES = tuple(SCENES)


def scenario_config(cfg, name: str):
    """``cfg`` with every camera looking at scenario ``name``'s synthetic scene."""
    spec, opts = SCENES[name]
    cams = [CameraConfig(c.camera, spec, c.rate_hz, {**{k: v for k, v in c.options.items() if k in ("color", "seed")},
                                                    "color": True, **opts}) for c in cfg.cameras]
    return replace(cfg, cameras=cams)


def scenario_master(name: str) -> ScriptedMaster:
    """The scripted master of scenario ``name`` (times s, master-frame positions m)."""
    if name == "inclined_plane":
        t = [0.0, 0.2, 1.7, 1.9, 4.4, 4.8]
        p = [[0, 0, 0], [0, 0, 0], [0.08, 0, -0.094], [0.08, 0, -0.094], [-0.16, 0, -0.094], [-0.16, 0, -0.094]]
    elif name == "balloon":
        t = [0.0, 0.2, 1.0, 1.3, 2.3, 2.8]
        p = [[0, 0, 0], [0, 0, 0], [0, 0, -0.06], [0, 0, -0.06], [0, 0, -0.12], [0, 0, -0.12]]
    elif name == "rocking_platform":
        t = [0.0, 0.2, 2.2, 6.0]
        p = [[0, 0, 0], [0, 0, 0], [0.1, 0, -0.174], [0.1, 0, -0.174]]
    else:
        raise KeyError(name)
    return ScriptedMaster(np.array(t), np.array(p, float), name=name)
