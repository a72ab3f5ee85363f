"""Inverse-kinematics helpers for the 20-DoF hand: closed-form finger angles, batched Jacobians.

Every finger of ``HandModel`` is a planar chain: the abduction turns the plane that holds the
finger's bones about the base frame's palmar axis, and the three flexions bend the bones
inside that plane. So the angles of one finger can be read off its three moving keypoints in
closed form (azimuth of the plane, then elevations of the bones), which is the start point of
the bounded least squares in ``fit_hand``. The base frames are measured from the model's
public API (finite differences at the rest pose), so they stay right if the model changes.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from graspcap.tasks.hand.model import HandModel, HandSide

N_FINGERS = 5
MOVING: tuple[tuple[int, int, int], ...] = tuple(
    (4 * f + 2, 4 * f + 3, 4 * f + 4) for f in range(N_FINGERS)
)
"""Keypoints that finger f's four angles move (its base keypoint 4f+1 is rigid)."""


@dataclass(frozen=True)
class FingerFrames:
    """Per finger base position ``origin_p`` (5, 3) and axes ``axes_p`` (5, 3, 3) (columns:
    lateral x towards the thumb side, y along the rest bone, z palmar), palm frame, scale 1."""

    origin_p: np.ndarray
    axes_p: np.ndarray


@cache
def finger_frames(side: HandSide) -> FingerFrames:
    """Measure each finger's base frame from the model: y the rest direction of the first bone,
    x its motion under abduction, z its motion under the first flexion."""
    model = HandModel(side)
    rest = model.rest_angles()
    h = 1e-5
    steps = np.zeros((4 * N_FINGERS, 20))  # +-abduction, +-first flexion per finger
    for f in range(N_FINGERS):
        steps[4 * f : 4 * f + 2, 4 * f] = (h, -h)
        steps[4 * f + 2 : 4 * f + 4, 4 * f + 1] = (h, -h)
    kp = model.keypoints_batch(rest + steps)
    rest_kp = model.keypoints(rest)
    origin = np.empty((N_FINGERS, 3))
    axes = np.empty((N_FINGERS, 3, 3))
    for f in range(N_FINGERS):
        base, first = 4 * f + 1, 4 * f + 2
        y = rest_kp[first] - rest_kp[base]
        x = kp[4 * f, first] - kp[4 * f + 1, first]
        z = kp[4 * f + 2, first] - kp[4 * f + 3, first]
        frame = np.stack([v / np.linalg.norm(v) for v in (x, y, z)], axis=1)
        u, _, vt = np.linalg.svd(frame)  # nearest orthonormal frame (exact up to ~1e-10)
        origin[f], axes[f] = rest_kp[base], u @ vt
    origin.setflags(write=False)
    axes.setflags(write=False)
    return FingerFrames(origin_p=origin, axes_p=axes)


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def closed_form_angles(
    side: HandSide, targets_p: np.ndarray, usable: np.ndarray, fallback: np.ndarray
) -> np.ndarray:
    """Finger angles (20,) that put each finger's bones along the target bones, unclipped.

    Parameters
    ----------
    targets_p : (21, 3) float
        Target keypoints in the palm frame at scale 1.
    usable : (21,) bool
        Keypoints that may be used; a finger with an unusable moving keypoint (or whose bones
        are all parallel to the palm normal, leaving the abduction open) keeps ``fallback``.
    fallback : (20,) float
        Angles for what cannot be read off the targets.
    """
    frames = finger_frames(side)
    out = np.array(fallback, dtype=float)
    for f, moving in enumerate(MOVING):
        if not usable[list(moving)].all():
            continue
        chain = np.concatenate([frames.origin_p[f][None], targets_p[list(moving)]])
        bones = np.diff(chain, axis=0) @ frames.axes_p[f]  # (3, 3) in the base frame
        flat = bones[:, :2]
        scatter = flat.T @ flat
        evals, evecs = np.linalg.eigh(scatter)
        if evals[1] < 1e-12:  # every bone along the palmar axis: abduction undetermined
            abduction = out[4 * f]
        else:
            u = evecs[:, 1] if evecs[1, 1] >= 0 else -evecs[:, 1]  # |abduction| < 90 deg
            abduction = np.arctan2(u[0], u[1])
        along = bones[:, 0] * np.sin(abduction) + bones[:, 1] * np.cos(abduction)
        phi = np.arctan2(bones[:, 2], along)  # accumulated flexion of each bone
        out[4 * f] = abduction
        out[4 * f + 1] = phi[0]
        out[4 * f + 2 : 4 * f + 4] = _wrap(np.diff(phi))
    return out


def central_jacobian(batch_fun, x: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Jacobian (r, n) of ``batch_fun`` ((b, n) -> (b, r)) at ``x`` (n,) by central differences,
    all 2n evaluations in one batched call."""
    n = len(x)
    X = np.repeat(x[None], 2 * n, axis=0)
    idx = np.arange(n)
    X[idx, idx] += step
    X[n + idx, idx] -= step
    R = batch_fun(X)
    return (R[:n] - R[n:]).T / (2 * step)


__all__ = ["MOVING", "FingerFrames", "central_jacobian", "closed_form_angles", "finger_frames"]
