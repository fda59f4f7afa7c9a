"""XYZ / TXT / CSV point clouds (rows of x y z, then optional columns: normals, colours,
intensities, as CloudCompare, MeshLab and scanners export them) and the text helpers the ascii
PLY and PCD readers share."""

from __future__ import annotations

import io
import warnings

import numpy as np

from ..errors import InputError
from ..tolerances import UNIT_NORMAL_TOL
from .cloud import FileData, RawCloud, add_warning, split_columns

MAX_TEXT_COLUMNS: int = 64
"""Most numbers per row of a text cloud (x y z, normals, colours, a few scalar fields)."""

NORMAL_NAMES: tuple[tuple[str, str, str], ...] = (
    ("nx", "ny", "nz"),
    ("normal_x", "normal_y", "normal_z"),
    ("normalx", "normaly", "normalz"),
    ("n_x", "n_y", "n_z"),
)
"""Header names of the normal columns (case-insensitive)."""


def decode_text(data: bytes, source: str, what: str) -> str:
    """``data`` as UTF-8 text (a BOM is dropped); binary bytes or bad UTF-8 -> InputError."""
    if data[:2] in (b"\xff\xfe", b"\xfe\xff") and _is_utf16(data):
        raise InputError(
            f"{source}: is UTF-16 text; {what} files must be UTF-8 or ASCII: save it as UTF-8"
        )
    if b"\x00" in data:
        raise InputError(f"{source}: contains binary data, not {what} text; check the format")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{source}: is not UTF-8/ASCII text ({exc.reason} at byte {exc.start}); "
            f"{what} files are text, check the format"
        ) from exc


def _is_utf16(data: bytes) -> bool:
    try:
        data.decode("utf-16")
    except UnicodeDecodeError:
        return False
    return True


def parse_numbers(lines: list[str] | str, source: str, what: str) -> np.ndarray:
    """Numbers of whitespace/comma-separated text rows as an (R, C) float64 array."""
    text = lines if isinstance(lines, str) else "\n".join(lines)
    text = text.replace(",", " ")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data" -> handled by callers
            arr = np.loadtxt(io.StringIO(text), dtype=np.float64, comments="#", ndmin=2)
    except ValueError as exc:
        msg = " ".join(str(exc).split())[:160]
        if "number of columns" in msg:
            problem = f"rows have different numbers of columns ({msg.split(';')[0]})"
        else:
            problem = f"non-numeric data ({msg})"
        raise InputError(
            f"{source}: {what}: {problem}; every row must hold the same count of numbers"
        ) from None
    return arr


def _is_numeric_row(line: str) -> bool:
    try:
        [float(t) for t in line.split("#", 1)[0].replace(",", " ").split()]
    except ValueError:
        return False
    return True


def read_text(file: FileData) -> RawCloud:
    """Rows of x y z and optional columns (:func:`text_columns`); ``#`` comments; a first line
    of column names (``x,y,z``, CloudCompare's ``//X Y Z R G B Nx Ny Nz``) names the columns
    when it names x, y and z, else it is skipped."""
    source = file.source
    warns: list[str] = []
    text = decode_text(file.data, source, "XYZ")
    lines = text.splitlines()
    names: list[str] | None = None
    first = next((i for i, ln in enumerate(lines) if ln.strip() and ln.lstrip()[0] != "#"), None)
    if first is not None and not _is_numeric_row(lines[first]):
        if any(c.isalpha() for c in lines[first]) and first + 1 < len(lines):
            head = lines[first].strip()
            names = head.lstrip("/").replace(",", " ").replace(";", " ").split()
            if not {"x", "y", "z"} <= {t.lower() for t in names}:
                names = None
            what = "read the header line" if names else "skipped the header line"
            add_warning(
                warns, f"{source}: {what} {head[:60]!r}" + (" as column names" if names else "")
            )
            del lines[first]
    arr = parse_numbers(lines, source, "XYZ/TXT data")
    if arr.size == 0:
        raise InputError(f"{source}: no data rows (only comments or blank lines)")
    raw = text_columns(arr, names, source)
    return RawCloud(raw.points, raw.normals, raw.n_read, warns + raw.warnings)


def _unit_rows(cols: np.ndarray) -> bool:
    """Whether every finite row of ``cols`` (N, 3) is a unit vector (and one is)."""
    with np.errstate(over="ignore", invalid="ignore"):  # huge columns: not unit vectors
        length = np.linalg.norm(cols, axis=1)
    ok = np.isfinite(length)
    return bool(ok.any() and np.all(np.abs(length[ok] - 1.0) < UNIT_NORMAL_TOL))


def _ranges(cols: list[int]) -> str:
    """1-based column numbers as ``4-6, 8``."""
    out: list[str] = []
    for c in sorted(cols):
        if out and out[-1].split("-")[-1] == str(c):  # (c is the next of the last run)
            out[-1] = f"{out[-1].split('-')[0]}-{c + 1}"
        else:
            out.append(str(c + 1))
    return ", ".join(out)


def text_columns(arr: np.ndarray, names: list[str] | None, source: str) -> RawCloud:
    """Points (and normals) of the rows ``arr`` (N, C) of a text cloud.

    Three or six columns without names read as before: x y z, then normals when columns 4-6
    are unit vectors on every row. Otherwise: the columns named ``x y z`` (and ``nx ny nz``,
    :data:`NORMAL_NAMES`) when a header names them, else x y z first and, as normals, the first
    three consecutive columns after them that are unit vectors on every row (CloudCompare
    writes ``x y z r g b nx ny nz``, MeshLab ``x y z nx ny nz``); every other column
    (colours, intensities, scalar fields) is ignored with a warning naming it."""
    n_cols = arr.shape[1]
    if names is None and n_cols in (3, 6):
        return split_columns(arr, source, "column")
    if not 3 <= n_cols <= MAX_TEXT_COLUMNS:
        raise InputError(
            f"{source}: wrong column count {n_cols}; expected 3 (x y z) to {MAX_TEXT_COLUMNS} "
            "(x y z first, then normals, colours or other values)"
        )
    warns: list[str] = []
    low = [t.lower() for t in names] if names is not None and len(names) == n_cols else None
    if names is not None and low is None:
        add_warning(
            warns,
            f"{source}: the header names {len(names)} columns, the rows hold {n_cols}; read "
            "columns 1-3 as x y z",
        )
    xyz = [low.index(a) for a in "xyz"] if low is not None else [0, 1, 2]
    nrm: list[int] | None = None
    if low is not None:
        named = next((t for t in NORMAL_NAMES if all(a in low for a in t)), None)
        if named is not None:
            nrm = [low.index(a) for a in named]
            if not _unit_rows(arr[:, nrm]):
                add_warning(
                    warns,
                    f"{source}: the columns named {' '.join(named)} are not unit vectors; "
                    "read without normals",
                )
                nrm = None
    else:
        nrm = next(
            ([k, k + 1, k + 2] for k in range(3, n_cols - 2) if _unit_rows(arr[:, k : k + 3])),
            None,
        )
    used = xyz + (nrm or [])
    ignored = [c for c in range(n_cols) if c not in used]
    if ignored or xyz != [0, 1, 2]:
        what = f"read columns {_ranges(xyz)} as x y z"
        if nrm is not None:
            what += f" and {_ranges(nrm)} as normals"
        if ignored:
            what += f"; ignored column(s) {_ranges(ignored)} (colours, intensities?)"
        add_warning(warns, f"{source}: {what}")
    return RawCloud(arr[:, xyz], None if nrm is None else arr[:, nrm], int(arr.shape[0]), warns)
