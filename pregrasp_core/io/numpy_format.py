"""NPY and NPZ point clouds (``allow_pickle=False``: nothing is ever unpickled)."""

from __future__ import annotations

import io
import math
import zipfile
from typing import IO

import numpy as np

from ..errors import InputError
from .cloud import FileData, RawCloud, describe_error, split_columns


def _numeric_array(arr: object, source: str, what: str) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.dtype.kind not in "fiu":
        raise InputError(
            f"{source}: {what} has dtype {arr.dtype}, expected a float or integer array of "
            "shape (N, 3) or (N, 6)"
        )
    if arr.ndim != 2:
        raise InputError(f"{source}: {what} has shape {arr.shape}, expected (N, 3) or (N, 6)")
    return arr.astype(np.float64)


def check_npy_header(fp: IO[bytes], n_bytes: int, source: str, what: str) -> None:
    """The NPY header at ``fp``: a numeric dtype and a shape whose data is exactly the
    ``n_bytes`` of the file (so a header claiming a huge shape is refused before numpy
    allocates it)."""

    def bad(problem: str) -> InputError:
        return InputError(
            f"{source}: not a readable NPY file ({what}: {problem}); save it with numpy.save of "
            "a float array (object arrays are refused)"
        )

    try:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fp)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fp)
        else:
            raise bad(f"NPY format version {version[0]}.{version[1]} is not supported")
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - numpy raises ValueError/EOFError/SyntaxError...
        raise bad(describe_error(exc)) from None
    if dtype.hasobject:
        raise bad("it holds Python objects")
    need = math.prod(shape) * dtype.itemsize
    have = n_bytes - fp.tell()
    if need != have:
        raise bad(
            f"the header declares shape {shape} of {dtype} ({need} bytes), the file holds "
            f"{have} bytes of data"
        )


def read_npy(file: FileData) -> RawCloud:
    """A float or integer (N, 3) or (N, 6) array saved by ``numpy.save``."""
    source = file.source
    if file.data.startswith(b"PK\x03\x04"):
        raise InputError(f"{source}: not an NPY array (an NPZ archive? rename it .npz)")
    check_npy_header(io.BytesIO(file.data), len(file.data), source, "the array")
    try:
        arr = np.load(io.BytesIO(file.data), allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - numpy raises ValueError/OSError/EOFError/...
        raise InputError(
            f"{source}: not a readable NPY file ({describe_error(exc)}); save it with "
            "numpy.save of a float array (object arrays are refused)"
        ) from exc
    if not isinstance(arr, np.ndarray):
        raise InputError(f"{source}: not an NPY array (an NPZ archive? rename it .npz)")
    return split_columns(_numeric_array(arr, source, "the array"), source, "column")


def read_npz(file: FileData) -> RawCloud:
    """The array ``points`` (or the only array) of an NPZ, optional ``normals``."""
    source, max_bytes = file.source, file.max_bytes
    try:
        with zipfile.ZipFile(io.BytesIO(file.data)) as zf:
            members = zf.infolist()
            unpacked = sum(i.file_size for i in members)
            if unpacked <= max_bytes:
                for info in members:  # each array's header against its size, before reading
                    with zf.open(info) as fp:
                        check_npy_header(fp, info.file_size, source, f"array {info.filename!r}")
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - zipfile raises BadZipFile, ValueError, ...
        raise InputError(
            f"{source}: not a readable NPZ archive ({describe_error(exc)}); save it with "
            "numpy.savez(points=...)"
        ) from exc
    if unpacked > max_bytes:
        raise InputError(
            f"{source}: the NPZ unpacks to {unpacked / 2**20:.1f} MiB, more than the limit of "
            f"{max_bytes / 2**20:.1f} MiB; downsample it or raise max_bytes"
        )
    try:
        with np.load(io.BytesIO(file.data), allow_pickle=False) as npz:
            keys = list(npz.files)
            if "points" in keys:
                key = "points"
            elif len(keys) == 1:
                key = keys[0]
            else:
                raise InputError(
                    f"{source}: NPZ holds arrays {keys} but none is named 'points'; save the "
                    "points under the key 'points' (optional 'normals')"
                )
            arr = npz[key]
            normals = npz["normals"] if "normals" in keys and key != "normals" else None
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise InputError(
            f"{source}: cannot read the NPZ arrays ({describe_error(exc)}); save float "
            "arrays with numpy.savez (object arrays are refused)"
        ) from exc
    pts = _numeric_array(arr, source, f"array '{key}'")
    if normals is None:
        return split_columns(pts, source, "column")
    if pts.shape[1] != 3:
        raise InputError(
            f"{source}: array '{key}' has shape {pts.shape}, expected (N, 3) with 'normals'"
        )
    nrm = _numeric_array(normals, source, "array 'normals'")
    if nrm.shape != pts.shape:
        raise InputError(
            f"{source}: 'normals' has shape {nrm.shape}, expected {pts.shape} like 'points'"
        )
    return RawCloud(pts, nrm, int(pts.shape[0]), [])
