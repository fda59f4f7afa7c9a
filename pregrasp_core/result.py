"""The ``pregrasp/1`` result document: a versioned JSON file (see ``docs/result-schema.md``).

The core sections (input, parameters, timings, tree) are built here. Later stages add theirs
without touching this module: each provides a function returning a JSON-ready dict (e.g. the
pool and the planned grasps), and the caller passes them as ``extra_sections``::

    doc = result_document(cloud, {"decomposition": dp, "shape": sp}, timings, tree, shapes,
                          extra_sections={"pool": pool_section(pool)})
    write_result(doc, "out.json")

Values are made JSON-ready by :func:`to_jsonable` (dataclasses -> dicts, enums -> their value,
numpy arrays -> nested lists, non-finite floats -> ``null``).
"""

from __future__ import annotations

import dataclasses
import enum
import json
import logging
import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, TypeAlias, cast

import numpy as np

from .decomposition import BoxTree
from .errors import InputError
from .shape import NodeShape

if TYPE_CHECKING:
    from .io import PointCloud

logger = logging.getLogger(__name__)

JsonValue: TypeAlias = "None | bool | int | float | str | list[JsonValue] | dict[str, JsonValue]"
"""A value of plain JSON types, what :func:`to_jsonable` returns."""

JsonDocument: TypeAlias = "dict[str, JsonValue]"
"""A JSON object (a result document or one of its sections)."""

FaceMaskInput: TypeAlias = "np.ndarray | Sequence[np.ndarray | None] | None"
"""Face masks given to :func:`tree_section`: an (n_nodes, 6, 5) array, a (6, 5) array or
``None`` per node, or ``None``."""

SCHEMA: str = "pregrasp/1"
"""The value of the document's ``"schema"`` key."""

CORE_SECTIONS: tuple[str, ...] = (
    "schema",
    "generator",
    "input",
    "parameters",
    "timings",
    "tree",
)
"""Top-level keys built by this module; ``extra_sections`` may not reuse them."""

FACE_MASK_SHAPE: tuple[int, int] = (6, 5)
"""Shape of one node's face mask: row f = [f, l(f), d(f), r(f), u(f)], 0 free, 1 blocked."""


def to_jsonable(obj: object) -> JsonValue:
    """``obj`` as plain JSON types (dict, list, str, int, float, bool, None).

    Dataclasses become dicts of their fields, enums their value, numpy arrays nested lists,
    numpy scalars Python scalars, paths strings, tuples lists; NaN and infinities ``None``
    (JSON has no such numbers). Raises ``TypeError`` for anything else.

    The plain types (most of a result document: the sections are built of dicts, lists and
    ``tolist()`` floats) are told by their exact type first, a float's finiteness by
    ``x - x == 0.0`` (NaN for an infinity or a NaN) without a call per float; everything else
    (subclasses such as str enums and numpy floats included) goes through
    :func:`_to_jsonable_other`.
    """
    t = type(obj)
    if t is float:
        return obj if obj - obj == 0.0 else None  # type: ignore[operator, return-value]
    if t is str or t is int or t is bool or obj is None:
        return obj  # type: ignore[return-value]
    if t is dict:
        return {
            (k if type(k) is str else str(k)): to_jsonable(v)
            for k, v in obj.items()  # type: ignore[attr-defined]
        }
    if t is list or t is tuple:
        return [
            x if type(x) is float and x - x == 0.0 else to_jsonable(x)
            for x in obj  # type: ignore[attr-defined]
        ]
    return _to_jsonable_other(obj)


