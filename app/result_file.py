"""A ``pregrasp/1`` result file (``pregrasp plan -o X.json``, the viewer's export) opened in the
viewer: the document's boxes, shape classes, face masks, pre-grasp pool and planned grasps turned
back into the core's value types, so that the scene and the panels draw them as they draw a live
run. Nothing is recomputed: no decomposition, no sampling, no planning.

What a result file does not hold, and what the viewer does about it:

- the points (``input`` describes them but the file keeps none): no cloud is drawn and the
  status says so; the boxes, face masks, ghosts, hand and contacts are drawn from the file;
- the friction-cone tangents: each contact's first cone edge is the y axis of the touching
  link's collision box at the stored pose and joints (the planner's definition,
  ``pregrasp_core.planner.verify``), found by the hand's forward kinematics;
- which boxes block a face, and the covered cells of the sub-face rule: the face masks are
  drawn from the stored 6 x 5 matrices; under the ``subface`` rule no sub-face outline is drawn
  (the cells are not in the file), under the paper's ``face`` rule they follow from the masks.

A file that is not JSON, not ``pregrasp/1`` or malformed ends in one :class:`InputError` naming
the file and the first field that is wrong.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import typing
from dataclasses import dataclass
from typing import Any

import numpy as np

from pregrasp_core.box import OrientedBox
from pregrasp_core.decomposition import BoxNode, BoxTree
from pregrasp_core.errors import InputError
from pregrasp_core.facemask import FaceMasks, usable_subfaces
from pregrasp_core.io import PointCloud
from pregrasp_core.limits import real_or_nan
from pregrasp_core.pipeline import PipelineParams, PipelineResult
from pregrasp_core.planner import Contact, FingerTrace, Grasp, GraspSet
from pregrasp_core.pregrasps import SURFACES, PreGraspPool
from pregrasp_core.result import SCHEMA
from pregrasp_core.shape import GraspType, NodeShape, ShapeClass

MAX_JSON_DEPTH = 64
"""Deepest nesting accepted in a result file (a pregrasp/1 document nests about 8 deep)."""


class FileFaceMasks(FaceMasks):
    """Face masks read from a result file: the blocked faces come from the stored matrices; the
    covered cells of the ``subface`` rule are not in the file, so no sub-face is called usable
    under that rule (under the paper's ``face`` rule they follow from the blocked faces)."""

    def usable(self, node: int, grasp_type: GraspType | str) -> list[np.ndarray]:
        whole = usable_subfaces(self.blocked[node], grasp_type)
        if self.params.rule == "face":
            return whole
        return [np.zeros_like(u) for u in whole]


@dataclass(frozen=True)
class ResultFile:
    """A result file as the viewer shows it."""

    name: str
    """The file's name (as given on the command line or uploaded)."""
    result: PipelineResult
    """Its content as the core's value types (``cloud`` has no points when the file has none)."""
    best: int | None
    """The file's ``best``: index into ``result.grasps`` of its best force-closure grasp."""
    best_reason: str
    """The file's ``best_reason`` ("" when the file was not planned)."""
    source: str
    """``input.source``: the cloud or mesh the result was computed from."""
    n_points: int
    """``input.n_points``: points of that cloud (the file keeps none of them)."""

    @property
    def has_points(self) -> bool:
        """Whether the file held the cloud's points (a pregrasp/1 file never does)."""
        return len(self.result.cloud.points) > 0

    @property
    def planned(self) -> bool:
        """Whether the file holds planned grasps."""
        return self.result.grasps is not None

    def best_grasp(self) -> Grasp | None:
        """The file's best grasp, or ``None``."""
        gs = self.result.grasps
        return None if gs is None or self.best is None else gs.grasps[self.best]


class _Bad(Exception):
    """A field of the document is missing or of the wrong kind (``where``: its path)."""

    def __init__(self, where: str, what: str) -> None:
        super().__init__(f"{where}: {what}")


def _get(d: Any, key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if not isinstance(d, dict):
        raise _Bad(where, "expected an object")
    if key not in d:
        raise _Bad(f"{where}.{key}", "missing")
    v = d[key]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if float in kinds and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)
    if not isinstance(v, kinds) or (isinstance(v, bool) and bool not in kinds):
        raise _Bad(f"{where}.{key}", f"expected {'/'.join(k.__name__ for k in kinds)}")
    return v


def _array(v: Any, shape: tuple[int, ...], where: str, dtype: Any = np.float64) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=dtype)
    except (TypeError, ValueError):
        raise _Bad(where, f"expected numbers of shape {shape}") from None
    if a.shape != shape or (a.dtype.kind == "f" and not np.all(np.isfinite(a))):
        raise _Bad(where, f"expected finite numbers of shape {shape}, got shape {a.shape}")
    return a


