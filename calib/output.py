"""Writing calibration results as ``[[camera]]`` keys of the scene configuration (TOML).

``camera_snippet(name, keys)`` renders one ``[[camera]]`` table; ``update_config(path, name,
keys)`` puts the keys into the entry ``name`` of a configuration file (adding the entry when it
is missing), checks the result with ``pointfence.service.config.parse`` and replaces the file
atomically, changing only those keys (comments and layout stay) and keeping every earlier
version as a numbered backup (``<file>.bak``, ``<file>.bak.2``, ...). Key names and units are those of
``service/config.py``: fx, fy, cx, cy (px), width, height, dist (k1, k2, p1, p2, k3),
T_world_cam (16 numbers, row-major, camera -> robot base), noise = {a = m, b = 1/m}.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
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
        if k not in ("name", "source"):
            lines.append(_statement(k, v))
    return "\n".join(lines) + "\n"


def _statement(k: str, v: Any) -> str:
    """``k = v`` as TOML (T_world_cam: four rows of four, on five lines); ``v`` normalised."""
    if k == "T_world_cam":
        rows = [", ".join(_scalar(x) for x in v[i:i + 4]) for i in range(0, 16, 4)]
        return "T_world_cam = [\n    " + ",\n    ".join(rows) + ",\n]"
    return f"{k} = {_scalar(v)}"


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


@dataclass
class ConfigUpdate:
    """What ``update_config`` did: ``doc`` the new document, ``backup`` where the previous
    version was kept (None for a new file), ``layout_kept`` False when the file had to be
    rewritten whole (its comments are then only in the backup)."""

    doc: dict
    backup: Optional[Path]
    layout_kept: bool

    def describe(self, path) -> str:
        """One line for the user: what was written and where the previous version is."""
        if self.backup is None:
            return f"wrote {path}"
        kept = "" if self.layout_kept else ("; its layout could not be edited in place, so it was rewritten "
                                             "without comments: they are in the backup")
        return f"previous version kept in {self.backup}{kept}"


def update_config(path, name: str, keys: dict, source: Optional[str] = None) -> ConfigUpdate:
    """Put ``keys`` into the ``[[camera]]`` entry ``name`` of the configuration file ``path``
    (created when missing; a new entry needs ``source``).

    Only the keys given (and ``source``) change: comments, blank lines, key order and every
    other table stay as they were (``toml_edit``); the edited text is parsed back and must give
    exactly the new document, else the file is rewritten whole (``dumps``). The result must
    pass ``service.config.parse``. The file is replaced atomically and its previous version
    kept as a new numbered backup (``pointfence.service.files.write_atomic``)."""
    from pointfence.service import config
    from pointfence.service.files import write_atomic

    from .toml_edit import set_keys

    p = Path(path)
    doc: dict = {}
    text = ""
    if p.exists():
        text = p.read_text()
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise InputError(f"{p}: not valid TOML ({e}); fix it or write the snippet elsewhere with --out") from None
    cams = doc.setdefault("camera", [])
    if not isinstance(cams, list) or not all(isinstance(c, dict) for c in cams):
        raise InputError(f"{p}: camera = {cams!r}; expected [[camera]] tables")
    index = next((i for i, c in enumerate(cams) if c.get("name") == name), None)
    new = normalise_keys(keys)
    if index is None:
        if not source:
            have = ", ".join(repr(c.get("name")) for c in cams) or "none"
            raise InputError(f"{p}: no [[camera]] named {name!r} (cameras: {have}); pass --source to add it")
        cams.append({"name": name, "source": source, **new})
        sep = "" if not text or text.endswith("\n\n") else "\n" if text.endswith("\n") else "\n\n"
        edited = text + sep + camera_snippet(name, keys, source)
    else:
        if source:
            new = {"source": source, **new}
        cams[index].update(new)
        try:
            edited = set_keys(text, "camera", index, {k: _statement(k, v) for k, v in new.items()})
        except InputError:
            edited = None
    config.parse(doc, str(p))  # refuse to write a file the service would reject
    try:
        layout_kept = edited is not None and tomllib.loads(edited) == doc
    except tomllib.TOMLDecodeError:
        layout_kept = False
    backup = write_atomic(p, edited if layout_kept else dumps(doc))
    return ConfigUpdate(doc, backup, layout_kept)


def write_snippet(path, snippet: str) -> str:
    """Write a ``[[camera]]`` snippet to ``path`` atomically, keeping any earlier file as a
    backup; the line to tell the user."""
    from pointfence.service.files import write_atomic

    backup = write_atomic(path, snippet)
    return f"wrote {path}" + (f" (previous version kept in {backup})" if backup else "")


def emit(args, name: str, keys: dict, comment: str) -> str:
    """Common output of the calib subcommands: print the snippet; ``--out`` writes it to a file;
    ``--config`` merges it into a scene configuration."""
    snippet = camera_snippet(name, keys, getattr(args, "source", None), comment)
    print(snippet, end="")
    if getattr(args, "out", None):
        print(f"# {write_snippet(args.out, snippet)}")
    if getattr(args, "config", None):
        res = update_config(args.config, name, keys, getattr(args, "source", None))
        print(f"# updated [[camera]] {name!r} in {args.config}; {res.describe(args.config)}")
    return snippet
