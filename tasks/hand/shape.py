"""Per-subject hand shape: 20 per-bone length factors and their anatomical prior.

The identity of a hand beyond its size is ``bone_scale``, one length factor per bone of the
skeleton (``hand.model.SKELETON`` order: per finger the wrist-to-base vector, i.e. the palm's
proportions, then the three segments), on top of the model's global ``scale``: a bone is
``scale * bone_scale[k] * TEMPLATE_BONE_LENGTHS_M[k]`` long. Per-bone factors rather than a
low-dimensional basis: the only data that could fit a basis here are the rig's own hands (a
basis learned from them would be the rig's distribution, not people's), the SfM joints observe
every bone length directly, and a correlated Gaussian prior over all 20 does what a basis
does (it ties the bones of a finger together and shrinks what the joints leave open) without
forbidding a real hand's odd bone.

The prior (``docs/hand_shape.md`` gives the sources and the numbers) is a zero-mean Gaussian
over ``log(bone_scale)``: the hand's proportions relative to the template (Buryanov & Kotiuk
2010 means) given its size (the size is ``scale``'s, so the prior pulls the factors' common
mode to 1 and the scale takes the size). Its covariance is a finger term (the three segments
of a finger lengthen together, SD ``FINGER_SD``) plus an independent term per bone
(``BONE_SD``). ``prior_residuals`` whitens it (``r = L^-1 log b`` with ``L L^T`` the
covariance; ``|r|^2`` is minus twice the log prior up to a constant) for least-squares solvers;
``check_shape`` says whether a shape is one a human hand has.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graspcap.tasks.hand.model import FINGERS, TEMPLATE_BONE_LENGTHS_M, check_bone_scale

# scipy: imported where used, so that importing the stage table stays cheap

SHAPE_VERSION = "hand_shape/1"
N_BONES = 20
BONE_NAMES: tuple[str, ...] = tuple(
    f"{finger}_{bone}"
    for finger, bones in zip(
        FINGERS,
        [("base", "metacarpal", "proximal", "distal")]
        + [("metacarpal", "proximal", "middle", "distal")] * 4,
        strict=True,
    )
    for bone in bones
)
"""Names of the 20 bones in ``SKELETON`` order. A finger's ``metacarpal`` is the wrist-to-MCP
keypoint vector (metacarpal and carpus); the thumb's ``base`` is wrist to CMC and its
``metacarpal`` CMC to MCP."""

BONE_SD = np.array([
    0.10, 0.08, 0.09, 0.10,  # thumb: base (wrist-CMC), metacarpal, proximal, distal
    0.04, 0.05, 0.06, 0.07,  # index: wrist-MCP, proximal, middle, distal
    0.04, 0.05, 0.06, 0.07,  # middle
    0.04, 0.05, 0.06, 0.07,  # ring
    0.05, 0.05, 0.06, 0.07,  # little
])  # fmt: skip
"""(20,) Independent SD of each bone's log length factor given the hand's size."""
BONE_SD.setflags(write=False)
FINGER_SD = 0.04
"""SD of the log length factor a finger's three segments share (a long finger)."""


def _covariance() -> np.ndarray:
    cov = np.diag(BONE_SD**2)
    for f in range(5):
        seg = slice(4 * f + 1, 4 * f + 4)
        cov[seg, seg] += FINGER_SD**2
    return cov


PRIOR_COVARIANCE: np.ndarray = _covariance()
"""(20, 20) Covariance of ``log(bone_scale)`` under the prior."""
PRIOR_COVARIANCE.setflags(write=False)
PRIOR_SQRT_INFORMATION: np.ndarray = np.linalg.inv(np.linalg.cholesky(PRIOR_COVARIANCE))
"""(20, 20) ``W`` with ``W^T W`` the prior's information: ``W @ log(bone_scale)`` are the
whitened prior residuals (lower triangular)."""
PRIOR_SQRT_INFORMATION.setflags(write=False)
MARGINAL_SD: np.ndarray = np.sqrt(np.diag(PRIOR_COVARIANCE))
"""(20,) SD of each bone's log length factor under the prior."""
MARGINAL_SD.setflags(write=False)

_ADJACENT = np.array([(4 * f + j, 4 * f + j + 1) for f in range(5) for j in (1, 2)])
_RATIO_SD = np.sqrt(PRIOR_COVARIANCE[_ADJACENT[:, 0], _ADJACENT[:, 0]]
                    + PRIOR_COVARIANCE[_ADJACENT[:, 1], _ADJACENT[:, 1]]
                    - 2 * PRIOR_COVARIANCE[_ADJACENT[:, 0], _ADJACENT[:, 1]])


