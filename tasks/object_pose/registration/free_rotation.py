"""The rotation one depth view leaves free, and the poses along it nearest register_object's.

A mug held with its handle turned away shows the camera a patch of its cylindrical body only:
every turn about the body's axis explains the depth equally (held-out mug [9900, 4]: the
truth, a pose 99 deg away and its upside-down twin all at fitness 1.0 and depth agreement
0.996-1.0, the handle hidden behind the body in 6 of 7 steady frames). Symmetry probes about
the model's principal axes miss that family when the axes are ill-defined (the mug's two
largest principal spreads are within 3 %, so its axes are mixed 54 deg away from the body's
axis and its handle's). The free rotation is read off the depth itself: the least
constrained direction of point-to-plane ICP (the 6 x 6 normal matrix of the scene's points and
normals, Gelfand et al. 2003). Turning a pose about it to the rotation nearest register_object's
gives the member of its family :mod:`estimate_adjustment`'s tie rule asks for.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graspcap.tasks.core.geometry import make_T

# scipy: imported where used, so that importing the stage table stays cheap


@dataclass(frozen=True)
class FreeAxis:
    """The least constrained rotation of a scene.

    Attributes
    ----------
    axis : (3,) float
        Unit direction, scene frame.
    point : (3,) float
        A point on the rotation's axis, scene frame.
    weakness : float
        Its eigenvalue over the largest (0 = entirely free, ~1 = as constrained as the rest).
    """

    axis: np.ndarray
    point: np.ndarray
    weakness: float


def free_axis(points: np.ndarray, normals: np.ndarray) -> FreeAxis:
    """The rotation (axis through a point) that moves ``points`` (n, 3) least along their
    ``normals`` (n, 3): the eigenvector of the point-to-plane normal matrix with the smallest
    eigenvalue among those dominated by rotation (a pure slide, e.g. along a cylinder, is not
    a rotation). Rotations are scaled by the points' RMS distance from their centroid."""
    p = np.asarray(points, float)
    n = np.asarray(normals, float)
    centre = p.mean(axis=0)
    q = p - centre
    scale = max(float(np.sqrt((q**2).sum(axis=1).mean())), 1e-9)
    J = np.hstack([np.cross(q, n) / scale, n])
    values, vectors = np.linalg.eigh(J.T @ J)
    # rotation-dominated eigenvectors, weakest first (the strongest is always one of them
    # or a slide; with none dominated, the one with the largest rotation part)
    share = np.linalg.norm(vectors[:3], axis=0)
    k = next((i for i in range(6) if share[i] >= np.sqrt(0.5)), int(np.argmax(share)))
    omega, v = vectors[:3, k] / scale, vectors[3:, k]
    norm = np.linalg.norm(omega)
    # twist (omega, v) about the centroid: v = c x omega for an axis through c (c _|_ omega)
    point = centre + np.cross(omega, v) / norm**2
    return FreeAxis(omega / norm, point, float(values[k] / max(values[-1], 1e-300)))


def turned(T_w_o: np.ndarray, axis: np.ndarray, point: np.ndarray, angle_rad: float) -> np.ndarray:
    """``T_w_o`` (4, 4) turned by ``angle_rad`` about the world axis ``axis`` through ``point``."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.asarray(axis, float) * angle_rad).as_matrix()
    return make_T(R, point - R @ point) @ T_w_o


def nearest_turn(T_w_o: np.ndarray, free: FreeAxis, R_w_o_ref: np.ndarray) -> np.ndarray:
    """``T_w_o`` turned about ``free`` to the rotation nearest ``R_w_o_ref`` (3, 3): the angle
    maximising ``trace(R_ref^T R(angle) R)`` (Rodrigues' formula, closed form)."""
    k = free.axis
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    M = T_w_o[:3, :3] @ np.asarray(R_w_o_ref, float).T
    a, b = np.trace(Kx @ M), np.trace(Kx @ Kx @ M)
    return turned(T_w_o, k, free.point, float(np.arctan2(a, -b)))


def free_starts(
    T_w_o: np.ndarray, free: FreeAxis, R_w_o_ref: np.ndarray, centre: np.ndarray
) -> list[tuple[str, np.ndarray]]:
    """Starts ``[(origin, T_w_o)]``: ``T_w_o`` turned about ``free`` to the rotation nearest
    ``R_w_o_ref``, and the same after turning it upside down (180 deg about an axis across
    ``free`` through the point of its axis nearest ``centre`` (3,), the visible points'
    centroid): a body seen from its side matches its own flip too."""
    k = free.axis
    foot = free.point + k * np.dot(np.asarray(centre, float) - free.point, k)
    across = np.cross(k, centre - foot)
    if np.linalg.norm(across) < 1e-9:
        across = np.cross(k, np.eye(3)[int(np.argmin(np.abs(k)))])
    flipped = turned(T_w_o, across / np.linalg.norm(across), foot, np.pi)
    return [
        ("free:turn", nearest_turn(T_w_o, free, R_w_o_ref)),
        ("free:flip", nearest_turn(flipped, free, R_w_o_ref)),
    ]
