"""The control API's bearer token: made per run by `pointfence serve`, read by `pointfence ctl`.

The token is 32 random bytes (64 hex digits), new for every run. ``serve`` writes it, once its
control port is bound, to a file only its user can read (mode 0600, written whole and renamed
into place): ``--control-token FILE``, else ``<run dir>/control-<port>.token`` where the run
dir is ``$XDG_RUNTIME_DIR/pointfence`` (or ``/tmp/pointfence-<uid>`` without it), a directory
of mode 0700 owned by the user (one that is not is refused: another user could read or swap
the token). Every request to the control API carries ``Authorization: Bearer <token>``; the
service compares it in constant time. ``ctl`` finds the same file from the port it talks to
(or ``--token-file``, ``$POINTFENCE_CONTROL_TOKEN``).
"""
from __future__ import annotations

import hmac
import os
import stat
from pathlib import Path
from typing import Optional

from pointfence.kernels.errors import InputError

TOKEN_BYTES = 32
TOKEN_ENV = "POINTFENCE_CONTROL_TOKEN"


def run_dir(create: bool = False) -> Path:
    """The user's private directory for per-run files (see the module docstring); with
    ``create`` it is made (mode 0700) if missing. Refused (``InputError``) if it is a symlink,
    not a directory, owned by another user, or open to group or others."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    d = Path(base) / "pointfence" if base else Path("/tmp") / f"pointfence-{os.geteuid()}"
    if create:
        try:
            os.mkdir(d, 0o700)
        except FileExistsError:
            pass
        except OSError as e:
            raise InputError(f"cannot create the run directory {d}: {e}; pass --control-token FILE "
                             "(a path in a directory you own)") from None
    try:
        st = os.lstat(d)
    except FileNotFoundError:
        return d
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        raise InputError(f"run directory {d} is not a plain directory (a symlink or a file); remove it "
                         "or pass --control-token FILE")
    if st.st_uid != os.geteuid():
        raise InputError(f"run directory {d} belongs to uid {st.st_uid}, not to you (uid {os.geteuid()}): "
                         "another user could read or replace the control token; remove it or pass "
                         "--control-token FILE")
    if st.st_mode & 0o077:
        raise InputError(f"run directory {d} has mode {stat.S_IMODE(st.st_mode):04o}; expected 0700 "
                         f"(chmod 700 {d}) so that no other user can reach the control token")
    return d


def default_token_path(port: int, create_dir: bool = False) -> Path:
    """Where the token of the control API on ``port`` lives by default."""
    return run_dir(create_dir) / f"control-{int(port)}.token"


def new_token() -> str:
    return os.urandom(TOKEN_BYTES).hex()


def write_token(path, token: str) -> Path:
    """Write ``token`` to ``path`` atomically, mode 0600 (a temporary file beside it, created
    exclusively, then renamed over ``path``)."""
    dest = Path(path)
    part = dest.with_name(f".{dest.name}.{os.getpid()}.part")
    try:
        fd = os.open(str(part), os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o600)
    except OSError as e:
        raise InputError(f"cannot write the control token to {dest}: {e}; choose another --control-token FILE") from None
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(token + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(part, dest)
    except BaseException:
        try:
            os.unlink(part)
        except OSError:
            pass
        raise
    return dest


def remove_token(path, token: str) -> None:
    """Delete the token file at the end of the run if it still holds this run's token."""
    try:
        if Path(path).read_text().strip() == token:
            os.unlink(path)
    except OSError:
        pass


def read_token(path, port: Optional[int] = None) -> str:
    """The token in ``path`` (for ``pointfence ctl``), with an error that says what to do when
    it cannot be read."""
    p = Path(path)
    where = f" for the control API on port {port}" if port is not None else ""
    try:
        fd = os.open(str(p), os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    except FileNotFoundError:
        raise InputError(f"no control token{where} at {p}: is `pointfence serve` running as this user with that "
                         "--control-port? (It writes the token there when its control API starts; with "
                         "`serve --control-token FILE` pass the same file as `ctl --token-file FILE`.)") from None
    except PermissionError:
        raise InputError(f"cannot read the control token {p}: permission denied; run `pointfence ctl` as the user "
                         "who runs `pointfence serve` (only that user may control the service)") from None
    except OSError as e:
        raise InputError(f"cannot read the control token {p}: {e}") from None
    with os.fdopen(fd) as fh:
        st = os.fstat(fh.fileno())
        if st.st_mode & 0o077:
            raise InputError(f"control token {p} has mode {stat.S_IMODE(st.st_mode):04o}: other users may have "
                             "read it; restart `pointfence serve` for a new token (it writes mode 0600)")
        text = fh.read(4 * TOKEN_BYTES).strip()
    if len(text) != 2 * TOKEN_BYTES or any(c not in "0123456789abcdef" for c in text):
        raise InputError(f"control token {p} is not a pointfence control token ({2 * TOKEN_BYTES} hex digits)")
    return text


class BearerCheck:
    """Checks a request's ``Authorization`` header against the run's token in constant time."""

    def __init__(self, token: str):
        self._token = token.encode()

    def check(self, header: Optional[str]) -> Optional[tuple]:
        """None if authorised, else (HTTP status, message): 401 without bearer credentials,
        403 with a wrong token. The scheme is case-insensitive (RFC 7235), the token exact."""
        scheme, _, cred = (header or "").strip().partition(" ")
        if scheme.lower() != "bearer":
            return 401, ("unauthenticated: every control request needs 'Authorization: Bearer <token>'; "
                         "`pointfence ctl` reads the token that `pointfence serve` wrote (see its "
                         "stderr: control token in ...)")
        if not hmac.compare_digest(cred.strip().encode("utf-8", "replace"), self._token):
            return 403, "wrong control token: refused (nothing changed)"
        return None
