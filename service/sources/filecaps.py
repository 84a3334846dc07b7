"""Hard caps on the sizes that frame files declare, checked before anything is allocated.

A file header (PCD ``WIDTH``/``HEIGHT``/``POINTS``, a PCLZF image size, an LZF block's
uncompressed size) is input like any other: a corrupt or hostile one must not make the reader
allocate gigabytes. Every reader checks each declared size against these caps and against the
file's actual size first, and refuses with an ``InputError`` naming the file, the field and the
value.
"""
from __future__ import annotations

import os
from pathlib import Path

from pointfence.kernels.errors import InputError

#: largest frame file read (bytes): a 640x480 PCD with every field is about 10 MB; 1 GiB leaves
#: room for large organised clouds and still refuses a stray disk image or a device file
MAX_FILE_BYTES = 1 << 30
#: largest image side (px) a header may declare: depth cameras deliver at most a few thousand
MAX_SIDE = 16384
#: most points (pixels) per frame: 64 Mpx, 100 times a 640x480 Kinect frame
MAX_POINTS = 1 << 26
#: most values per PCD field (COUNT): PCL's largest descriptor (VFH) has 308
MAX_COUNT = 4096


def read_capped(path: Path, what: str) -> bytes:
    """The bytes of ``path``; InputError when it cannot be read or is over ``MAX_FILE_BYTES``
    (checked on the file's size before reading)."""
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size > MAX_FILE_BYTES:
                raise InputError(f"{path}: {size} bytes, over the {MAX_FILE_BYTES}-byte limit for one frame file; "
                                 f"expected {what}")
            return f.read(size)  # what it held when opened: a file growing meanwhile is read only that far
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror}); expected {what}") from None


def check_count(path, field: str, value: int, maximum: int, minimum: int = 1) -> int:
    """``value`` of header field ``field``, refused outside ``minimum..maximum``."""
    if not minimum <= value <= maximum:
        raise InputError(f"{path}: header field {field} = {value}; expected {minimum}..{maximum}")
    return value


def check_data_size(path, field: str, need: int, have: int) -> None:
    """Refuse a header that promises ``need`` bytes of data when the file holds only ``have``."""
    if need > have:
        raise InputError(f"{path}: header field {field} needs {need} bytes of data, the file holds {have} after the "
                         "header (truncated or corrupt file); expected a complete file")
