"""XYZ / TXT / CSV point clouds (rows of 3 or 6 numbers) and the text helpers the ascii PLY and
PCD readers share."""

from __future__ import annotations

import io
import warnings

import numpy as np

from ..errors import InputError
from .cloud import FileData, RawCloud, add_warning, split_columns


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
    """Rows of x y z (or x y z nx ny nz); ``#`` comments; a first line of column names skipped."""
    source = file.source
    warns: list[str] = []
    text = decode_text(file.data, source, "XYZ")
    lines = text.splitlines()
    # A column-name line such as "x,y,z" before the data (common in CSV) is skipped.
    first = next((i for i, ln in enumerate(lines) if ln.strip() and ln.lstrip()[0] != "#"), None)
    if first is not None and not _is_numeric_row(lines[first]):
        if any(c.isalpha() for c in lines[first]) and first + 1 < len(lines):
            add_warning(warns, f"{source}: skipped the header line {lines[first].strip()[:60]!r}")
            del lines[first]
    arr = parse_numbers(lines, source, "XYZ/TXT data")
    if arr.size == 0:
        raise InputError(f"{source}: no data rows (only comments or blank lines)")
    raw = split_columns(arr, source, "column")
    return RawCloud(raw.points, raw.normals, raw.n_read, warns + raw.warnings)
