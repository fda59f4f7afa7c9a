"""LZF decompression (Marc Lehmann's liblzf format), for PCD's ``DATA binary_compressed``.

An LZF stream is a sequence of tokens, each starting with a control byte ``c``:

- ``c < 32``: a literal run, the next ``c + 1`` bytes copied as they are;
- else a back reference: length ``(c >> 5) + 2`` (when ``c >> 5`` is 7, the next byte is added
  to the length), distance ``((c & 0x1f) << 8) + next byte + 1`` back from the end of the output
  so far; the copy may overlap what it writes (a run of one repeated pattern).

The loop is compiled by numba on its first call (or loaded from numba's cache), like the core's
other kernels; every malformed stream (a token cut off, a reference before the start, more or
fewer bytes than declared) raises :class:`~pregrasp_core.errors.InputError` naming the file.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..jit import Lazy, njit

MAX_RATIO: int = 88
"""The most bytes an LZF stream can expand to per byte of it: a back reference of 3 bytes
writes at most 264 (``7 + 255 + 2``). A declared size beyond ``MAX_RATIO`` times the stream is
refused before anything is allocated."""

_TRUNCATED, _OVERFLOW, _BEFORE_START = -1, -2, -3
"""What the kernel returns for a stream cut off inside a token, one that writes past the
declared size, and a reference before the start of the output."""


def _decompress(src: np.ndarray, out: np.ndarray) -> int:
    """Decode ``src`` (uint8) into ``out`` (uint8, the declared size); the number of bytes
    written, or one of the negative codes above."""
    ip, op = 0, 0
    n_in, n_out = src.shape[0], out.shape[0]
    while ip < n_in:
        ctrl = int(src[ip])
        ip += 1
        if ctrl < 32:  # a literal run
            run = ctrl + 1
            if ip + run > n_in:
                return _TRUNCATED
            if op + run > n_out:
                return _OVERFLOW
            for k in range(run):
                out[op + k] = src[ip + k]
            ip += run
            op += run
        else:  # a back reference
            length = ctrl >> 5
            ref = op - ((ctrl & 0x1F) << 8) - 1
            if ip >= n_in:
                return _TRUNCATED
            if length == 7:
                length += int(src[ip])
                ip += 1
                if ip >= n_in:
                    return _TRUNCATED
            ref -= int(src[ip])
            ip += 1
            length += 2
            if op + length > n_out:
                return _OVERFLOW
            if ref < 0:
                return _BEFORE_START
            for k in range(length):  # byte by byte: the copy may overlap its own output
                out[op + k] = out[ref + k]
            op += length
    return op


_KERNEL = Lazy(lambda: njit(_decompress))


def lzf_decompress(data: bytes | memoryview, size: int, source: str) -> bytes:
    """The ``size`` bytes that the LZF stream ``data`` decodes to; ``source`` names the file in
    the error raised when the stream is malformed or decodes to another size."""
    src = np.frombuffer(data, dtype=np.uint8)
    if size < 0 or size > MAX_RATIO * max(len(src), 1):
        raise InputError(
            f"{source}: the compressed PCD data ({len(src)} bytes) cannot hold the {size} bytes "
            "its header declares; the file is corrupt: re-save the cloud"
        )
    out = np.empty(size, dtype=np.uint8)
    n = int(_KERNEL.get()(src, out))
    problem = {
        _TRUNCATED: "it ends inside a token",
        _OVERFLOW: f"it holds more than the {size} bytes declared",
        _BEFORE_START: "a back reference points before its start",
    }.get(n)
    if problem is None and n != size:
        problem = f"it holds {n} bytes, the header declares {size}"
    if problem is not None:
        raise InputError(f"{source}: corrupt compressed PCD data ({problem}); re-save the cloud")
    return out.tobytes()
