"""Numerical tolerances in one place (metres and radians)."""

from __future__ import annotations

GEOM_EPS: float = 1e-9
"""Lengths below this are zero (metres)."""

BOX_CONTAINS_TOL: float = 1e-7
"""Slack when testing that a point lies inside its box (metres): floating-point round-off only."""

FLAT_EXTENT: float = 1e-6
"""A box side shorter than this is flat (coplanar input gives a flat box; metres)."""

# --- quality and planner (issue 5) ---

QUALITY_EPS: float = 1e-9
"""Epsilon (wrench units) at or below this is 0: the origin is on the hull boundary or outside."""

QUALITY_RANK_TOL: float = 1e-9
"""Relative singular-value threshold below which a wrench set is rank-deficient (score 0)."""

HULL_CHECK_TOL: float = 1e-9
"""An exact (unmerged) wrench hull is accepted when no wrench lies farther than this, relative to
the largest wrench coordinate, outside any of its facets (else the joggled hull is used)."""

CONTACT_DISTANCE: float = 0.003
"""A hand link counts as touching the cloud when a cloud point is within this distance (metres)."""

PENETRATION_TOL: float = 0.002
"""Largest depth a cloud point may lie inside a link of the final hand (metres)."""

MVBB_DEGENERATE_REL: float = 1e-9
"""MVBB: a principal-axis spread below this fraction of the largest spread counts as zero
(identical, collinear or coplanar points; see ``docs/mvbb.md``)."""

UNIT_NORMAL_TOL: float = 1e-2
"""Input columns 4-6 are read as normals when every row's length is within this of 1
(otherwise they are colours or other attributes and are ignored); used by ``io``."""

FACE_OVERLAP_TOL: float = 0.002
"""Metres: a box blocks a face only when it penetrates the slab in front of the face deeper than
this (touching, e.g. a part sitting flush on the face's edge, does not block; face masks)."""

SUPPORT_PENETRATION_TOL: float = 0.002
"""Metres: the support plane blocks a face only when the slab in front of the face reaches deeper
than this below it (so side faces of a part standing on the table stay free; face masks)."""

# --- hand (issue 3) ---

HAND_CLOSING_ANGLE_TOL: float = 1e-4
"""Radians: the hand's closing model refines the first touching step (dense resampling) until the
bracket [last free, first touching] of the path parameter is narrower than this."""

SELF_COLLISION_SAT_MARGIN: float = 1e-9
"""Metres: the self-collision pre-filter (``Hand.self_collisions_many``) calls two link boxes
apart without python-fcl only when one of the 15 separating axes parts them by more than this;
every other pair goes to python-fcl, so the answer stays python-fcl's."""

SAT_ABS_ROTATION_EPS: float = 1e-9
"""Added to every entry of ``|R_a^T R_b|`` in the box-box separating-axis pre-filter (the usual
guard for near-parallel edges, whose cross product is round-off): it only enlarges the boxes'
projected radii (by at most this times their summed half sides), so the test stays conservative."""
