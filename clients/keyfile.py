"""Pre-shared key files (``clients/PROTOCOL.md`` section 3.1 is the normative format).

A key file holds the key as 32 to 128 hexadecimal digits (16 to 64 bytes; 64 digits = 32
random bytes recommended), upper or lower case, optionally followed by ONE line ending
(``\\n`` or ``\\r\\n``), and nothing else: no spaces, no ``0x``, no second line, no raw bytes.
An all-zero key is refused (it is a placeholder, not a secret), and so is a file that its
group or other users may read or write (mode bits 0o077: ``chmod 600 FILE``). The C SDK's
``pf_load_key`` accepts exactly the same files (``clients/vectors/keyfiles.json`` is the shared
table both test suites run).
"""
from __future__ import annotations

import os
import stat
from pathlib import Path

from pointfence.kernels.errors import InputError

KEY_MIN, KEY_MAX = 16, 64            # bytes
MAX_FILE = 2 * KEY_MAX + 2           # bytes: 128 hex digits and "\r\n"
_HEX = frozenset(b"0123456789abcdefABCDEF")


def check_key(key) -> bytes:
    """A pre-shared key given as bytes: 16 to 64 bytes, not all zero."""
    if not isinstance(key, (bytes, bytearray)) or not KEY_MIN <= len(key) <= KEY_MAX:
        what = f"{len(key)} bytes" if isinstance(key, (bytes, bytearray)) else type(key).__name__
        raise InputError(f"pre-shared key of {what}; expected {KEY_MIN} to {KEY_MAX} bytes "
                         "(32 random bytes recommended: `pointfence serve --new-key FILE`)")
    if not any(key):
        raise InputError("pre-shared key is all zero bytes; use a random key (`pointfence serve --new-key FILE`)")
    return bytes(key)


def parse_key_text(data: bytes, where: str = "key file") -> bytes:
    """The key in the bytes of a key file (format in the module docstring); InputError naming
    ``where`` and the fault otherwise."""
    body = data
    if body.endswith(b"\r\n"):
        body = body[:-2]
    elif body.endswith(b"\n"):
        body = body[:-1]
    fix = f"expected {2 * KEY_MIN} to {2 * KEY_MAX} hex digits and at most one newline (`pointfence serve --new-key FILE` writes one)"
    if not body:
        raise InputError(f"{where}: empty; {fix}")
    bad = next((i for i, c in enumerate(body) if c not in _HEX), None)
    if bad is not None:
        raise InputError(f"{where}: byte {bad} ({body[bad:bad + 1]!r}) is not a hex digit; {fix}")
    if len(body) % 2 or not 2 * KEY_MIN <= len(body) <= 2 * KEY_MAX:
        raise InputError(f"{where}: {len(body)} hex digits; {fix}")
    key = bytes.fromhex(body.decode("ascii"))
    if not any(key):
        raise InputError(f"{where}: the key is all zero; replace it with a random key (`pointfence serve --new-key FILE`)")
    return key


def load_key(path) -> bytes:
    """Read and check a key file: a regular file of mode 0600 or stricter, in the format above."""
    p = Path(path)
    try:
        fd = os.open(str(p), os.O_RDONLY)
    except FileNotFoundError:
        raise InputError(f"key file {str(p)!r} not found; create one with `pointfence serve --new-key {p}`") from None
    except OSError as e:
        raise InputError(f"key file {str(p)!r} cannot be opened ({e.strerror}); check its path and owner") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"key file {str(p)!r} is not a regular file")
        if st.st_mode & 0o077:
            raise InputError(f"key file {str(p)!r} has mode {stat.S_IMODE(st.st_mode):04o}: its group or other users have access to the secret; "
                             f"run `chmod 600 {p}` (and replace the key if it may have leaked: "
                             "`pointfence serve --new-key NEWFILE`)")
        data = os.read(fd, MAX_FILE + 1)
    finally:
        os.close(fd)
    if len(data) > MAX_FILE:
        raise InputError(f"key file {str(p)!r} is longer than {MAX_FILE} bytes; expected only the key's hex digits "
                         "and at most one newline")
    return parse_key_text(data, f"key file {str(p)!r}")
