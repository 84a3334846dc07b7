"""LZF decompression (liblzf format, as used by PCL's binary_compressed PCD and PCLZF files).

The stream is a sequence of chunks, each led by a control byte ``c``:

* ``c < 32``: a literal run of ``c + 1`` bytes follows;
* otherwise a back-reference: length ``c >> 5`` (7 means "add the next byte"), plus 2;
  offset ``((c & 31) << 8) + next byte + 1`` bytes back into the output.

Pure Python on ``bytearray`` slices; overlapping back-references (offset < length) repeat the
referenced pattern, as the byte-by-byte copy of the reference implementation does.
"""
from __future__ import annotations

from pointfence.kernels.errors import InputError

#: most output bytes one input byte of LZF can give: a 3-byte back-reference copies at most
#: 7 + 255 + 2 = 264 bytes (a 2-byte one 8, a literal run its own length)
MAX_RATIO = 88


def max_output(n_in: int) -> int:
    """The most bytes a valid LZF stream of ``n_in`` bytes decodes to (``MAX_RATIO * n_in``)."""
    return MAX_RATIO * max(0, int(n_in))


def lzf_decompress(data: bytes, out_len: int, what: str = "LZF data") -> bytes:
    """Decompress ``data`` to exactly ``out_len`` bytes; InputError naming ``what`` if corrupt.

    ``out_len`` is checked against what ``len(data)`` bytes can decode to (``max_output``) before
    the output is allocated: a header's uncompressed size cannot make it allocate more."""
    if not 0 <= out_len <= max_output(len(data)):
        raise InputError(f"{what}: uncompressed size {out_len} bytes cannot come from {len(data)} compressed bytes "
                         f"(LZF expands at most {MAX_RATIO}x); the header is corrupt")
    src = memoryview(bytes(data))
    out = bytearray(out_len)
    n = len(src)
    i = o = 0
    try:
        while i < n:
            c = src[i]
            i += 1
            if c < 32:
                run = c + 1
                if i + run > n or o + run > out_len:
                    raise IndexError
                out[o:o + run] = src[i:i + run]
                i += run
                o += run
                continue
            length = c >> 5
            if length == 7:
                length += src[i]
                i += 1
            ref = o - ((c & 31) << 8) - src[i] - 1
            i += 1
            length += 2
            if ref < 0 or o + length > out_len:
                raise IndexError
            dist = o - ref
            if dist >= length:
                out[o:o + length] = out[ref:ref + length]
            else:
                pattern = bytes(out[ref:o])
                out[o:o + length] = (pattern * (length // dist + 1))[:length]
            o += length
    except IndexError:
        raise InputError(f"{what}: corrupt LZF stream (at input byte {i} of {n}, output byte {o} of {out_len}); "
                         "expected a complete liblzf-compressed block") from None
    if o != out_len:
        raise InputError(f"{what}: LZF stream decoded to {o} bytes; the header promised {out_len}")
    return bytes(out)
