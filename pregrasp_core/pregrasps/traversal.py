"""Which nodes of the decomposition tree get pre-grasps (:func:`traverse`)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..box import OrientedBox
from ..decomposition import BoxTree
from ..hand import grasp_type_name
from ..shape import GRASP_TYPES, NodeShape, ShapeParams, is_small
from .params import SamplingParams, TraversalPolicy

if TYPE_CHECKING:
    from ..hand import Hand

logger = logging.getLogger(__name__)


def grip_width(box: OrientedBox, grasp_type: str) -> float:
    """Metres: the width of the part the open hand must span for this grasp type.

    cylindrical: the larger side of the cross-section (the fingers close across axis 0);
    spherical and two-finger tip: the longest side (sampled from every direction);
    three-finger tip: the thickness (the fingertips close across axis 2).
    """
    gt = grasp_type_name(grasp_type)
    e = box.extents
    return float({"cylindrical": e[1], "three_finger_tip": e[2]}.get(gt, e[0]))


def fitting_types(box: OrientedBox, hand: Hand, params: SamplingParams) -> list[str]:
    """The grasp types whose grip of the part in ``box`` fits the open hand
    (:func:`grip_width` at most ``hand.aperture(type) * params.aperture_scale``), in
    ``GRASP_TYPES`` order."""
    return [
        gt
        for gt in GRASP_TYPES
        if grip_width(box, gt) <= float(hand.aperture(gt)) * params.aperture_scale
    ]


def no_fit_hint(
    tree: BoxTree,
    shapes: Sequence[NodeShape],
    hand: Hand,
    params: SamplingParams | None = None,
) -> str:
    """Why no node of ``tree`` is a candidate, in one sentence for a user. A part is grasped
    with the grasp type its shape gives it (``shapes``, what :func:`traverse` tests), so the
    sentence names the part whose grip of that type is the narrowest against what the hand opens
    for it; when another type would fit some part, it says so (the classification's thresholds
    decide the type); when even the narrowest grip of any type is at least 3 times too wide, it
    hints that the file may not be in metres (a mug in inches is 4.5 m long; the millimetre rule
    does not catch it)."""
    params = SamplingParams() if params is None else params
    if not tree.nodes:
        return "the decomposition has no part"
    if len(shapes) != len(tree.nodes):
        raise ValueError(
            f"shapes must have one entry per node ({len(tree.nodes)}), got {len(shapes)}"
        )

    def ratio(nd_id: int, gt: str) -> tuple[float, float, float, str, int]:
        width = grip_width(tree.nodes[nd_id].box, gt)
        opens = float(hand.aperture(gt)) * params.aperture_scale
        return width / max(opens, 1e-12), width, opens, grasp_type_name(gt), nd_id

    own = min(ratio(nd.id, shapes[nd.id].grasp_type) for nd in tree.nodes)
    any_type = min(ratio(nd.id, gt) for nd in tree.nodes for gt in GRASP_TYPES)
    _, width, opens, gt, i = own
    text = (
        f"no part of the object fits the hand with the grasp type its shape gives it: the "
        f"narrowest is part {i}, {gt} across {width:.3g} m, and the hand opens {opens:.3g} m for "
        "it"
    )
    if any_type[0] <= 1.0:
        _, w2, o2, gt2, i2 = any_type
        text += (
            f" (a {gt2} grip of part {i2} would fit, {w2:.3g} m of {o2:.3g} m: the shape "
            "classification's thresholds give the parts their types)"
        )
    elif any_type[0] >= 3.0:
        longest = float(tree.nodes[0].box.extents[0])
        text += (
            f"; the object is {longest:.3g} m long: if the file is not in metres, pass --scale "
            "(0.001 for millimetres, 0.01 for centimetres, 0.0254 for inches)"
        )
    return text


@dataclass(frozen=True)
class Traversal:
    """Which nodes get pre-grasps, and why each node does or does not."""

    candidates: tuple[int, ...]
    """Ids of the candidate nodes, in traversal order (breadth-first from the root)."""
    reasons: tuple[str, ...]
    """Per node id: ``"candidate"`` or why not (``"no small child"``, ``"too big: ..."``)."""
    policy: TraversalPolicy
    """The policy used."""

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return {
            "policy": self.policy.value,
            "candidates": list(self.candidates),
            "reasons": list(self.reasons),
        }


def traverse(
    tree: BoxTree,
    shapes: Sequence[NodeShape],
    hand: Hand,
    params: SamplingParams | None = None,
    shape_params: ShapeParams | None = None,
) -> Traversal:
    """Visit the tree from the root down and pick the candidate nodes (see
    :class:`TraversalPolicy`). ``hand`` provides ``aperture(grasp_type) -> metres``;
    ``shape_params.small_size`` decides which children are small. With ``params.fallback``,
    when no node fits its own type, the nodes the policy allows that another type fits are
    the candidates (:func:`fitting_types`; ``docs/pregrasps.md``, section 6)."""
    params = SamplingParams() if params is None else params
    if len(shapes) != len(tree.nodes):
        raise ValueError(
            f"shapes must have one entry per node ({len(tree.nodes)}), got {len(shapes)}"
        )
    order: list[int] = []
    queue = [tree.root.id]
    while queue:  # breadth-first over nodes (small set)
        i = queue.pop(0)
        order.append(i)
        queue.extend(tree.nodes[i].children)
    reasons = [""] * len(tree.nodes)
    candidates: list[int] = []
    too_big: list[int] = []  # structural nodes too big for their own type
    for i in order:
        nd = tree.nodes[i]
        gt = shapes[i].grasp_type
        if params.policy is TraversalPolicy.ALL:
            ok, why = True, "candidate"
        else:
            width = grip_width(nd.box, gt)
            aperture = float(hand.aperture(gt)) * params.aperture_scale
            fits = width <= aperture
            if params.policy is TraversalPolicy.LEAVES:
                structural = nd.is_leaf
                no_why = "not a leaf"
            else:
                structural = nd.is_leaf or any(
                    is_small(tree.nodes[c].box, shape_params) for c in nd.children
                )
                no_why = "no small child"
            if not structural:
                ok, why = False, no_why
            elif not fits:
                ok, why = (
                    False,
                    f"too big: {grasp_type_name(gt)} width {width:.3f} m > aperture "
                    f"{aperture:.3f} m",
                )
                too_big.append(i)
            else:
                ok, why = True, "candidate"
        reasons[i] = why
        if ok:
            candidates.append(i)
    if not candidates and params.fallback:
        # no part fits the type its shape gives it: as a last resort the parts that another
        # type fits (the pool then tries only those types, SamplingParams.fallback)
        for i in too_big:  # loop over the few structural nodes, in traversal order
            if fitting_types(tree.nodes[i].box, hand, params):
                candidates.append(i)
                reasons[i] += "; candidate by fallback (no part fits its own type)"
    logger.info("traversal (%s): candidates %s", params.policy.value, candidates)
    return Traversal(candidates=tuple(candidates), reasons=tuple(reasons), policy=params.policy)
