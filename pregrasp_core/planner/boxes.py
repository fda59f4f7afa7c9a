"""Exact point-box geometry of the planner: the signed distance from points to oriented boxes
and the first contact of boxes swept along a direction (slab intersection per (point, box))."""

from __future__ import annotations

import numpy as np


def box_signed_distance(p: np.ndarray, T_boxes: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(M, L) exact signed distance from points ``p`` (M, 3) to boxes with poses ``T_boxes``
    (L, 4, 4) (same frame as ``p``) and half extents ``half`` (L, 3); negative inside (minus the
    depth to the nearest face)."""
    R = T_boxes[:, :3, :3]  # (L, 3, 3)
    L = R.shape[0]
    local = (p @ R.transpose(1, 0, 2).reshape(3, 3 * L)).reshape(-1, L, 3)
    local -= np.einsum("li,lij->lj", T_boxes[:, :3, 3], R)[None]
    q = np.abs(local) - half[None]  # (M, L, 3)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=2)
    inside = np.minimum(q.max(axis=2), 0.0)
    return outside + inside


def box_push_direction(p: np.ndarray, T_boxes: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(M, 3) unit direction in which each box ``T_boxes[k]`` (M, 4, 4; half extents ``half[k]``
    (M, 3)) pushes the point ``p[k]`` (M, 3, same frame): the box's outward normal at the point
    of its surface nearest ``p[k]`` (from that point to ``p[k]`` when ``p[k]`` is outside; the
    normal of the nearest face when it is inside or on it)."""
    R = T_boxes[:, :3, :3]
    local = np.einsum("kji,kj->ki", R, p - T_boxes[:, :3, 3])  # R^T (p - c)
    q = np.abs(local) - half
    out = np.where(q > 0.0, np.sign(local) * q, 0.0)  # from the nearest surface point
    norm = np.linalg.norm(out, axis=1)
    inside = norm <= 0.0
    if inside.any():  # on or in the box: the face of least depth
        ax = np.argmax(q[inside], axis=1)
        face = np.zeros((int(inside.sum()), 3))
        rows = np.arange(len(ax))
        face[rows, ax] = np.where(local[inside][rows, ax] < 0.0, -1.0, 1.0)
        out[inside] = face
        norm[inside] = 1.0
    return np.einsum("kij,kj->ki", R, out / norm[:, None])


def sweep_hit(
    p: np.ndarray, T_boxes: np.ndarray, half: np.ndarray, direction: np.ndarray
) -> tuple[float, int]:
    """First travel ``s >= 0`` at which boxes moving by ``s * direction`` touch a point.

    p: (M, 3) points, T_boxes: (L, 4, 4) box poses, half: (L, 3) half extents (already grown by
    any clearance), direction: (3,) unit, all in one frame. Returns ``(s, box index)``, or
    ``(inf, -1)`` when no point is ever touched. Exact slab intersection per (point, box).
    """
    p = np.asarray(p, dtype=np.float64)
    T = np.asarray(T_boxes, dtype=np.float64)
    if len(p) == 0 or len(T) == 0:
        return np.inf, -1
    # rotate everything so that the motion is along +z, then test every (point, box) pair
    z = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    F = np.stack([x, np.cross(z, x), z])  # rows: the new frame's axes
    Tz = T.copy()
    Tz[:, :3, :3] = F @ T[:, :3, :3]
    Tz[:, :3, 3] = T[:, :3, 3] @ F.T
    ip, il = np.divmod(np.arange(len(p) * len(T)), len(T))
    pz = p @ F.T  # (M, 3) in the frame whose z is the motion
    hw = np.asarray(half, dtype=np.float64)
    s, k = sweep_pairs(pz[ip, 0], pz[ip, 1], pz[ip, 2], il, Tz, hw)
    return (s, int(il[k])) if np.isfinite(s) else (np.inf, -1)


def sweep_pairs(
    px: np.ndarray, py: np.ndarray, pz: np.ndarray, il: np.ndarray, T: np.ndarray, half: np.ndarray
) -> tuple[float, int]:
    """First travel along +z (the frame's z axis) at which box ``il[k]`` (pose ``T[il[k]]``,
    half extents ``half[il[k]]``; T (L, 4, 4), half (L, 3)) touches point k (coordinates ``px,
    py, pz`` (K,)), minimised over the K pairs: ``(s, k)``, or ``(inf, -1)`` if never. Exact
    slab intersection in each box's frame, one axis at a time."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    v0, v1, v2 = px - t[il, 0], py - t[il, 1], pz - t[il, 2]
    s_in = np.full(len(il), -np.inf)
    s_out = np.full(len(il), np.inf)
    for j in range(3):  # the box's three axes
        a = v0 * R[il, 0, j] + v1 * R[il, 1, j] + v2 * R[il, 2, j]  # box coordinate j
        d = R[il, 2, j]  # the motion (+z) in box coordinate j
        h = half[il, j]
        small = np.abs(d) < 1e-12
        d_safe = np.where(small, 1.0, d)
        t1 = (a - h) / d_safe
        t2 = (a + h) / d_safe
        inside = np.abs(a) <= h
        s_in = np.maximum(
            s_in, np.where(small, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
        )
        s_out = np.minimum(
            s_out, np.where(small, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
        )
    hit = (s_in <= s_out) & (s_out >= 0.0)
    if not hit.any():
        return np.inf, -1
    s = np.where(hit, np.maximum(s_in, 0.0), np.inf)
    k = int(np.argmin(s))
    return float(s[k]), k
