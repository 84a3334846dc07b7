"""Writing files that users keep (configurations, calibrations, keys): atomically, with backups.

``write_atomic(path, data)`` guarantees, on a POSIX file system:

* **All or nothing.** The new content goes to a temporary file in the same directory, is
  flushed and ``fsync``-ed, then renamed over ``path`` with ``os.replace`` (atomic), and the
  directory is ``fsync``-ed so the rename itself survives a power loss. A crash, a full disk or
  an exception at any point leaves ``path`` either wholly old or wholly new, never partial, and
  removes the temporary file (a ``kill -9`` may leave one, named ``.<name>.*.tmp``).
* **Earlier versions are kept.** With ``keep_backups`` (the default) the current content is
  first copied to a new backup beside it: ``<name>.bak`` the first time, then ``<name>.bak.2``,
  ``<name>.bak.3``, ... (one above the highest number present, so the highest is the newest).
  An existing backup is never overwritten (each is created with a hard link, which fails
  rather than replace) and never deleted. The backup is itself written and ``fsync``-ed
  before the original is replaced.
* **The file's mode is kept** (a new file gets 0o666 minus the umask, or ``mode``), and a
  symbolic link is followed: its target is replaced, the link stays.
"""
from __future__ import annotations

import os
import re
import stat
import tempfile
from pathlib import Path
from typing import Optional, Union

#: the first backup of a file; later ones add ``.<n>``, n >= 2
BACKUP_SUFFIX = ".bak"


def _numbered(path: Path) -> list:
    """(number, path) of each backup of ``path`` (``.bak`` is number 1), sorted."""
    pat = re.compile(re.escape(path.name + BACKUP_SUFFIX) + r"(?:\.(\d+))?$")
    found = []
    if path.parent.is_dir():
        for p in path.parent.iterdir():
            m = pat.match(p.name)
            if m:
                found.append((int(m.group(1) or 1), p))
    return sorted(found)


def backups_of(path) -> list:
    """The backups ``write_atomic`` kept of ``path``, oldest first."""
    return [p for _, p in _numbered(Path(os.path.realpath(path)))]


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_temp(directory: Path, name: str, data: bytes, mode: int) -> str:
    """A new temporary file in ``directory`` holding ``data``, fsync-ed, with ``mode``; its path."""
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fchmod(f.fileno(), mode)
            os.fsync(f.fileno())
    except BaseException:
        os.unlink(tmp)
        raise
    return tmp


def _backup(target: Path, mode: int) -> Path:
    """Copy ``target`` to its next free backup name without ever replacing one; the backup's path."""
    tmp = _write_temp(target.parent, target.name, target.read_bytes(), mode)
    try:
        n = 1 + max((k for k, _ in _numbered(target)), default=0)
        while True:
            dest = target.with_name(target.name + BACKUP_SUFFIX + ("" if n == 1 else f".{n}"))
            try:
                os.link(tmp, dest)  # fails with FileExistsError instead of replacing
                return dest
            except FileExistsError:
                n += 1
    finally:
        os.unlink(tmp)


def write_atomic(path, data: Union[bytes, str], keep_backups: bool = True, mode: Optional[int] = None) -> Optional[Path]:
    """Replace the content of ``path`` with ``data`` (str is written as UTF-8) atomically,
    keeping the current content as a new backup first (see the module docstring for the
    guarantees). Returns the backup's path, or None when none was made (no earlier file, or
    ``keep_backups`` false). ``mode``: the permission bits; default: the existing file's, or
    0o666 minus the umask for a new file."""
    if isinstance(data, str):
        data = data.encode("utf-8")
    target = Path(os.path.realpath(path))
    exists = target.exists()
    if mode is None:
        if exists:
            mode = stat.S_IMODE(target.stat().st_mode)
        else:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
    backup = _backup(target, stat.S_IMODE(target.stat().st_mode)) if exists and keep_backups else None
    tmp = _write_temp(target.parent, target.name, data, mode)
    try:
        os.replace(tmp, target)
    except BaseException:
        os.unlink(tmp)
        raise
    _fsync_dir(target.parent)
    return backup
