"""Grasps packed for a pipe between processes: a few stacked arrays instead of thousands of
small ones.

The forked planner (``planner/plan.py``) sends each chunk's grasps from its copy to the parent,
and the viewer's planner process (``app/planner_proc.py``) sends a whole ``GraspSet`` back to
the viewer. Pickled as they are, 276 grasps are about 4,300 small numpy arrays (the hand pose,
the joints, each finger's angles, each contact's point, normal and tangent), and pickle spends
a few microseconds on each one: about 20 ms to dump and 15 ms to load on the default object.
:func:`pack_grasps` stacks every array field into one array per field (in grasp, finger and
contact order) and keeps every other field as the very object it was (so its type, and every
float's bits, come back unchanged); :func:`unpack_grasps` builds the same grasps again, each
array a row of its field's stacked array. When an array field's rows differ in shape or dtype,
or are not plain ``ndarray`` objects, the grasps are passed on unpacked (plain pickle), so
nothing outside the planner's own layout changes what comes out.

``unpack_grasps(pack_grasps(gs))`` equals ``gs`` field by field, bit for bit
(``tests/core/test_packing.py``); the arrays it returns are views into the stacked ones (C
ordered and writeable, as pickle's copies are).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, cast

import numpy as np

from .types import Contact, FingerTrace, Grasp, GraspSet

_FORMAT: str = "pregrasp-grasps-2"
"""Tag of a packed list (its first item)."""

_PLAIN: str = "pregrasp-grasps-plain"
"""Tag of a list passed on unpacked (an array field whose rows cannot be stacked)."""

Packed = tuple[object, ...]
"""Grasps in the packed form: a tag, then the tag's parts (picklable)."""


def _stack(rows: list[Any]) -> np.ndarray | None:
    """The rows (each an ``ndarray`` of one shape and dtype) stacked, or None when they are not
    all plain arrays of the first one's shape and dtype. An empty list gives None too (the
    caller then has nothing to split)."""
    if not rows:
        return None
    first = rows[0]
    if type(first) is not np.ndarray:
        return None
    shape, dtype = first.shape, first.dtype
    for r in rows:  # loop over the rows (a type and shape check each, no copy)
        if type(r) is not np.ndarray or r.shape != shape or r.dtype != dtype:
            return None
    return np.stack(rows)


def pack_grasps(grasps: Sequence[Grasp]) -> Packed:
    """``grasps`` in the packed form (module docstring), picklable; for :func:`unpack_grasps`."""
    gs = list(grasps)
    if not all(type(g) is Grasp for g in gs):
        return (_PLAIN, gs)
    fingers = [f for g in gs for f in g.fingers]
    contacts = [c for g in gs for c in g.contacts]
    if not all(type(f) is FingerTrace for f in fingers) or not all(
        type(c) is Contact for c in contacts
    ):
        return (_PLAIN, gs)
    arrays = {
        "T": [g.T_world_hand for g in gs],
        "q": [g.q for g in gs],
        "fq": [f.q for f in fingers],
        "point": [c.point for c in contacts],
        "normal": [c.normal for c in contacts],
        "tangent": [c.tangent for c in contacts],
    }
    stacked: dict[str, np.ndarray | None] = {}
    for key, rows in arrays.items():  # loop over the 6 array fields
        stacked[key] = _stack(rows)
        if rows and stacked[key] is None:
            return (_PLAIN, gs)
    grasp_rows = [
        (
            g.pregrasp, g.grasp_type, g.approach_distance, g.approach_stop, len(g.fingers),
            len(g.contacts), g.epsilon, g.volume, g.rank, g.rejection, g.detail,
            g.epsilon_exact, g.volume_exact, g.quality_bound,
        )
        for g in gs
    ]  # fmt: skip
    finger_rows = [
        (f.finger, f.n_slice, f.links_touched, f.palm_stop, f.support_stop, f.at_limits,
         f.corrected)
        for f in fingers
    ]  # fmt: skip
    contact_rows = [(c.link, c.point_index, c.distance, c.assumed, c.crest) for c in contacts]
    return (_FORMAT, grasp_rows, finger_rows, contact_rows, stacked)


def unpack_grasps(packed: Packed) -> list[Grasp]:
    """The grasps that :func:`pack_grasps` packed, equal to them field by field."""
    if packed[0] == _PLAIN:
        return list(cast(list[Grasp], packed[1]))
    if packed[0] != _FORMAT:
        raise ValueError(f"not a packed list of grasps: {packed[0]!r}")
    _, grasp_rows, finger_rows, contact_rows, s = cast(tuple[Any, ...], packed)
    T, q, fq = s["T"], s["q"], s["fq"]
    point, normal, tangent = s["point"], s["normal"], s["tangent"]
    fingers = [
        FingerTrace(name, n_slice, fq[k], links, palm, support, limits, corrected)
        for k, (name, n_slice, links, palm, support, limits, corrected) in enumerate(finger_rows)
    ]
    contacts = [
        Contact(point[k], normal[k], link, index, distance, tangent[k], assumed, crest)
        for k, (link, index, distance, assumed, crest) in enumerate(contact_rows)
    ]
    out = []
    kf = kc = 0
    for i, row in enumerate(grasp_rows):  # loop over the grasps
        (pregrasp, gtype, dist, stop, nf, nc, eps, vol, rank, rejection, detail, e_exact,
         v_exact, bound) = row  # fmt: skip
        grasp = Grasp(
            pregrasp, gtype, T[i], dist, stop, q[i], tuple(fingers[kf : kf + nf]),
            tuple(contacts[kc : kc + nc]), eps, vol, rank, rejection, detail, e_exact,
            v_exact, bound,
        )  # fmt: skip
        out.append(grasp)
        kf += nf
        kc += nc
    return out


def pack_grasp_set(gs: GraspSet) -> Packed:
    """A ``GraspSet`` with its grasps packed (:func:`pack_grasps`), picklable."""
    return (pack_grasps(gs.grasps), gs.ranking, gs.joint_names, gs.rejected, gs.phase_seconds)


def unpack_grasp_set(packed: Packed) -> GraspSet:
    """The ``GraspSet`` that :func:`pack_grasp_set` packed."""
    grasps, ranking, joint_names, rejected, phase_seconds = cast(tuple[Any, ...], packed)
    return GraspSet(tuple(unpack_grasps(grasps)), ranking, joint_names, rejected, phase_seconds)