def _to_jsonable_other(obj: object) -> JsonValue:
    """:func:`to_jsonable` of the values that are not exactly a plain JSON type."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, enum.Enum):
        return to_jsonable(obj.value)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.ndarray):
        return [to_jsonable(x) for x in obj.tolist()] if obj.dtype.kind == "f" else obj.tolist()
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(x) for x in obj]
    raise TypeError(f"cannot write a {type(obj).__name__} to the result JSON: {obj!r}")


_encode_str = json.encoder.encode_basestring_ascii
_float_repr = float.__repr__
_int_repr = int.__repr__


def _finite_repr(x: float) -> str:
    """A float as ``json.dumps`` writes it, non-finite as ``null`` (what :func:`to_jsonable`
    makes of it)."""
    return _float_repr(x) if math.isfinite(x) else "null"


def dumps_result(obj: object) -> str:
    """``json.dumps(to_jsonable(obj), indent=1, allow_nan=False)``, the same text, written in
    one pass without the intermediate plain-JSON copy.

    The standard library writes indented JSON with its pure-Python encoder, one generator step
    per value; a result file holds ~10^5 numbers, most of them in short lists of floats, which
    are written here as one ``join`` each. Values as :func:`to_jsonable` converts them (the
    same ``TypeError`` for anything else)."""
    out: list[str] = []
    _dump(obj, "\n", out)
    return "".join(out)


def _dump(obj: object, nl: str, out: list[str]) -> None:
    """Append the indented JSON of ``obj`` to ``out``; ``nl``: newline + the indent of the
    level ``obj`` sits at (one space per level, as ``indent=1``)."""
    t = type(obj)
    if t is float:
        out.append(_float_repr(obj) if obj - obj == 0.0 else "null")  # type: ignore[operator]
    elif t is str:
        out.append(_encode_str(obj))  # type: ignore[arg-type]
    elif t is int:
        out.append(_int_repr(obj))
    elif obj is None:
        out.append("null")
    elif t is bool:
        out.append("true" if obj else "false")
    elif t is list or t is tuple:
        _dump_list(obj, nl, out)  # type: ignore[arg-type]
    elif t is dict:
        _dump_dict(obj, nl, out)  # type: ignore[arg-type]
    elif isinstance(obj, np.ndarray) and obj.ndim:
        _dump_list(obj.tolist(), nl, out, obj.dtype.kind == "f")
    elif isinstance(obj, str):  # str subclasses (str enums: json writes their text)
        out.append(_encode_str(obj))
    else:  # the rest (enums, numpy scalars, dataclasses, mappings, paths) as to_jsonable does
        value = to_jsonable(obj) if not _container(obj) else _shallow(obj)
        _dump(value, nl, out)


def _container(obj: object) -> bool:
    """A dataclass instance or a mapping (converted one level at a time by :func:`_shallow`)."""
    return (dataclasses.is_dataclass(obj) and not isinstance(obj, type)) or isinstance(obj, Mapping)


def _shallow(obj: object) -> dict[str, object]:
    """A dataclass instance or a mapping as a dict of its fields or items (values as they
    are: converted by :func:`_dump` on the way)."""
    if isinstance(obj, Mapping):
        return {str(k): v for k, v in obj.items()}
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}  # type: ignore[arg-type]


def _dump_list(
    items: list[object] | tuple[object, ...], nl: str, out: list[str], floats: bool = False
) -> None:
    """Append a list; ``floats``: every item is a float or a (nested) list of floats (a float
    array's ``tolist()``)."""
    if not items:
        out.append("[]")
        return
    inner = nl + " "
    sep = "," + inner
    if floats or all(type(x) is float for x in items):
        if type(items[0]) is float:
            # every float's repr in C; only a list holding an inf or a nan ("n" in its text,
            # never in a finite float's repr) is written again with nulls for them
            text = sep.join(map(_float_repr, items))
            if "n" in text:
                text = sep.join(map(_finite_repr, items))  # type: ignore[arg-type]
            out.append("[" + inner + text + nl + "]")
            return
    elif all(type(x) is int for x in items):
        out.append("[" + inner + sep.join(map(_int_repr, items)) + nl + "]")
        return
    out.append("[" + inner)
    for k, x in enumerate(items):  # loop over the items (nested lists, objects)
        if k:
            out.append(sep)
        if floats:
            _dump_list(x, inner, out, True)  # type: ignore[arg-type]
        else:
            _dump(x, inner, out)
    out.append(nl + "]")


def _dump_dict(d: dict[object, object], nl: str, out: list[str]) -> None:
    """Append an object (keys as ``str``, like :func:`to_jsonable`)."""
    if not d:
        out.append("{}")
        return
    inner = nl + " "
    sep = "," + inner
    lead = inner
    out.append("{")
    for k, v in d.items():  # loop over the keys
        key = lead + _encode_str(str(k)) + ": "
        lead = sep
        t = type(v)  # the scalars written here, without a call of _dump each
        if t is float:
            out.append(key + (_float_repr(v) if v - v == 0.0 else "null"))  # type: ignore[operator]
        elif t is str:
            out.append(key + _encode_str(v))  # type: ignore[arg-type]
        elif t is int:
            out.append(key + _int_repr(v))
        elif v is None:
            out.append(key + "null")
        elif t is bool:
            out.append(key + ("true" if v else "false"))
        else:
            out.append(key)
            _dump(v, inner, out)
    out.append(nl + "}")


def _json_object(value: JsonValue) -> JsonDocument:
    """``value`` (a JSON object) as a dict; ``TypeError`` when it is another JSON value."""
    if not isinstance(value, dict):
        raise TypeError(f"expected a JSON object, got {type(value).__name__}")
    return value


def _version() -> str | None:
    try:
        return metadata.version("pregrasp")
    except metadata.PackageNotFoundError:  # running from a source tree without install
        return None


def input_section(cloud: PointCloud, seed: int | None = None) -> JsonDocument:
    """The ``input`` section for a ``PointCloud``."""
    info = dict(getattr(cloud, "info", {}) or {})
    pts = np.asarray(cloud.points)
    lo, hi = (pts.min(axis=0), pts.max(axis=0)) if pts.size else (np.zeros(3), np.zeros(3))
    return {
        "source": str(cloud.source),
        "format": info.get("format"),
        "kind": info.get("kind"),
        "n_points": int(pts.shape[0]),
        "seed": info.get("seed") if seed is None else int(seed),
        "scale": info.get("scale", 1.0),
        "n_read": info.get("n_read"),
        "n_dropped_nonfinite": info.get("n_dropped_nonfinite", 0),
        **({"n_dropped_strays": info["n_dropped_strays"]} if "n_dropped_strays" in info else {}),
        "has_normals": getattr(cloud, "normals", None) is not None,
        "bounds": to_jsonable(np.stack([lo, hi])),
        "warnings": list(info.get("warnings", [])),
        **({"scene": info["scene"]} if "scene" in info else {}),
    }


def _face_mask_list(face_masks: FaceMaskInput, n_nodes: int) -> list[np.ndarray | None]:
    """Normalise face masks to one (6, 5) int array or None per node."""
    if face_masks is None:
        return [None] * n_nodes
    if isinstance(face_masks, np.ndarray):
        fm = face_masks
        if fm.shape != (n_nodes, *FACE_MASK_SHAPE):
            raise ValueError(
                f"face_masks must have shape ({n_nodes}, 6, 5) (one per node), got {fm.shape}"
            )
        masks: list[np.ndarray | None] = list(fm)
    else:
        masks = list(face_masks)
        if len(masks) != n_nodes:
            raise ValueError(
                f"face_masks must have {n_nodes} entries (one per node), got {len(masks)}"
            )
    out: list[np.ndarray | None] = []
    for i, m in enumerate(masks):
        if m is None:
            out.append(None)
            continue
        a = np.asarray(m)
        if a.shape != FACE_MASK_SHAPE:
            raise ValueError(f"face mask of node {i} must have shape (6, 5), got {a.shape}")
        if not np.all((a == 0) | (a == 1)):
            raise ValueError(f"face mask of node {i} must hold only 0 (free) and 1 (blocked)")
        out.append(a.astype(np.int64))
    return out


def tree_section(
    tree: BoxTree,
    shapes: Sequence[NodeShape] | None = None,
    face_masks: FaceMaskInput = None,
    include_indices: bool = False,
) -> JsonDocument:
    """The ``tree`` section: summary and one entry per node (see ``docs/result-schema.md``).

    shapes: one ``NodeShape`` per node (by id) or None; face_masks: None, an (n_nodes, 6, 5)
    array, or a sequence of (6, 5) arrays / None per node; include_indices: add each node's
    point indices.
    """
    n = len(tree.nodes)
    if shapes is not None and len(shapes) != n:
        raise ValueError(f"shapes must have {n} entries (one per node), got {len(shapes)}")
    masks = _face_mask_list(face_masks, n)
    nodes: list[JsonValue] = []
    for nd in tree.nodes:
        entry: JsonDocument = {
            "id": nd.id,
            "parent": nd.parent,
            "children": list(nd.children),
            "depth": nd.depth,
            "split_order": nd.split_order,
            "n_points": nd.n_points,
            **_json_object(nd.box.to_dict()),
        }
        sh = None if shapes is None else shapes[nd.id]
        entry["eigenvalues"] = None if sh is None else to_jsonable(sh.eigenvalues)
        entry["shape_class"] = None if sh is None else sh.shape_class.value
        entry["grasp_type"] = None if sh is None else sh.grasp_type.value
        mask = masks[nd.id]
        entry["face_mask"] = None if mask is None else mask.tolist()
        if include_indices:
            entry["indices"] = nd.indices.tolist()
        nodes.append(entry)
    return {
        "n_points": tree.n_points,
        "n_nodes": n,
        "n_splits": tree.n_splits,
        "leaves": list(tree.leaves()),
        "includes_indices": bool(include_indices),
        "nodes": nodes,
    }


def result_document(
    cloud: PointCloud,
    params: Mapping[str, object],
    timings: Mapping[str, float],
    tree: BoxTree,
    shapes: Sequence[NodeShape] | None,
    face_masks: FaceMaskInput = None,
    include_indices: bool = False,
    extra_sections: Mapping[str, object] | None = None,
    seed: int | None = None,
    plain: bool = True,
) -> JsonDocument:
    """The ``pregrasp/1`` document as a JSON-ready dict.

    cloud: the ``PointCloud`` the tree was built from; params: stage name -> its parameters
    dataclass (or dict), e.g. ``{"decomposition": DecompositionParams(), "shape": ...}``;
    timings: stage name -> seconds; shapes: one ``NodeShape`` per node; face_masks, include_indices:
    see :func:`tree_section`; extra_sections: further top-level sections (e.g. ``"pool"``,
    ``"grasps"``, ``"best"``) made JSON-ready with :func:`to_jsonable`, after the core ones;
    seed: the sampling seed of the input (else ``cloud.info["seed"]`` if present). plain: the
    extra sections made plain JSON; ``False`` leaves them as built (numpy arrays, dataclasses):
    for a document that goes to :func:`write_result` (or :func:`to_jsonable`) only, which
    writes the same text without the copy.
    """
    if int(np.asarray(cloud.points).shape[0]) != tree.n_points:
        raise ValueError(
            f"the tree has {tree.n_points} points but the cloud {np.asarray(cloud.points).shape[0]}"
        )
    t: JsonDocument = {}  # stage name -> seconds
    for k, v in timings.items():
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
            raise ValueError(f"timing {k!r} must be a number of seconds, got {v!r}")
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"timing {k!r} must be a finite number of seconds >= 0, got {v!r}")
        t[str(k)] = float(v)
    doc: JsonDocument = {
        "schema": SCHEMA,
        "generator": {"name": "pregrasp", "version": _version()},
        "input": input_section(cloud, seed),
        "parameters": {str(k): to_jsonable(v) for k, v in params.items()},
        "timings": t,
        "tree": tree_section(tree, shapes, face_masks, include_indices),
    }
    for name, section in (extra_sections or {}).items():
        if name in CORE_SECTIONS:
            raise ValueError(f"extra section {name!r} would replace a core section")
        # not plain: values to_jsonable takes (write_result writes them as it would)
        doc[str(name)] = to_jsonable(section) if plain else cast(JsonValue, section)
    return doc


