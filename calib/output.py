"""Writing calibration results as ``[[camera]]`` keys of the scene configuration (TOML).

``camera_snippet(name, keys)`` renders one ``[[camera]]`` table; ``update_config(path, name,
keys)`` puts the keys into the entry ``name`` of a configuration file (adding the entry when it
is missing), checks the result with ``pointfence.service.config.parse`` and rewrites the file,
keeping the previous version as ``<file>.bak``. Key names and units are those of
``service/config.py``: fx, fy, cx, cy (px), width, height, dist (k1, k2, p1, p2, k3),
T_world_cam (16 numbers, row-major, camera -> robot base), noise = {a = m, b = 1/m}.
"""
from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import Any, Optional

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

import numpy as np

from pointfence.kernels.errors import InputError


def _scalar(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if not math.isfinite(f):
            raise InputError(f"cannot write {f} to TOML; the calibration produced a non-finite value")
        return repr(f)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_scalar(x) for x in np.asarray(v, dtype=object).ravel().tolist()) + "]" \
            if isinstance(v, np.ndarray) else "[" + ", ".join(_scalar(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_scalar(x)}" for k, x in v.items()) + " }"
    raise InputError(f"cannot write {type(v).__name__} {v!r} to TOML")


def normalise_keys(keys: dict) -> dict:
    """Calibration values as config values: arrays to lists, T_world_cam to 16 numbers."""
    out = {}
    for k, v in keys.items():
        if k == "T_world_cam":
            v = [float(x) for x in np.asarray(v, dtype=np.float64).reshape(16)]
        elif isinstance(v, np.ndarray):
            v = v.tolist()
        elif isinstance(v, tuple):
            v = list(v)
        out[k] = v
    return out


def camera_snippet(name: str, keys: dict, source: Optional[str] = None, comment: Optional[str] = None) -> str:
    """One ``[[camera]]`` table as TOML text."""
    lines = []
    if comment:
        lines += [f"# {c}" for c in comment.splitlines()]
    lines.append("[[camera]]")
    lines.append(f"name = {_scalar(name)}")
    if source:
        lines.append(f"source = {_scalar(source)}")
    for k, v in normalise_keys(keys).items():
        if k in ("name", "source"):
            continue
        if k == "T_world_cam":
            rows = [", ".join(_scalar(x) for x in v[i:i + 4]) for i in range(0, 16, 4)]
            lines.append("T_world_cam = [\n    " + ",\n    ".join(rows) + ",\n]")
        else:
            lines.append(f"{k} = {_scalar(v)}")
    return "\n".join(lines) + "\n"


def dumps(doc: dict) -> str:
    """A configuration document (as tomllib reads it) back to TOML text."""
    top, tables, arrays = [], [], []
    for k, v in doc.items():
        if isinstance(v, dict):
            tables.append((k, v))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            arrays.append((k, v))
        else:
            top.append(f"{k} = {_scalar(v)}")
    parts = ["\n".join(top)] if top else []
    for k, v in tables:
        plain = {a: b for a, b in v.items() if not isinstance(b, dict)}
        sub = {a: b for a, b in v.items() if isinstance(b, dict)}
        body = "\n".join(f"{a} = {_scalar(b)}" for a, b in plain.items())
        parts.append(f"[{k}]\n{body}".rstrip())
        for a, b in sub.items():
            parts.append(f"[{k}.{a}]\n" + "\n".join(f"{c} = {_scalar(d)}" for c, d in b.items()))
    for k, items in arrays:
        for item in items:
            if k == "camera":
                parts.append(camera_snippet(item.get("name", ""), {a: b for a, b in item.items() if a not in ("name", "source")},
                                            item.get("source")).rstrip())
            else:
                parts.append(f"[[{k}]]\n" + "\n".join(f"{a} = {_scalar(b)}" for a, b in item.items()))
    return "\n\n".join(parts) + "\n"


def update_config(path, name: str, keys: dict, source: Optional[str] = None) -> dict:
    """Put ``keys`` into the ``[[camera]]`` entry ``name`` of the configuration file ``path``
    (created when missing; a new entry needs ``source``). Returns the new document."""
    p = Path(path)
    doc: dict = {}
    if p.exists():
        try:
            doc = tomllib.loads(p.read_text())
        except tomllib.TOMLDecodeError as e:
            raise InputError(f"{p}: not valid TOML ({e}); fix it or write the snippet elsewhere with --out") from None
    cams = doc.setdefault("camera", [])
    entry = next((c for c in cams if c.get("name") == name), None)
    if entry is None:
        if not source:
            have = ", ".join(repr(c.get("name")) for c in cams) or "none"
            raise InputError(f"{p}: no [[camera]] named {name!r} (cameras: {have}); pass --source to add it")
        entry = {"name": name, "source": source}
        cams.append(entry)
    elif source:
        entry["source"] = source
    entry.update(normalise_keys(keys))
    from pointfence.service import config

    config.parse(doc, str(p))  # refuse to write a file the service would reject
    if p.exists():
        shutil.copyfile(p, str(p) + ".bak")
    p.write_text(dumps(doc))
    return doc


def emit(args, name: str, keys: dict, comment: str) -> str:
    """Common output of the calib subcommands: print the snippet; ``--out`` writes it to a file;
    ``--config`` merges it into a scene configuration."""
    snippet = camera_snippet(name, keys, getattr(args, "source", None), comment)
    print(snippet, end="")
    if getattr(args, "out", None):
        Path(args.out).write_text(snippet)
        print(f"# wrote {args.out}")
    if getattr(args, "config", None):
        update_config(args.config, name, keys, getattr(args, "source", None))
        print(f"# updated [[camera]] {name!r} in {args.config} (previous version: {args.config}.bak)")
    return snippet