def prior_residuals(bone_scale: np.ndarray) -> np.ndarray:
    """(20,) whitened prior residuals of a shape (``PRIOR_SQRT_INFORMATION @ log b``): unit
    variance each under the prior, zero for the template. Add them to a least squares (times
    the data's noise SD where its residuals are not whitened)."""
    return PRIOR_SQRT_INFORMATION @ np.log(check_bone_scale(bone_scale))


def prior_residuals_log(log_bone_scale: np.ndarray) -> np.ndarray:
    """(..., 20) whitened prior residuals for ``log(bone_scale)`` (..., 20) (linear: the
    Jacobian is ``PRIOR_SQRT_INFORMATION``); batched."""
    return np.asarray(log_bone_scale, dtype=float) @ PRIOR_SQRT_INFORMATION.T


def prior_jacobian(bone_scale: np.ndarray) -> np.ndarray:
    """(20, 20) Jacobian of :func:`prior_residuals` with respect to ``bone_scale``."""
    return PRIOR_SQRT_INFORMATION / check_bone_scale(bone_scale)[None, :]


def bone_lengths_m(scale: float, bone_scale: np.ndarray | None = None) -> np.ndarray:
    """(20,) bone lengths in metres (``SKELETON`` order) of a hand of ``scale`` and shape."""
    return float(scale) * check_bone_scale(bone_scale) * TEMPLATE_BONE_LENGTHS_M


def bone_scale_from_lengths(lengths_m: np.ndarray, scale: float) -> np.ndarray:
    """(20,) the ``bone_scale`` of a hand of ``scale`` whose bones are ``lengths_m`` (20,)
    metres long (the catalog's ``hand_shape`` back into the model's parameters)."""
    lengths = np.asarray(lengths_m, dtype=float)
    if lengths.shape != (N_BONES,) or not np.all(np.isfinite(lengths)) or np.any(lengths <= 0):
        raise ValueError(f"bone lengths must be 20 positive finite metres, got {lengths!r}")
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"scale must be positive and finite, got {scale!r}")
    return lengths / (float(scale) * TEMPLATE_BONE_LENGTHS_M)


@dataclass(frozen=True)
class ShapeCheck:
    """Whether a shape is one a human hand has.

    mahalanobis : float
        ``|prior_residuals|``; chi-square with 20 degrees of freedom under the prior.
    z_bone : (20,) float
        Each bone's log factor in marginal SDs.
    z_ratio : (10,) float
        Each finger's proximal/middle and middle/distal segment ratio (thumb: metacarpal/
        proximal, proximal/distal) in SDs of the prior's log ratio.
    reasons : tuple[str, ...]
        What is out of range (empty: plausible).
    """

    mahalanobis: float
    z_bone: np.ndarray
    z_ratio: np.ndarray
    reasons: tuple[str, ...]

    @property
    def plausible(self) -> bool:
        return not self.reasons


def check_shape(bone_scale: np.ndarray, max_z: float = 4.0, p_max: float = 0.999) -> ShapeCheck:
    """Check a shape against the prior: every bone and every adjacent-segment ratio within
    ``max_z`` SDs, and the whole shape within the prior's ``p_max`` quantile (chi-square, 20
    degrees of freedom)."""
    from scipy.stats import chi2

    log_b = np.log(check_bone_scale(bone_scale))
    r = float(np.linalg.norm(PRIOR_SQRT_INFORMATION @ log_b))
    z_bone = log_b / MARGINAL_SD
    z_ratio = (log_b[_ADJACENT[:, 0]] - log_b[_ADJACENT[:, 1]]) / _RATIO_SD
    reasons = [f"{BONE_NAMES[k]} is {np.exp(log_b[k]):.2f} x the template's length "
               f"({z_bone[k]:+.1f} SD)" for k in np.flatnonzero(np.abs(z_bone) > max_z)]
    reasons += [f"{BONE_NAMES[a]}/{BONE_NAMES[b].split('_')[1]} ratio is "
                f"{np.exp(log_b[a] - log_b[b]):.2f} x the template's ({z:+.1f} SD)"
                for (a, b), z in zip(_ADJACENT, z_ratio, strict=True) if abs(z) > max_z]
    limit = float(np.sqrt(chi2.ppf(p_max, N_BONES)))
    if r > limit:
        reasons.append(f"the proportions are {r:.1f} from the template in the prior's SDs "
                       f"(a hand lies within {limit:.1f} with probability {p_max})")
    return ShapeCheck(r, z_bone, z_ratio, tuple(reasons))


__all__ = [
    "BONE_NAMES", "BONE_SD", "FINGER_SD", "MARGINAL_SD", "N_BONES", "PRIOR_COVARIANCE",
    "PRIOR_SQRT_INFORMATION", "SHAPE_VERSION", "ShapeCheck", "bone_lengths_m",
    "bone_scale_from_lengths", "check_shape", "prior_jacobian", "prior_residuals",
    "prior_residuals_log",
]  # fmt: skip
