"""Settings tables as dataclasses: one table of the scene configuration is one dataclass, and its
fields are the table's keys, their types, their defaults and their docs (``setting``).

``parse_table(cls, table, where)`` checks a TOML table against the dataclass and returns an
instance. Everything it checks is derived from the fields:

* the known keys are the field names; an unknown key is an ``InputError`` naming the key, the
  table (``where``), the closest known key and every known key;
* the type is the field's annotation (or ``setting(toml=...)`` where the TOML form differs from
  the attribute's, e.g. 16 numbers for a 4x4 transform): ``bool``, ``int``, ``float``, ``str``,
  ``Literal[...]`` (one of the names), ``Tuple[float, float, float]`` (a list of exactly 3
  numbers), ``Tuple[float, ...]`` (a list of numbers), ``dict`` (a free table), a nested
  dataclass (a sub-table), ``Optional[X]`` (None: the default is computed, see the field's
  ``default_doc``) and ``Union[str, SomeTable]``; a wrong type is an ``InputError`` naming the
  value and the expected type;
* ranges: ``lo`` / ``hi`` / ``positive`` of the field, and the hard limit
  ``limits.LIMITS["<table>.<key>"]`` (SAFETY.md S7) where one exists for the key;
* defaults: the dataclass's own (a key not given is not passed: the dataclass fills it in);
  relations between keys are the dataclass's ``__post_init__``; a table whose relations say more
  than its limits (``[motion]``: v_min > v_max) sets ``RELATIONS_FIRST = True`` and has its
  limits checked after them.

``rows(cls)`` lists (key, type, default, doc) for the README's settings table.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
import typing
from typing import Any, Literal, Optional, Tuple, Union

from pointfence.kernels.errors import InputError

from . import limits

_NONE = type(None)


def setting(default=dataclasses.MISSING, *, doc: str, factory=None, lo: Optional[float] = None,
            hi: Optional[float] = None, positive: bool = False, toml=None, convert=None, parse=None,
            default_doc: Optional[str] = None, hint: Optional[str] = None):
    """A field of a settings table: ``doc`` is its one-line description with units; ``lo`` /
    ``hi`` / ``positive`` bound a number; ``toml`` is the TOML type where it differs from the
    annotation and ``convert`` maps the checked TOML value to the attribute; ``parse(value,
    label)`` replaces the generic check (tables with rules of their own, e.g. ``[robot]``);
    ``default_doc`` describes a computed default (None); ``hint`` is added to type errors."""
    md = {"doc": doc, "lo": lo, "hi": hi, "positive": positive, "toml": toml, "convert": convert, "parse": parse,
          "default_doc": default_doc, "hint": hint}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=md)
    return dataclasses.field(default=default, metadata=md)


def fields(cls) -> tuple:
    """The settings of table ``cls``: (name, TOML type, metadata) per field, in order."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        md = dict(f.metadata) if "doc" in f.metadata else {"doc": "", "toml": None}
        out.append((f.name, md.get("toml") or hints[f.name], md, f))
    return tuple(out)


def keys(cls) -> tuple:
    """The keys of table ``cls`` (its field names)."""
    return tuple(f.name for f in dataclasses.fields(cls))


def unknown_key(key: str, known, where: str, extra: str = "") -> InputError:
    """The error for ``key`` not among ``known`` in table ``where``."""
    known = sorted(known)
    near = difflib.get_close_matches(str(key), known, n=1)
    hint = f"; did you mean {near[0]!r}?" if near else ";"
    return InputError(f"{where}: unknown key {key!r}{hint}{extra} Known keys: {', '.join(known)}")


def check_keys(table: Any, known, where: str) -> dict:
    """``table`` as a dict whose keys are all in ``known``."""
    if not isinstance(table, dict):
        raise InputError(f"{where}: expected a table, got {type(table).__name__} {table!r}")
    for key in table:
        if key not in known:
            raise unknown_key(key, known, where)
    return table


def describe(tp, md: Optional[dict] = None) -> str:
    """The TOML type ``tp`` in words ("an integer 0-99", "a list of 3 numbers")."""
    md = md or {}
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Union:
        arms = [a for a in args if a is not _NONE]
        return " or ".join(describe(a, md) for a in arms)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if tp is bool:
        return "true or false"
    lo, hi = md.get("lo"), md.get("hi")
    if tp is int:
        if lo is not None and hi is not None:
            return f"an integer {lo:g}-{hi:g}"
        return "an integer" + (f" >= {lo:g}" if lo is not None else "")
    if tp is float:
        if md.get("positive"):
            return "a number > 0"
        if lo is not None:
            return f"a number >= {lo:g}" + (f" and <= {hi:g}" if hi is not None else "")
        return "a finite number"
    if tp is str:
        return "a string"
    if tp is dict:
        return "a table"
    if origin in (tuple, Tuple):
        if len(args) == 2 and args[1] is Ellipsis:
            inner = describe(args[0], md)
            return "a list of numbers" if args[0] is float else f"a list of ({inner})"
        return f"a list of {len(args)} numbers"
    if dataclasses.is_dataclass(tp):
        return f"a table ({', '.join(keys(tp))})"
    return getattr(tp, "__name__", str(tp))


