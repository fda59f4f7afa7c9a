"""Compiled loops on first use: the one way the core's numba kernels are built.

Every module with compiled loops (the planner's, the decomposition's, the quality stage's, the
closing model's) keeps numba out of the package's import: its kernels are plain Python
functions, compiled (or loaded from numba's on-disk cache, ``cache=True``) on the first call
that needs them. :class:`Lazy` builds such a value once per process, even when several threads
ask at the same time; :func:`njit` compiles one function with the options every kernel shares
(``cache=True``; ``nogil=True``, so that threads run the kernels side by side).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from types import ModuleType
from typing import Generic, Literal, TypeVar, cast

T = TypeVar("T")
F = TypeVar("F", bound=Callable[..., object])

_NUMBA_IMPORT = threading.Lock()


def import_numba() -> ModuleType:
    """numba, imported by one thread at a time: numba's own modules import each other in a
    circle, so a thread that imports one of them (``numba.core.extending``, say) while another
    thread is halfway through ``import numba`` finds it half initialised and fails with an
    ``ImportError`` (seen with the pipeline's normals thread and the decomposition starting
    their kernels together in a fresh process). Every numba import of the package goes
    through here."""
    with _NUMBA_IMPORT:
        import numba
        import numba.core.extending  # noqa: F401 - imported whole while the lock is held

    return numba


class Lazy(Generic[T]):
    """A value built by ``build()`` on the first :meth:`get` of the process, once (a lock and
    a second look keep two threads that ask together from building it twice)."""

    def __init__(self, build: Callable[[], T]) -> None:
        self._build = build
        self._lock = threading.Lock()
        self._value: T | None = None

    def get(self) -> T:
        """The value, built on the first call."""
        if self._value is None:
            with self._lock:
                if self._value is None:
                    self._value = self._build()
        return self._value


def njit(
    fn: F, fastmath: bool | set[str] = False, error_model: Literal["python", "numpy"] = "python"
) -> F:
    """``fn`` compiled by numba (imported here, on the first call): ``cache=True``,
    ``nogil=True``, ``fastmath`` as given (False: none) and numba's ``error_model``
    ("python": a float division by zero raises ZeroDivisionError, which puts a branch into
    every division; "numpy": it gives inf or NaN as numpy does, and loops with divisions can
    be vectorised; the same value for every other division)."""
    numba = import_numba()

    return cast(
        F, numba.njit(fn, cache=True, nogil=True, fastmath=fastmath, error_model=error_model)
    )


def inline_helpers(namespace: dict[str, object], *names: str) -> None:
    """Replace each named plain-Python helper of ``namespace`` (a module's ``globals()``) by its
    numba compilation with ``inline="always"``: the kernels that call it then find a compiled
    function there and numba copies its body into theirs (no call in their loops, the same
    operations in the same order). Call before the kernels' first compilation."""
    numba = import_numba()

    for name in names:
        fn = cast(Callable[..., object], namespace[name])
        namespace[name] = numba.njit(fn, inline="always", cache=True)
