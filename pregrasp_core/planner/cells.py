"""The planner's spatial index: the cloud grouped into cubic cells, each with a ball that holds
its points, so that a candidate search tests a few thousand balls instead of every point."""

from __future__ import annotations

import numpy as np

CELL_MARGIN: float = 1e-9
"""Added to every cell's bounding-ball radius (metres): far above the rounding of a frame
change, so that a cell test never drops a point the exact test would keep."""


class Cells:
    """The cloud grouped into cubic cells for candidate searches. A search tests every cell's
    bounding ball (a few thousand cells instead of tens of thousands of points) and expands the
    cells that pass into their points: a superset of what it looks for, on which the exact test
    then runs. So the cells change only the speed, never which points pass."""

    def __init__(self, points: np.ndarray, size: float) -> None:
        """points: (N, 3) float64, world; size: the cells' side (metres)."""
        n = len(points)
        key = np.floor(points / size).astype(np.int64)
        if n:  # one integer per cell, in the lexicographic order of its (x, y, z) keys
            key -= key.min(axis=0)
            dim = key.max(axis=0) + 1
            cell = (key[:, 0] * dim[1] + key[:, 1]) * dim[2] + key[:, 2]
        else:
            cell = np.zeros(0, dtype=np.int64)
        self.order = np.argsort(cell, kind="stable")
        """(N,) cloud indices grouped by cell (cells in the lexicographic order of their integer
        coordinates), ascending within a cell."""
        sc = cell[self.order]
        self.start = np.flatnonzero(np.r_[True, sc[1:] != sc[:-1]]) if n else np.zeros(0, int)
        """(C,) where each cell's points begin in ``order``."""
        self.count = np.diff(np.r_[self.start, n])
        """(C,) points per cell."""
        if n:
            ps = points[self.order]
            lo = np.minimum.reduceat(ps, self.start, axis=0)
            hi = np.maximum.reduceat(ps, self.start, axis=0)
            self.centre = 0.5 * (lo + hi)
            """(C, 3) cell ball centres, world."""
            d = np.linalg.norm(ps - np.repeat(self.centre, self.count, axis=0), axis=1)
            self.radius = np.maximum.reduceat(d, self.start) + CELL_MARGIN
            """(C,) radii of balls about ``centre`` that hold every point of the cell."""
        else:
            self.centre, self.radius = np.zeros((0, 3)), np.zeros(0)

    def points_of(self, cells: np.ndarray) -> np.ndarray:
        """The cloud indices of the points of ``cells`` (distinct cells), ascending."""
        seen = np.zeros(len(self.order), dtype=bool)
        seen[self.expand(cells)[0]] = True
        return np.flatnonzero(seen)

    def expand(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The cloud indices (K,) of the points of ``cells`` (a list that may repeat cells) and,
        for each point, its row in ``cells``."""
        n = self.count[cells]
        k = np.repeat(np.arange(len(cells)), n)
        first = np.cumsum(n) - n
        return self.order[np.arange(len(k)) - first[k] + self.start[cells][k]], k
