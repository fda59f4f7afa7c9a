"""PCD point clouds (the Point Cloud Library's format): ``DATA ascii``, ``binary`` and
``binary_compressed`` (LZF, ``io/lzf.py``; the fields stored one after another, each for every
point, as PCL writes them).

Every header field is checked before anything is allocated: each key once, FIELDS named once,
SIZE/TYPE/COUNT per field and in range, WIDTH x HEIGHT = POINTS, VIEWPOINT of 7 numbers, and a
body holding exactly POINTS rows (no missing and no extra data; for ``binary_compressed``, the
two sizes before the stream, the stream's length and the size it decodes to)."""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .cloud import FileData, RawCloud
from .lzf import lzf_decompress
from .text import decode_text, parse_numbers

PCD_KEYS: tuple[str, ...] = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT",
                             "VIEWPOINT", "POINTS", "DATA")  # fmt: skip
"""The header keys of a PCD file (PCL's order)."""

MAX_FIELD_COUNT: int = 4096
"""Largest COUNT of one field (PCL's widest point types, e.g. FPFH, have a few hundred)."""

MAX_DECOMPRESSED: int = 1 << 30
"""Most bytes a ``binary_compressed`` body may decode to (1 GiB: 10 million points of PCL's
widest common point type, ``PointXYZRGBNormal`` at 48 bytes, take 480 MB)."""

_BINARY_FIELDS: tuple[str, ...] = ("x", "y", "z", "normal_x", "normal_y", "normal_z")
"""The fields read from a binary body (the rest are skipped)."""


def read_pcd(file: FileData) -> RawCloud:
    """A PCD file (PCL), ``DATA ascii``, ``binary`` or ``binary_compressed``."""
    data, source = file.data, file.source

    def bad(problem: str) -> InputError:
        return InputError(
            f"{source}: malformed PCD header: {problem}; re-save the cloud with PCL "
            "(pcl::io::savePCDFile) as ascii or binary"
        )

    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        nl = data.find(b"\n", pos)
        line_b = data[pos:] if nl < 0 else data[pos:nl]
        pos = len(data) if nl < 0 else nl + 1
        try:
            line = line_b.decode("ascii").strip()
        except UnicodeDecodeError:
            raise bad("non-ASCII bytes in the header") from None
        if line and not line.startswith("#"):
            tok = line.split()
            key = tok[0].upper()
            if key not in PCD_KEYS:
                raise bad(f"unexpected line {line[:60]!r}")
            if key in header:
                raise bad(f"{key} given twice")
            header[key] = tok[1:]
            if key == "DATA":
                break
        if nl < 0:
            raise bad("no DATA line")
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT"):
        if key not in header:
            raise bad(f"no {key} line")
    fields = header["FIELDS"]
    n_f = len(fields)
    counts_s = header.get("COUNT", ["1"] * n_f)
    if not (len(header["SIZE"]) == len(header["TYPE"]) == len(counts_s) == n_f) or n_f == 0:
        raise bad(
            f"FIELDS ({n_f}), SIZE ({len(header['SIZE'])}), TYPE ({len(header['TYPE'])}) and "
            f"COUNT ({len(counts_s)}) must list the same number of entries"
        )
    twice = sorted({f for f in fields if fields.count(f) > 1 and f != "_"})
    if twice:
        raise bad(f"field {twice[0]!r} named twice in FIELDS")
    for key in ("WIDTH", "HEIGHT", "POINTS"):
        if key in header and len(header[key]) != 1:
            raise bad(f"{key} must be one integer, got {' '.join(header[key])!r}")
    ints = header["SIZE"] + counts_s + header["WIDTH"] + header["HEIGHT"] + header.get("POINTS", [])
    if not all(s.isascii() and s.lstrip("-").isdigit() for s in ints):
        raise bad("SIZE, COUNT, WIDTH, HEIGHT and POINTS must be integers")
    sizes = [int(s) for s in header["SIZE"]]
    counts = [int(c) for c in counts_s]
    width = int(header["WIDTH"][0])
    height = int(header["HEIGHT"][0])
    n_pts = int(header["POINTS"][0]) if "POINTS" in header else width * height
    if n_pts < 0 or width < 0 or height < 0:
        raise bad("negative WIDTH, HEIGHT or POINTS")
    if width * height != n_pts:
        raise bad(f"WIDTH x HEIGHT ({width} x {height}) differs from POINTS ({n_pts})")
    if "VIEWPOINT" in header:
        try:
            vp = [float(v) for v in header["VIEWPOINT"]]
        except ValueError:
            vp = []
        if len(vp) != 7 or not np.isfinite(vp).all():
            raise bad(f"VIEWPOINT must be 7 numbers, got {' '.join(header['VIEWPOINT'])[:60]!r}")
    types = [t.upper() for t in header["TYPE"]]
    dtypes: list[tuple[str, str] | tuple[str, str, tuple[int]]] = []
    for i, (name, t, s, c) in enumerate(zip(fields, types, sizes, counts, strict=True)):
        if t not in ("F", "I", "U") or s not in (1, 2, 4, 8) or (t == "F" and s not in (4, 8)):
            raise bad(f"field {name!r} has unsupported TYPE {t} SIZE {s}")
        if not 1 <= c <= MAX_FIELD_COUNT:
            raise bad(f"field {name!r} has COUNT {c} (1 to {MAX_FIELD_COUNT})")
        code = {"F": "f", "I": "i", "U": "u"}[t] + str(s)
        key = name if name != "_" else f"_{i}"  # PCL pads with fields named '_'
        dtypes.append((key, "<" + code, (c,)) if c > 1 else (key, "<" + code))
    for axis in ("x", "y", "z"):
        if axis not in fields:
            raise InputError(f"{source}: the PCD has fields {fields}, no {axis!r}; nothing to read")
    if n_pts == 0:
        raise InputError(f"{source}: the PCD declares 0 points; nothing to read")
    mode = " ".join(header["DATA"]).lower()
    body = len(data) - pos
    n_cols = sum(counts)
    if mode == "ascii":  # arrays sized by the text itself, not by the header
        text = decode_text(data[pos:], source, "ascii PCD")
        arr = parse_numbers(text, source, "ascii PCD data")
        if arr.size == 0:
            raise InputError(f"{source}: the ascii PCD has no data rows; re-save the cloud")
        if arr.shape[1] != n_cols:
            raise InputError(
                f"{source}: wrong column count in the ascii PCD: {arr.shape[1]} numbers per "
                f"row, the header declares {n_cols}"
            )
        if arr.shape[0] != n_pts:
            raise InputError(
                f"{source}: the PCD header declares {n_pts} points, the data has "
                f"{arr.shape[0]} rows; re-save the cloud"
            )
        starts = np.cumsum([0] + counts[:-1])
        col = {f: arr[:, st] for f, st in zip(fields, starts, strict=True)}
    elif mode == "binary":
        row = sum(s * c for s, c in zip(sizes, counts, strict=True))
        need = n_pts * row
        if body < need:
            raise InputError(
                f"{source}: truncated PCD: the header declares {n_pts} points ({need} bytes), "
                f"the file holds {body} data bytes; re-save the cloud"
            )
        if body > need:
            raise InputError(
                f"{source}: {body - need} bytes after the {n_pts} points the header declares "
                f"({need} bytes); the header is wrong or the file is corrupt: re-save the cloud"
            )
        rec = np.frombuffer(data, dtype=np.dtype(dtypes), count=n_pts, offset=pos)
        col = {
            f: (rec[f] if rec[f].ndim == 1 else rec[f][:, 0]).astype(np.float64)
            for f in _BINARY_FIELDS
            if f in fields
        }
    elif mode == "binary_compressed":
        col = _compressed_columns(data, pos, fields, dtypes, n_pts, source)
    else:
        raise bad(
            f"unknown DATA mode {' '.join(header['DATA'])!r} (ascii, binary or binary_compressed)"
        )
    pts = np.column_stack([col["x"], col["y"], col["z"]])
    nrm = None
    if {"normal_x", "normal_y", "normal_z"} <= set(fields):
        nrm = np.column_stack([col["normal_x"], col["normal_y"], col["normal_z"]])
    return RawCloud(pts, nrm, int(n_pts), [])


