"""Errors of pregrasp. Every domain failure is a :class:`PregraspError`; the message says what
went wrong, where (file name when there is one) and what to do."""

from __future__ import annotations


class PregraspError(Exception):
    """Base class of every error pregrasp raises on purpose."""


class InputError(PregraspError):
    """A file or array given to pregrasp cannot be used (missing, empty, malformed, NaN...)."""


class DegenerateGeometryError(PregraspError):
    """The geometry cannot support the requested computation (too few points, all collinear...)."""


class HandModelError(PregraspError):
    """The hand description (URDF) is missing or inconsistent."""


class WorkLimitError(PregraspError):
    """The requested work would pass one of the limits that keep memory and time finite
    (:class:`~pregrasp_core.limits.WorkLimits`); the message names the parameters to change."""