def write_result(doc: Mapping[str, object], path: str | os.PathLike[str]) -> Path:
    """Write ``doc`` as JSON to ``path`` atomically (a temporary file beside it, then rename).

    Raises ``InputError`` when the folder does not exist or cannot be written.
    """
    out = Path(path)
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir():
        raise InputError(f"{out}: folder {folder} does not exist; create it or choose another path")
    text = dumps_result(doc)
    tmp_name = None
    try:
        with tempfile.NamedTemporaryFile(
            "w", encoding="utf-8", dir=folder, prefix=f".{out.name}.", suffix=".tmp", delete=False
        ) as fh:
            tmp_name = fh.name
            fh.write(text)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, out)
    except OSError as exc:
        if tmp_name is not None and os.path.exists(tmp_name):
            os.unlink(tmp_name)
        raise InputError(f"{out}: cannot write the result ({exc}); check the path") from exc
    logger.info("wrote %s (%d bytes)", out, len(text) + 1)
    return out


def read_result(path: str | os.PathLike[str]) -> JsonDocument:
    """Read a result document and check its schema; raises ``InputError`` naming the file."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{p}: file not found; check the path") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{p}: not a readable JSON result ({exc})") from None
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
        found = doc.get("schema") if isinstance(doc, dict) else type(doc).__name__
        raise InputError(
            f"{p}: not a {SCHEMA} result (schema {found!r}); write it with pregrasp decompose/plan"
        )
    return doc
