"""A minimal, layout-preserving edit of one ``[[name]]`` table in TOML text.

``set_keys(text, "camera", 1, {"fx": "fx = 525.0", ...})`` replaces (or adds) the given keys in
the second ``[[camera]]`` table and leaves every other byte as it was: comments, blank lines,
key order, other tables. A replaced single-line key keeps its trailing comment. The edit works
on the text, statement by statement (a header, a ``key = value`` that may span lines, or a
comment/blank line); it does not check the result, so callers parse it and compare with the
document they expect (``calib.output.update_config`` does, and falls back to a full rewrite).
"""
from __future__ import annotations

import re
from typing import Iterator, Optional

from pointfence.kernels.errors import InputError


def _skip_string(text: str, i: int) -> int:
    """Index just past the TOML string starting at ``text[i]`` (', ", ''' or \"\"\")."""
    q = text[i]
    if text.startswith(q * 3, i):
        end = text.find(q * 3, i + 3)
        if end < 0:
            raise InputError("unterminated multi-line string in TOML text")
        while text.startswith(q, end + 3):  # up to two quotes may close the string's content
            end += 1
        return end + 3
    j = i + 1
    while j < len(text) and text[j] not in (q, "\n"):
        j += 2 if q == '"' and text[j] == "\\" else 1
    if j >= len(text) or text[j] != q:
        raise InputError("unterminated string in TOML text")
    return j + 1


def _value_end(text: str, i: int) -> tuple[int, Optional[int]]:
    """(index after the newline ending the value that starts at ``i``, index of its trailing
    ``#`` comment or None)."""
    depth, comment = 0, None
    while i < len(text):
        c = text[i]
        if c in "\"'":
            i = _skip_string(text, i)
            continue
        if c == "#":
            nl = text.find("\n", i)
            if depth == 0:
                return (len(text) if nl < 0 else nl + 1), i
            i = len(text) if nl < 0 else nl
            continue
        if c in "[{":
            depth += 1
        elif c in "]}":
            depth -= 1
        elif c == "\n" and depth <= 0:
            return i + 1, comment
        i += 1
    return len(text), comment


def _key_name(text: str, i: int) -> tuple[str, int]:
    """(first dotted part of the key starting at ``i``, unquoted; index of its ``=``)."""
    if text[i] in "\"'":
        end = _skip_string(text, i)
        name = text[i + 1:end - 1]
    else:
        m = re.compile(r"[A-Za-z0-9_-]+").match(text, i)
        if not m:
            raise InputError(f"cannot read a TOML key at {text[i:i + 20]!r}")
        name, end = m.group(0), m.end()
    eq = end
    while eq < len(text) and text[eq] != "=":
        if text[eq] in "\"'":
            eq = _skip_string(text, eq)
            continue
        if text[eq] == "\n":
            raise InputError(f"TOML key {name!r} has no '='")
        eq += 1
    return name, eq


def statements(text: str) -> Iterator[tuple]:
    """(start, end, kind, name, comment) of each statement: kind "header" (name: the header
    without spaces, e.g. "[[camera]]"), "key" (name: the key's first dotted part; comment: the
    index of a trailing comment or None) or "other" (blank or comment lines)."""
    i = 0
    while i < len(text):
        j = i
        while j < len(text) and text[j] in " \t":
            j += 1
        nl = text.find("\n", j)
        eol = len(text) if nl < 0 else nl + 1
        if j >= len(text) or text[j] in "\r\n#":
            yield i, eol, "other", None, None
            i = eol
        elif text[j] == "[":
            end, _ = _value_end(text, j)
            head = text[j:end].split("#", 1)[0]
            yield i, end, "header", re.sub(r"\s", "", head), None
            i = end
        else:
            name, eq = _key_name(text, j)
            end, comment = _value_end(text, eq + 1)
            yield i, end, "key", name, comment
            i = end


def set_keys(text: str, table: str, index: Optional[int], lines: dict) -> str:
    """``text`` with the keys of ``lines`` (key -> its whole TOML statement, without newline)
    set in the ``index``-th (0-based) ``[[table]]`` (``index`` None: the plain table ``[table]``):
    a key defined there (also as dotted keys ``key.x = ...``) is replaced in place, a new one is
    added after the table's last key."""
    stmts = list(statements(text))
    heads = [k for k, s in enumerate(stmts) if s[2] == "header"]
    header = f"[{table}]" if index is None else f"[[{table}]]"
    mine = [k for k in heads if stmts[k][3] == header]
    index = 0 if index is None else index
    if index >= len(mine):
        raise InputError(f"no {header} table number {index + 1} in the text ({len(mine)} found)")
    first = mine[index]
    last = next((k for k in heads if k > first), len(stmts)) - 1
    body = [k for k in range(first + 1, last + 1) if stmts[k][2] == "key"]
    edits, added = [], []  # (start, end, replacement); statements of new keys
    for key, line in lines.items():
        hits = [k for k in body if stmts[k][3] == key]
        if hits:
            start, end, _, _, comment = stmts[hits[0]]
            indent = re.match(r"[ \t]*", text[start:end]).group(0)
            tail = ""
            if comment is not None and "\n" not in text[start:comment]:  # keep a one-line key's comment
                before = text[start:comment]
                tail = before[len(before.rstrip()):] + text[comment:end].rstrip("\r\n")
            nl = text[end - 2:end] if text.endswith("\r\n", 0, end) else "\n"
            edits.append((start, end, indent + line + tail + nl))
            edits += [(stmts[k][0], stmts[k][1], "") for k in hits[1:]]
        else:
            added.append(line)
    if added:
        after = body[-1] if body else first
        at = stmts[after][1]
        indent = re.match(r"[ \t]*", text[stmts[after][0]:]).group(0) if body else ""
        sep = "" if text[:at].endswith("\n") else "\n"
        edits.append((at, at, sep + "".join(indent + line + "\n" for line in added)))
    for start, end, new in sorted(edits, key=lambda e: (e[0], e[1]), reverse=True):
        text = text[:start] + new + text[end:]
    return text