def _depth(obj: Any, limit: int) -> int:
    """Nesting depth of a parsed JSON value (stops counting past ``limit``)."""
    stack, deepest = [(obj, 1)], 0
    while stack:
        o, d = stack.pop()
        deepest = max(deepest, d)
        if d > limit:
            return d
        if isinstance(o, dict):
            stack += [(v, d + 1) for v in o.values()]
        elif isinstance(o, list):
            stack += [(v, d + 1) for v in o]
    return deepest


def looks_like_result(data: bytes) -> bool:
    """Whether ``data`` is a JSON object (a result file rather than a point cloud)."""
    return data.lstrip()[:1] == b"{"


def parse_document(data: bytes, name: str) -> dict[str, Any]:
    """The JSON object of a result file; ``InputError`` naming ``name`` when it is not JSON, too
    deep, or not a ``pregrasp/1`` document."""

    def no_constant(c: str) -> None:
        raise ValueError(f"{c} is not JSON")

    try:
        doc = json.loads(data.decode("utf-8"), parse_constant=no_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise InputError(f"{name}: not a readable JSON result file ({exc})") from None
    if not isinstance(doc, dict):
        raise InputError(f"{name}: not a {SCHEMA} result file (a JSON {type(doc).__name__})")
    if doc.get("schema") != SCHEMA:
        raise InputError(
            f"{name}: not a {SCHEMA} result file (schema {str(doc.get('schema'))[:40]!r}); "
            "write one with `pregrasp plan -o FILE.json` or the viewer's export"
        )
    if _depth(doc, MAX_JSON_DEPTH) > MAX_JSON_DEPTH:
        raise InputError(f"{name}: nested deeper than {MAX_JSON_DEPTH} levels")
    return doc


def _build(cls: Any, d: Any, where: str) -> Any:
    """A parameter dataclass from its section (unknown keys ignored, missing ones default);
    its own checks run (a refused value names the field)."""
    if not isinstance(d, dict):
        raise _Bad(where, "expected an object")
    hints = typing.get_type_hints(cls)
    base = cls()
    kw = {}
    for f in dataclasses.fields(cls):
        if f.name not in d:
            continue
        cur, v = getattr(base, f.name), d[f.name]
        if dataclasses.is_dataclass(cur):
            v = _build(type(cur), v, f"{where}.{f.name}")
        elif isinstance(cur, enum.Enum):
            try:
                v = type(cur)(v)
            except ValueError as exc:
                raise _Bad(f"{where}.{f.name}", str(exc)) from None
        elif isinstance(cur, tuple) and isinstance(v, list):
            v = tuple(v)
        elif hints.get(f.name) is float and isinstance(v, int) and not isinstance(v, bool):
            v = real_or_nan(v)  # an integer beyond the float range: inf, which the field refuses
        kw[f.name] = v
    try:
        return cls(**kw)
    except (TypeError, ValueError) as exc:
        raise _Bad(where, str(exc)) from None


def _params(doc: dict[str, Any]) -> tuple[PipelineParams, str]:
    """The file's parameters and the setting its single view's hidden space was planned with
    (``PipelineResult.occluded_used``). ``parameters.occluded`` is written only when it is not
    the default ``auto``; a view's file without it and without ``occluded_used`` was written
    before ``auto`` existed, when the default was ``completed`` (docs/result-schema.md)."""
    sections = _get(doc, "parameters", dict, "")
    base = PipelineParams()
    kw: dict[str, Any] = {}
    for name in base.as_dict():
        if name in sections:
            kw[name] = _build(type(getattr(base, name)), sections[name], f"parameters.{name}")
    inp = doc.get("input")
    view = isinstance(inp, dict) and "scene" in inp
    used = sections.get("occluded_used", "completed")
    if used not in ("completed", "occupied"):
        raise _Bad("parameters.occluded_used", f"{used!r} is not 'completed' or 'occupied'")
    if "occluded" in sections:
        kw["occluded"] = _get(sections, "occluded", str, "parameters")
    elif view and "occluded_used" not in sections:
        kw["occluded"] = "completed"
    return PipelineParams(**kw), used if view else "completed"


def _tree(doc: dict[str, Any]) -> tuple[BoxTree, tuple[NodeShape, ...] | None, np.ndarray | None]:
    tree = _get(doc, "tree", dict, "")
    nodes_doc = _get(tree, "nodes", list, "tree")
    n_points = _get(tree, "n_points", int, "tree")
    nodes, shapes, masks = [], [], []
    for i, nd in enumerate(nodes_doc):
        w = f"tree.nodes[{i}]"
        box = OrientedBox(
            center=_array(_get(nd, "center", list, w), (3,), f"{w}.center"),
            rotation=_array(_get(nd, "rotation", list, w), (3, 3), f"{w}.rotation"),
            extents=_array(_get(nd, "extents", list, w), (3,), f"{w}.extents"),
        )
        idx = nd.get("indices")
        indices = (
            np.zeros(0, dtype=np.int64)
            if idx is None
            else _array(idx, (len(idx),), f"{w}.indices", np.int64)
        )
        if len(indices) and (indices.min() < 0 or indices.max() >= n_points):
            raise _Bad(f"{w}.indices", f"outside [0, {n_points})")
        nodes.append(
            BoxNode(
                id=_get(nd, "id", int, w),
                parent=_get(nd, "parent", int, w),
                children=tuple(_get(nd, "children", list, w)),
                depth=_get(nd, "depth", int, w),
                indices=indices,
                box=box,
                split_order=_get(nd, "split_order", int, w),
            )
        )
        ev, sc, gt = nd.get("eigenvalues"), nd.get("shape_class"), nd.get("grasp_type")
        shapes.append(
            None
            if ev is None or sc is None or gt is None
            else NodeShape(_array(ev, (3,), f"{w}.eigenvalues"), ShapeClass(sc), GraspType(gt))
        )
        fm = nd.get("face_mask")
        masks.append(None if fm is None else _array(fm, (6, 5), f"{w}.face_mask", np.int64))
    try:
        box_tree = BoxTree(nodes=tuple(nodes), n_points=n_points)
    except ValueError as exc:
        raise _Bad("tree.nodes", str(exc)) from None
    known = tuple(s for s in shapes if s is not None)
    all_shapes = known if len(known) == len(shapes) else None
    given = [m for m in masks if m is not None]
    all_masks = np.stack(given) if given and len(given) == len(masks) else None
    return box_tree, all_shapes, all_masks


def _pool(doc: dict[str, Any], joint_names: tuple[str, ...]) -> PreGraspPool | None:
    pool = doc.get("pool")
    if pool is None:
        return None
    items = _get(pool, "pregrasps", list, "pool")
    names = joint_names
    if items:
        first = _get(items[0], "preshape", dict, "pool.pregrasps[0]")
        names = tuple(first)
    P, J = len(items), len(names)
    T, app, q = np.zeros((P, 4, 4)), np.zeros((P, 3)), np.zeros((P, J))
    ints = {k: np.zeros(P, dtype=np.int64) for k in ("node", "face", "subface", "surface")}
    spread, backoff, limit = np.zeros(P), np.zeros(P), np.full(P, np.inf)
    types = []
    for i, it in enumerate(items):  # one loop over the pool: parsing, not computing
        w = f"pool.pregrasps[{i}]"
        T[i] = _array(_get(it, "T_world_hand", list, w), (4, 4), f"{w}.T_world_hand")
        app[i] = _array(_get(it, "approach", list, w), (3,), f"{w}.approach")
        types.append(str(GraspType(_get(it, "grasp_type", str, w)).value))
        spread[i] = _get(it, "spread", float, w)
        for k in ("node", "face", "subface"):
            ints[k][i] = _get(it, k, int, w)
        surface = _get(it, "surface", str, w)
        if surface not in SURFACES:
            raise _Bad(f"{w}.surface", f"not one of {list(SURFACES)}")
        ints["surface"][i] = SURFACES.index(surface)
        backoff[i] = float(it.get("backoff", 0.0) or 0.0)
        lim = it.get("approach_limit")
        limit[i] = np.inf if lim is None else float(lim)
        pre = _get(it, "preshape", dict, w)
        if tuple(pre) != names:
            raise _Bad(f"{w}.preshape", f"expected the joints {list(names)}")
        q[i] = _array(list(pre.values()), (J,), f"{w}.preshape")
    dropped = _get(pool, "dropped", dict, "pool") if "dropped" in pool else {}
    fallback = pool.get("fallback") or {}
    return PreGraspPool(
        T_world_hand=T,
        approach=app,
        grasp_type=np.array(types, dtype=str) if types else np.zeros(0, dtype=str),
        spread=spread,
        q=q,
        node=ints["node"],
        face=ints["face"],
        subface=ints["subface"],
        surface=ints["surface"],
        joint_names=names,
        backoff=backoff,
        approach_limit=limit,
        candidates=tuple(int(c) for c in pool.get("candidates", ()) or ()),
        fallback={int(k): str(v) for k, v in fallback.items()},
        dropped={str(k): int(v) for k, v in dropped.items()},
    )


def _grasps(doc: dict[str, Any], hand: Any, pool: PreGraspPool | None) -> GraspSet | None:
    section = doc.get("grasps")
    if section is None:
        return None
    items = _get(section, "items", list, "grasps")
    if pool is None or len(items) != len(pool):
        raise _Bad("grasps.items", "expected one item per pre-grasp of the pool")
    names = tuple(hand.joint_names)
    links = list(hand.link_names)
    grasps = []
    for i, it in enumerate(items):  # one loop over the pool: parsing, not computing
        w = f"grasps.items[{i}]"
        T = _array(_get(it, "T_world_hand", list, w), (4, 4), f"{w}.T_world_hand")
        joints = _get(it, "joints", dict, w)
        missing = [n for n in names if n not in joints]
        if missing:
            raise _Bad(f"{w}.joints", f"missing {missing}")
        q = _array([joints[n] for n in names], (len(names),), f"{w}.joints")
        fingers = tuple(
            FingerTrace(
                finger=str(_get(f, "finger", str, f"{w}.fingers")),
                n_slice=int(_get(f, "n_slice", int, f"{w}.fingers")),
                q=_array(_get(f, "q", list, f"{w}.fingers"), (2,), f"{w}.fingers.q"),
                links_touched=tuple(str(x) for x in f.get("links_touched", ())),
                palm_stop=bool(f.get("palm_stop", False)),
                support_stop=bool(f.get("support_stop", False)),
                at_limits=bool(f.get("at_limits", False)),
                corrected=bool(f.get("corrected", False)),
            )
            for f in _get(it, "fingers", list, w)
        )
        contacts_doc = _get(it, "contacts", list, w)
        contacts = []
        if contacts_doc:
            Tb = hand.box_poses(q)  # (L, 4, 4): the tangent is the link box's y axis (verify.py)
            for k, c in enumerate(contacts_doc):
                wc = f"{w}.contacts[{k}]"
                link = _get(c, "link", str, wc)
                if link not in links:
                    raise _Bad(f"{wc}.link", f"no link {link[:40]!r} in the hand")
                contacts.append(
                    Contact(
                        point=_array(_get(c, "point", list, wc), (3,), f"{wc}.point"),
                        normal=_array(_get(c, "normal", list, wc), (3,), f"{wc}.normal"),
                        link=link,
                        point_index=int(_get(c, "point_index", int, wc)),
                        distance=float(_get(c, "distance", float, wc)),
                        tangent=T[:3, :3] @ Tb[links.index(link), :3, 1],
                        assumed=bool(c.get("assumed", False)),
                        crest=bool(c.get("crest", False)),
                    )
                )
        rank = it.get("rank")
        grasps.append(
            Grasp(
                pregrasp=_get(it, "pregrasp", int, w),
                grasp_type=str(_get(it, "grasp_type", str, w)),
                T_world_hand=T,
                approach_distance=float(_get(it, "approach_distance", float, w)),
                approach_stop=str(_get(it, "approach_stop", str, w)),
                q=q,
                fingers=fingers,
                contacts=tuple(contacts),
                epsilon=float(_get(it, "epsilon", float, w)),
                volume=float(_get(it, "volume", float, w)),
                rank=None if rank is None else int(rank),
                rejection=it.get("rejection"),
                detail=str(it.get("detail", "")),
                # bounds of issue 15 (files written before it hold exact scores only)
                epsilon_exact=bool(it.get("epsilon_exact", True)),
                volume_exact=bool(it.get("volume_exact", True)),
                quality_bound=str(it.get("quality_bound", "")),
            )
        )
    ranking = _array(
        _get(section, "ranking", list, "grasps"),
        (len(section["ranking"]),),
        "grasps.ranking",
        np.int64,
    )
    if len(ranking) and (ranking.min() < 0 or ranking.max() >= len(grasps)):
        raise _Bad("grasps.ranking", "index outside grasps.items")
    rejected = _get(section, "rejected", dict, "grasps")
    return GraspSet(
        grasps=tuple(grasps),
        ranking=ranking,
        joint_names=names,
        rejected={str(k): int(v) for k, v in rejected.items()},
    )


def read_result_file(data: bytes, name: str, hand: Any) -> ResultFile:
    """The result file ``data`` (named ``name`` in messages) as the viewer shows it; ``hand``
    is the ``pregrasp_core.hand.Hand`` (its joint and link names, and the cone tangents).

    Raises ``InputError`` naming the file and the first bad field."""
    doc = parse_document(data, name)
    try:
        params, occluded_used = _params(doc)
        tree, shapes, fm = _tree(doc)
        inp = _get(doc, "input", dict, "")
        pool = _pool(doc, tuple(hand.joint_names))
        grasps = _grasps(doc, hand, pool)
        masks = None
        if fm is not None:
            K = len(tree.nodes)
            pool_doc = doc.get("pool") or {}
            sp = pool_doc.get("support_plane") if isinstance(pool_doc, dict) else None
            from pregrasp_core.facemask import SupportPlane

            support = (
                None
                if sp is None
                else SupportPlane(
                    _array(_get(sp, "normal", list, "pool.support_plane"), (3,), "normal"),
                    float(_get(sp, "height", float, "pool.support_plane")),
                )
            )
            masks = FileFaceMasks(
                blocked=fm[:, :, 0].astype(bool),
                by_support=np.zeros((K, 6), dtype=bool),
                blockers=tuple(tuple(() for _ in range(6)) for _ in range(K)),
                cut=tuple(tree.leaves()),
                support=support,
                params=params.facemask,
            )
        best = doc.get("best")
        if best is not None and (
            grasps is None or not isinstance(best, int) or not 0 <= best < len(grasps)
        ):
            raise _Bad("best", "not an index into grasps.items")
        source = str(inp.get("source", ""))
        cloud = PointCloud(points=np.zeros((0, 3)), source=source)
        timings = doc.get("timings") or {}
        result = PipelineResult(
            cloud=cloud,
            params=params,
            tree=tree,
            shapes=shapes,
            masks=masks,
            pool=pool,
            grasps=grasps,
            timings={str(k): float(v) for k, v in timings.items() if isinstance(v, int | float)},
            hand=hand,
            occluded_used=occluded_used,
        )
    except _Bad as exc:
        raise InputError(f"{name}: malformed {SCHEMA} result file: {exc}") from None
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as exc:
        raise InputError(f"{name}: malformed {SCHEMA} result file ({exc})") from None
    return ResultFile(
        name=name,
        result=result,
        best=best,
        best_reason=str(doc.get("best_reason", "") or ""),
        source=source,
        n_points=int(inp.get("n_points", 0) or 0),
    )


__all__ = ["FileFaceMasks", "MAX_JSON_DEPTH", "ResultFile", "looks_like_result", "parse_document",
           "read_result_file"]  # fmt: skip