def _compressed_columns(
    data: bytes,
    pos: int,
    fields: list[str],
    dtypes: list[tuple[str, str] | tuple[str, str, tuple[int]]],
    n_pts: int,
    source: str,
) -> dict[str, np.ndarray]:
    """The columns of ``_BINARY_FIELDS`` of a ``DATA binary_compressed`` body starting at
    ``pos``: two little-endian uint32 (the stream's length, the size it decodes to), the LZF
    stream, then nothing; decoded, each field's values for every point, field after field."""
    body = len(data) - pos
    if body < 8:
        raise InputError(
            f"{source}: truncated PCD: the compressed data has no sizes ({body} bytes after the "
            "header, 8 needed); re-save the cloud"
        )
    n_comp, n_raw = (int(v) for v in np.frombuffer(data, dtype="<u4", count=2, offset=pos))
    item = [np.dtype(dt[1]).itemsize * (dt[2][0] if len(dt) == 3 else 1) for dt in dtypes]
    need = n_pts * sum(item)
    if n_raw != need:
        raise InputError(
            f"{source}: the PCD header declares {n_pts} points, the data has {n_raw} bytes "
            f"once decompressed ({need} needed); the header is wrong or the file is corrupt: "
            "re-save the cloud"
        )
    if need > MAX_DECOMPRESSED:
        raise InputError(
            f"{source}: the compressed PCD data decodes to {need} bytes, more than the "
            f"{MAX_DECOMPRESSED} pregrasp reads; subsample the cloud first"
        )
    if body - 8 != n_comp:
        what = "truncated PCD" if body - 8 < n_comp else f"{body - 8 - n_comp} bytes after the data"
        raise InputError(
            f"{source}: {what}: the header declares {n_comp} bytes of compressed data, the "
            f"file holds {body - 8}; re-save the cloud"
        )
    raw = lzf_decompress(memoryview(data)[pos + 8 :], n_raw, source)
    col: dict[str, np.ndarray] = {}
    start = 0
    for name, dt, size in zip(fields, dtypes, item, strict=True):
        if name in _BINARY_FIELDS:
            block = np.frombuffer(raw, dtype=dt[1], count=n_pts * size // np.dtype(dt[1]).itemsize,
                                  offset=start)  # fmt: skip
            col[name] = block.reshape(n_pts, -1)[:, 0].astype(np.float64)
        start += n_pts * size
    return col
