"""The object's pose in the hand's world from every steady frame whose depth registered the
object (``estimate_adjustment``).

After the steady onset the hand and the object are one rigid body, so the object's pose in the
hand's world, ``T_w_o``, is one constant for the whole grasp. ``estimate_adjustment`` registers
it in the first steady frame (or a few, fused with stage 2's cameras), so one frame's camera
error moves it whole, and the onset is often detected a frame or two early, while the object
still settles. Every steady frame where the object was tracked in its own depth
(:mod:`track_object`) measures it again through that frame's stage 2 camera,
``T_w_c[i] @ T_c_o[i]``; their robust mean averages the cameras' frame-to-frame errors out.

That pose is what the grasp is built on: the refined hand sits in the object frame through it,
and ``propagate_poses`` defines each tracked frame's camera as ``T_w_o @ inv(T_c_o[i])``, so the
hand in a tracked frame is exactly as wrong as ``T_w_o``. On tuning seeds (real-detector
[9700, i] i<6, ``docs/benchmarks.md``, session 12) the first frame's ``T_w_o`` put the hand in
the tracked frames 19.9 and 12.4 mm off ([9700, 1], [9700, 4]); with this mean, 8.7 and 6.6 mm.

**Over every registered frame, not the tracked ones alone** (``estimate_adjustment/22``). A
tracked frame's delivered camera is ``T_w_o @ inv(T_c_o[i])``, an untracked one keeps stage 2's,
so ``T_w_o`` is the reference both kinds share. The gain test tracks exactly the frames where
stage 2's camera is wrong, so a mean over them alone carries their cameras' error, and every
untracked frame then disagrees with the tracked ones by it. A frame the gain test left
untracked was still registered in its own depth (``ObjectTracking.registered``: a candidate
the depth agrees with, only not a clear improvement on the propagated pose), and through its
stage 2 camera, the one it delivers, it measures ``T_w_o`` too; the mean over all of them is
the pose that agrees with the kept cameras as well as the replaced ones. Frames where no
candidate agreed with the depth stay out, so a wrong first pose is still replaced (wild
[22921, 1] mug, first pose 9.4 deg off: delivered cameras 1.66 deg either way; [80625, 3]
carton 11.69 / aligned 0.40 either way; a mean with the untracked frames' propagated poses
instead: 3.18 deg, aligned 9.93). On tuning seeds (``docs/benchmarks.md``, session 15),
delivered cameras ``camera_rot_deg`` tracked-only mean -> this: wild [22921, 4] can 1.51 -> 0.83
(stage 2 0.70), [82664, 1] bulb 0.54 -> 0.38, [82664, 3] 1.23 -> 1.20, [80625, 11] mug 2.96 ->
2.85 (per-frame object 5.41 -> 4.42 deg); real-detector [82100, 3] 0.46 -> 0.41; realistic
[9400, 1] 0.89 -> 0.85, the others unchanged.

The mean: chordal mean rotation and median object centre, then the frames whose pose is more
than ``outlier_factor`` median deviations from it (rotation, or the object centre's distance)
dropped once and the mean taken again. Frames still settling after an early onset, and a frame
tracked onto the wrong surface, are those outliers. Fewer than ``min_frames`` tracked frames:
the first frame's pose stands.

Pure numpy and scipy; no Prefect.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.geometry import rotation_error_deg

if TYPE_CHECKING:
    from graspcap.tasks.object_pose.track_object import ObjectTracking

# scipy: imported where used, so that importing the stage table stays cheap


class TrackedAverageConfig(StageConfig):
    """``T_w_o`` as the mean over the registered steady frames (``estimate_adjustment``)."""

    enabled: bool = True
    """Replace the first frame's ``T_w_o`` by the mean over the frames; False keeps it
    (``estimate_adjustment/17``)."""
    frames: Literal["registered", "tracked"] = "registered"
    """The frames measured: every frame whose depth registered the object, tracked or left
    with stage 2's camera by the gain test (``ObjectTracking.registered``), or the tracked
    ones alone (``estimate_adjustment/21``: their mean carried the error of the cameras the
    gain test replaced, and the kept cameras disagreed with it; wild [22921, 4] delivered
    cameras 1.51 deg against 0.83 over the registered frames)."""
    min_frames: int = 5
    """Fewest frames (after the outliers are dropped) for a mean."""
    outlier_factor: float = 3.0
    """A frame further from the first mean than this many median deviations (rotation, or the
    object centre's distance) is dropped before the second."""
    min_deviation_deg: float = 1.0
    """Floor of the median rotation deviation in that test (tracked frames that agree to a
    fraction of a degree must not drop a frame 1 deg away)."""
    min_deviation_m: float = 0.003
    """Floor of the median centre deviation in that test."""
    retrack_deg: float = 2.0
    """Where the mean turns the object more than this from the pose the tracking started from
    (``estimate_adjustment``'s first-frame pose), every frame is tracked again from the pose
    the mean propagates, the mean kept. The frames the gain test leaves untracked deliver that
    pose, so it is the one a tracked pose must beat; the first pass judged them against the
    first-frame pose, and where that was far off, a pose ICP left half way beat it (tuning
    real-detector ``[52033, 9]``, a carton: the first pose 13 deg off, frames 18-19 and 43-47
    tracked 6.6-7.7 deg short, delivered 5.7-6.9 deg off where stage 2 was 0.1-0.7 deg).
    Averaging the second pass again was tried and not kept (``docs/benchmarks.md``, session
    15). 0: never."""


DEFAULT = TrackedAverageConfig()


@dataclass(frozen=True)
class TrackedAverage:
    """The mean of the tracked frames' object poses in the world.

    Attributes
    ----------
    T_w_o : (4, 4) float or None
        The mean; None where there were too few frames (``reason`` says why).
    frames : int
        Frames in the mean (after the outliers are dropped).
    dropped : int
        Frames dropped as outliers.
    spread_deg, spread_m : float
        Median rotation and object-centre deviation of the kept frames from the mean.
    reason : str or None
        Why there is no mean.
    """

    T_w_o: np.ndarray | None
    frames: int
    dropped: int
    spread_deg: float
    spread_m: float
    reason: str | None = None


def _mean(T: np.ndarray, centre_o: np.ndarray) -> np.ndarray:
    """(4, 4) chordal mean rotation of ``T`` (k, 4, 4) and the median of its object centres."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix(T[:, :3, :3]).mean().as_matrix()
    centre = np.median(T[:, :3, :3] @ centre_o + T[:, :3, 3], axis=0)
    out[:3, 3] = centre - out[:3, :3] @ centre_o
    return out


def _deviations(T: np.ndarray, mean: np.ndarray, centre_o: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    rot = np.array([rotation_error_deg(R, mean[:3, :3]) for R in T[:, :3, :3]])
    centres = T[:, :3, :3] @ centre_o + T[:, :3, 3]
    return rot, np.linalg.norm(centres - (mean[:3, :3] @ centre_o + mean[:3, 3]), axis=1)


def average_object_pose(
    T_w_c: np.ndarray,
    T_c_o: np.ndarray,
    tracked: np.ndarray,
    centre_o: np.ndarray,
    config: TrackedAverageConfig = DEFAULT,
) -> TrackedAverage:
    """The object's pose in the world as the robust mean over the tracked frames.

    Parameters
    ----------
    T_w_c : (m, 4, 4) float, the steady frames' stage 2 cameras.
    T_c_o : (m, 4, 4) float, the object in each frame's camera (``ObjectTracking.T_c_o``).
    tracked : (m,) bool, frames whose ``T_c_o`` the depth gave.
    centre_o : (3,) float, the object's centre in its own frame (the deviations are of it).
    """
    rows = np.flatnonzero(np.asarray(tracked, bool))
    if len(rows) < config.min_frames:
        return TrackedAverage(None, len(rows), 0, np.nan, np.nan,
                              f"{len(rows)} tracked frames, fewer than {config.min_frames}")
    centre_o = np.asarray(centre_o, float)
    T = np.einsum("mij,mjk->mik", np.asarray(T_w_c, float)[rows], np.asarray(T_c_o, float)[rows])
    mean = _mean(T, centre_o)
    rot, dist = _deviations(T, mean, centre_o)
    keep = ((rot <= config.outlier_factor * max(np.median(rot), config.min_deviation_deg))
            & (dist <= config.outlier_factor * max(np.median(dist), config.min_deviation_m)))
    if keep.sum() < config.min_frames:
        return TrackedAverage(None, int(keep.sum()), int((~keep).sum()), np.nan, np.nan,
                              f"{int(keep.sum())} tracked frames agree, fewer than "
                              f"{config.min_frames}")
    mean = _mean(T[keep], centre_o)
    rot, dist = _deviations(T[keep], mean, centre_o)
    return TrackedAverage(mean, int(keep.sum()), int((~keep).sum()), float(np.median(rot)),
                          float(np.median(dist)))


def average_tracking(
    T_w_c: np.ndarray,
    tracking: ObjectTracking,
    centre_o: np.ndarray,
    config: TrackedAverageConfig = DEFAULT,
) -> TrackedAverage:
    """:func:`average_object_pose` over the frames ``config.frames`` names: every registered
    frame at its registered pose, or the tracked ones at their tracked pose (also where the
    tracking has no registrations).

    Parameters
    ----------
    T_w_c : (m, 4, 4) float, the steady frames' stage 2 cameras.
    tracking : the object tracked in the same frames (:func:`track_object.track_object`).
    centre_o : (3,) float, the object's centre in its own frame.
    """
    if config.frames == "registered" and tracking.registered is not None:
        return average_object_pose(T_w_c, tracking.T_c_o_registered, tracking.registered,
                                   centre_o, config)
    return average_object_pose(T_w_c, tracking.T_c_o, tracking.tracked, centre_o, config)


__all__ = ["TrackedAverage", "TrackedAverageConfig", "average_object_pose", "average_tracking"]
