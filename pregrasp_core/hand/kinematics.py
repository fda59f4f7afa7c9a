"""Forward kinematics of the hand and the joint vector: limits, the configuration of every
moving joint, link and collision-box poses (vectorised over configurations), fingertips, the
fingers' flexion planes and the palm's box. Every function takes the :class:`HandModel` first."""

from __future__ import annotations

import numpy as np

from ..box import OrientedBox
from .model import Finger, FlexionPlane, HandModel


def clamp(model: HandModel, q: np.ndarray) -> np.ndarray:
    """``q`` ((J,) or (B, J)) clipped to the joint limits."""
    arr = np.asarray(q, dtype=np.float64)
    model.as_q(arr)
    return np.clip(arr, model.lower, model.upper)


def within_limits(model: HandModel, q: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Whether each configuration respects the limits: bool () for (J,), (B,) for (B, J)."""
    Q, single = model.as_q(q)
    ok = np.all((Q >= model.lower - tol) & (Q <= model.upper + tol), axis=1)
    return ok[0] if single else ok


def full_cfg(model: HandModel, q: np.ndarray) -> dict[str, float]:
    """Joint name -> value for every moving joint (actuated and mimic), e.g. for yourdfpy's
    and viser's ``update_cfg`` or the result file."""
    Q, single = model.as_q(q)
    if not single:
        raise ValueError(f"full_cfg takes one configuration ({model.n_joints},), got {Q.shape}")
    out = {}
    for j in model.chain:
        if j.axis is not None:
            out[j.name] = float(j.multiplier * Q[0, j.source] + j.offset)
    return out


def with_flexion(
    model: HandModel, q: np.ndarray, finger: str | Finger, q_flex: np.ndarray
) -> np.ndarray:
    """A copy of ``q`` (J,) with the finger's two flexion joints set to ``q_flex`` (2,)."""
    out = model.one_q(q).copy()
    f = model.finger(finger)
    out[list(f.flex_index)] = np.asarray(q_flex, dtype=np.float64).reshape(2)
    return out


def fk_array(model: HandModel, q: np.ndarray) -> np.ndarray:
    """Link poses ``T_hand_link`` as one array: (B, L, 4, 4) for ``q`` (B, J), in
    ``link_names`` order; (L, 4, 4) for ``q`` (J,). Vectorised over configurations."""
    Q, single = model.as_q(q)
    R, t = _fk_rt(model, Q)
    B, L = R.shape[0], R.shape[1]
    out = np.zeros((B, L, 4, 4))
    out[:, :, :3, :3] = R
    out[:, :, :3, 3] = t
    out[:, :, 3, 3] = 1.0
    return out[0] if single else out


def _fk_rt(model: HandModel, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (B, L, 3, 3) and translations (B, L, 3) of every link for ``Q`` (B, J).

    Per joint: ``R_child = R_parent R_origin R_axis(angle)`` with Rodrigues' formula written
    as ``A R_axis = A + sin(angle) A K + (1 - cos(angle)) A K^2`` (A = R_parent R_origin,
    K the axis' cross-product matrix), so every product is a (3B, 3) x (3, 3) matrix product;
    the rotation about the joint origin leaves the translation alone."""
    B = Q.shape[0]
    L = len(model.link_names)
    R = np.empty((L, B, 3, 3))  # link-major so that every R[i] is contiguous
    t = np.empty((L, B, 3))
    root = model.link_names.index("palm")
    R[root] = np.eye(3)  # the palm (root) is the hand frame
    t[root] = 0.0
    for j in model.chain:  # parents before children
        ip, ic, K, K2 = j.parent_index, j.child_index, j.K, j.K2
        Rp = R[ip].reshape(3 * B, 3)  # rows of the parent rotations
        A = Rp @ j.origin[:3, :3]  # (3B, 3): R_parent R_origin
        t[ic] = t[ip] + (Rp @ j.origin[:3, 3]).reshape(B, 3)
        if K is None or K2 is None:  # a fixed joint
            R[ic] = A.reshape(B, 3, 3)
            continue
        angle = j.multiplier * Q[:, j.source] + j.offset
        s = np.repeat(np.sin(angle), 3)[:, None]  # (3B, 1): one per row
        c1 = np.repeat(1.0 - np.cos(angle), 3)[:, None]
        R[ic] = (A + s * (A @ K) + c1 * (A @ K2)).reshape(B, 3, 3)
    return R.transpose(1, 0, 2, 3), t.transpose(1, 0, 2)


def fk(model: HandModel, q: np.ndarray) -> dict[str, np.ndarray]:
    """Link name -> ``T_hand_link``: (B, 4, 4) for ``q`` (B, J), (4, 4) for ``q`` (J,)."""
    T = fk_array(model, q)
    return {n: T[..., i, :, :] for i, n in enumerate(model.link_names)}


def box_poses(model: HandModel, q: np.ndarray) -> np.ndarray:
    """Collision box poses ``T_hand_box``: (B, L, 4, 4) for (B, J), (L, 4, 4) for (J,)."""
    return fk_array(model, q) @ model.link_box_T


def fingertips(model: HandModel, q: np.ndarray) -> dict[str, np.ndarray]:
    """Finger name -> fingertip centre (end of the distal link on its axis) in the hand frame:
    (B, 3) for ``q`` (B, J), (3,) for (J,)."""
    return _distal_ends(model, q, pads=False)


def tip_pads(model: HandModel, q: np.ndarray) -> dict[str, np.ndarray]:
    """Finger name -> the fingertip's inner edge (end of the distal link, on the closing side,
    in the flexion plane): the point apertures are measured between. (3,) or (B, 3)."""
    return _distal_ends(model, q, pads=True)


def _distal_ends(model: HandModel, q: np.ndarray, pads: bool) -> dict[str, np.ndarray]:
    # finger -> end of the distal link on its axis (origin + length z), with pads moved half
    # the link's thickness along its x (the closing side); left to right, as one sum
    T = fk_array(model, q)
    out = {}
    for f in model.fingers:
        Td = T[..., model.link_names.index(f.links[2]), :, :]
        end = Td[..., :3, 3] + f.distal_length * Td[..., :3, 2]
        out[f.name] = end + 0.5 * f.thickness * Td[..., :3, 0] if pads else end
    return out


def flexion_plane(model: HandModel, finger: str | Finger, spread: float = 0.0) -> FlexionPlane:
    """The finger's flexion plane in the hand frame for a spread angle (ignored for the
    thumb). Independent of the flexion angles."""
    f = model.finger(finger)
    q = np.zeros(model.n_joints)
    q[model.spread_index] = float(spread)
    T = fk_array(model, q)
    Tk = T[model.link_names.index(f.links[0])]  # knuckle frame: axes of the finger frame
    Tm = T[model.link_names.index(f.links[1])]  # origin = first flexion joint
    return FlexionPlane(
        origin=Tm[:3, 3].copy(), u=Tk[:3, 2].copy(), v=Tk[:3, 0].copy(), normal=Tk[:3, 1].copy()
    )


def palm_box(model: HandModel) -> OrientedBox:
    """The palm's collision box in the hand frame (its top face is the plane z = 0)."""
    i = model.link_names.index("palm")
    T = model.link_box_T[i]
    return OrientedBox(
        center=T[:3, 3].copy(), rotation=T[:3, :3].copy(), extents=2.0 * model.link_box_half[i]
    )