def _fits(tp, v) -> bool:
    """Whether ``v`` has the TOML shape of ``tp`` (to pick a Union's arm)."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp) or tp is dict:
        return isinstance(v, dict)
    if origin in (tuple, Tuple):
        return isinstance(v, (list, tuple))
    if tp is str or origin is Literal:
        return isinstance(v, str)
    return True


def check_value(tp, v: Any, label: str, md: Optional[dict] = None):
    """``v`` checked against TOML type ``tp`` and the range of ``md`` (see ``setting``)."""
    md = md or {}
    origin, args = typing.get_origin(tp), typing.get_args(tp)

    def bad(extra: str = ""):
        hint = md.get("hint")
        return InputError(f"{label} = {v!r}; expected {extra or describe(tp, md)}" + (f" ({hint})" if hint else ""))

    if origin is Union:
        if v is None and _NONE in args:
            return None
        for arm in (a for a in args if a is not _NONE):
            if _fits(arm, v):
                return check_value(arm, v, label, md)
        raise bad()
    if origin is Literal:
        if v not in args:
            near = difflib.get_close_matches(str(v), [str(a) for a in args], n=1)
            raise bad(f"one of {', '.join(repr(a) for a in args)}" + (f" (did you mean {near[0]!r}?)" if near else ""))
        return v
    if tp is bool:
        if not isinstance(v, bool):
            raise bad()
        return v
    if tp is str:
        if not isinstance(v, str):
            raise bad()
        return v
    if tp is dict:
        if not isinstance(v, dict):
            raise bad()
        return dict(v)
    if tp in (int, float):
        ok = not isinstance(v, bool) and isinstance(v, numbers.Real) and math.isfinite(v)
        if not ok or (tp is int and v != int(v)):
            raise bad()
        lo, hi = md.get("lo"), md.get("hi")
        if (md.get("positive") and v <= 0) or (lo is not None and v < lo) or (hi is not None and v > hi):
            raise bad()
        return int(v) if tp is int else float(v)
    if origin in (tuple, Tuple):
        var = len(args) == 2 and args[1] is Ellipsis
        if hasattr(v, "tolist") and getattr(v, "ndim", 0) >= 1:     # a NumPy array (programmatic tables)
            v = v.ravel().tolist() if args[0] is float else v.tolist()
        if not isinstance(v, (list, tuple)):
            raise bad()
        if not var and len(v) != len(args):
            raise bad()
        return tuple(check_value(args[0] if var else args[i], x, f"{label}[{i}]", md) for i, x in enumerate(v))
    if dataclasses.is_dataclass(tp):
        return parse_table(tp, v, label)
    raise TypeError(f"settings type {tp!r} of {label} is not supported")


def parse_table(cls, table: Any, where: str, sep: str = " ", limit_prefix: Optional[str] = None):
    """Table ``table`` (a dict from TOML) checked against the settings dataclass ``cls``: an
    instance with the given keys and the dataclass's defaults for the others. ``where`` names
    the table in errors ("[service]"); a key is labelled ``where + sep + key``; its hard limit is
    ``limits.LIMITS[limit_prefix + "." + key]`` (default prefix: ``cls.TABLE``)."""
    check_keys(table, keys(cls), where)
    prefix = limit_prefix if limit_prefix is not None else getattr(cls, "TABLE", "")
    later = getattr(cls, "RELATIONS_FIRST", False)
    kw, deferred = {}, []
    for name, tp, md, f in fields(cls):
        label = f"{where}{sep}{name}"
        if name not in table:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise InputError(f"{where}: {name} is missing; expected {describe(tp, md)} ({md['doc']})")
            continue
        v = table[name]
        if md.get("parse") is not None:
            kw[name] = md["parse"](v, label)
            continue
        v = check_value(tp, v, label, md)
        lim = f"{prefix}.{name}"
        if lim in limits.LIMITS and v is not None:
            if later:
                deferred.append((lim, v, label))
            else:
                v = _limit(lim, v, label)
        kw[name] = md["convert"](v, label) if md.get("convert") is not None else v
    obj = cls(**kw)
    for lim, v, label in deferred:
        _limit(lim, v, label)
    return obj


def _limit(lim: str, v, label: str):
    """``v`` (a number or a tuple of numbers) within its hard limit ``limits.LIMITS[lim]``."""
    if isinstance(v, tuple):
        return tuple(limits.check(lim, x, f"{label}[{i}]") for i, x in enumerate(v))
    return limits.check(lim, v, label)


def default_of(f: dataclasses.Field):
    """The default value of field ``f`` (a fresh one for factories; MISSING for required keys)."""
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return f.default


def format_default(f: dataclasses.Field, md: dict) -> str:
    """The default of field ``f`` as the README writes it (TOML syntax; its ``default_doc`` for
    a computed one; "required" where there is none)."""
    if md.get("default_doc"):
        return md["default_doc"]
    v = default_of(f)
    if v is dataclasses.MISSING:
        return "required"
    return toml_value(v)


def toml_value(v) -> str:
    """``v`` in TOML syntax (numbers as Python's shortest repr, ``%g`` style)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, (int, float)):
        return f"{v:g}"
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"no TOML form for {v!r}")


def rows(cls, only=None) -> list:
    """(key, type, default, doc) of every key of table ``cls`` (or of the keys ``only``), in
    field order."""
    return [(name, describe(tp, md), format_default(f, md), md["doc"]) for name, tp, md, f in fields(cls)
            if only is None or name in only]
