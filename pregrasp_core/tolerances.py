"""Numerical tolerances in one place (metres and radians)."""

from __future__ import annotations

GEOM_EPS: float = 1e-9
"""Lengths below this are zero (metres)."""

BOX_CONTAINS_TOL: float = 1e-7
"""Slack when testing that a point lies inside its box (metres): floating-point round-off only."""

FLAT_EXTENT: float = 1e-6
"""A box side shorter than this is flat (coplanar input gives a flat box; metres)."""
