"""The operator's steady-phase motion: hand and object turned together in front of the camera.

Structure from motion of the static hand (``reconstruct_hand``) needs the hand to turn
relative to the camera; a real capture protocol instructs the participant to turn it by a
stated minimum while keeping it in view and above the table, lifting the object as it
turns. The rig does the same: it draws smooth random motions until one turns the hand by
at least :data:`MIN_STEADY_TURN_DEG` over the steady frames while every joint stays in the
image and the hand and object stay above the table (lifted by up to :data:`MAX_LIFT_M`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.spatial.transform import Rotation

from graspcap.synth.config import CaptureConfig, SynthConfig
from graspcap.synth.rig import smoothstep
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import make_T

MIN_STEADY_TURN_DEG = 30.0
"""Smallest total turn of the hand relative to the camera over the steady frames (the
largest rotation of any steady frame's pose away from the first steady frame's), as a
protocol would instruct the operator. ``reconstruct_hand`` rejects a hand turned less than
12 deg and names the little motion below 25 deg; sessions turned 23-53 deg solve to
0.1-0.4 deg per camera. Every generated session meets this (``synth/2``)."""

MAX_LIFT_M = 0.08
"""Highest the operator lifts hand and object (along the table normal) while turning them,
so that a turned object held just above the table does not dip into it."""

TABLE_CLEARANCE_M = 0.012
"""Height above the table the lift aims for (the table check itself needs 8 mm)."""

MOTION_DRAWS = 40
"""Random motions drawn before the rig gives up on a session (measured on 53 placements:
at least 60 % of the draws meet every condition, so 40 draws essentially never fail)."""

SCALE_STEPS = 12
"""Times a drawn motion is shrunk by 0.75 to stay in view before the next draw."""


@dataclass(frozen=True)
class Motion:
    """Smooth rigid motion of the hand and object in the camera frame after the steady frame.

    ``rotvec(tau)`` and ``shift(tau)`` are sums of sines (zero at tau = 0), so
    the motion starts at the steady pose; ``centre`` is the rotation centre (m).
    """

    axes: np.ndarray  # (3, 3) unit rotation axes
    amplitudes_rad: np.ndarray  # (3,)
    freq: np.ndarray  # (3,) cycles over the video
    shift_dirs: np.ndarray  # (2, 3) unit translation directions
    shift_m: np.ndarray  # (2,)
    shift_freq: np.ndarray  # (2,)
    centre: np.ndarray  # (3,)

    def M(self, tau: float) -> np.ndarray:
        """(4, 4) motion at normalised time ``tau`` in [0, 1]; identity at 0."""
        rotvec = (self.amplitudes_rad * np.sin(2 * np.pi * self.freq * tau)) @ self.axes
        shift = (self.shift_m * np.sin(2 * np.pi * self.shift_freq * tau)) @ self.shift_dirs
        R = Rotation.from_rotvec(rotvec).as_matrix()
        return make_T(R, self.centre + shift - R @ self.centre)

    def scaled(self, factor: float) -> Motion:
        """The same motion with rotation and translation amplitudes times ``factor``."""
        return Motion(self.axes, self.amplitudes_rad * factor, self.freq, self.shift_dirs,
                      self.shift_m * factor, self.shift_freq, self.centre)


def random_motion(centre: np.ndarray, cfg: SynthConfig, rng: np.random.Generator) -> Motion:
    """A motion reaching up to ``cfg.motion_rotation_deg`` about varied axes, a few cm of shift."""
    axes = rng.normal(size=(3, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    total = np.radians(cfg.motion_rotation_deg) * rng.uniform(0.6, 1.0)
    amplitudes = total * rng.dirichlet(np.ones(3) * 2.0) * 1.6
    dirs = rng.normal(size=(2, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return Motion(axes, np.minimum(amplitudes, np.radians(cfg.motion_rotation_deg)),
                  rng.uniform(0.4, 1.2, 3), dirs,
                  cfg.motion_translation_m * rng.uniform(0.3, 0.6, 2), rng.uniform(0.3, 1.0, 2),
                  np.asarray(centre, float))


def turn_deg(Ms: np.ndarray) -> np.ndarray:
    """Rotation angle (n,) in degrees of each motion (n, 4, 4) away from the identity."""
    R = np.asarray(Ms)[:, :3, :3]
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)))


def lift(Ms: np.ndarray, heights_m: np.ndarray, up: np.ndarray,
         max_lift_m: float = MAX_LIFT_M) -> np.ndarray | None:
    """The motions lifted along ``up`` in proportion to each one's turn, just enough to bring
    the lowest point to ``TABLE_CLEARANCE_M``; None when that needs more than ``max_lift_m``.

    Ms : (n, 4, 4) motions; heights_m : (n,) lowest point above the table under each.
    up : (3,) unit table normal in the camera frame.
    """
    turn = turn_deg(Ms)
    share = turn / max(float(turn.max()), 1e-9)
    deficit = TABLE_CLEARANCE_M - np.asarray(heights_m)
    low = deficit > 0
    if not low.any():
        return np.asarray(Ms)
    if np.any(share[low] <= 0):
        return None  # too low without any turn: a lift proportional to the turn cannot help
    height = float(np.max(deficit[low] / share[low]))
    if height > max_lift_m:
        return None
    out = np.array(Ms, dtype=float)
    out[:, :3, 3] += height * share[:, None] * np.asarray(up, float)
    return out


def steady_motion(
    centre: np.ndarray,
    n_frames: int,
    cfg: SynthConfig,
    rng: np.random.Generator,
    *,
    in_view: Callable[[np.ndarray], bool],
    heights_m: Callable[[np.ndarray], float],
    up: np.ndarray,
) -> np.ndarray:
    """Motions (n_frames, 4, 4) of hand and object (camera frame) for the steady frames.

    The first frame's is the identity; the largest turn is at least ``MIN_STEADY_TURN_DEG``
    and at most ``cfg.motion_rotation_deg``. A drawn motion is shrunk (x 0.75) while it
    leaves the view or cannot be lifted clear of the table, and redrawn once it turns too
    little.

    centre : (3,) rotation centre (the palm) in the camera frame.
    in_view(M (4, 4)) : whether every joint stays in the image under M.
    heights_m(M (4, 4)) : lowest point of hand and object above the table under M.
    up : (3,) table normal in the camera frame.
    """
    taus = np.arange(n_frames) / max(n_frames - 1, 1)
    for _ in range(MOTION_DRAWS):
        motion = random_motion(centre, cfg, rng)
        for _ in range(SCALE_STEPS):
            Ms = np.stack([motion.M(t) for t in taus])
            worst = float(turn_deg(Ms).max())
            if worst < MIN_STEADY_TURN_DEG:
                break  # shrinking only turns it less: draw another
            if worst <= cfg.motion_rotation_deg + 1e-6:
                lifted = lift(Ms, np.array([heights_m(M) for M in Ms]), up)
                if lifted is not None and all(in_view(M) for M in lifted):
                    return lifted
            motion = motion.scaled(0.75)
    raise StageError(
        "synth", f"no motion turns the hand >= {MIN_STEADY_TURN_DEG:g} deg in view, above the "
        f"table, in {MOTION_DRAWS} draws",
    )


def _time_warp(n_frames: int, irregularity: float, rng: np.random.Generator) -> np.ndarray:
    """Normalised times (n,) from 0 to 1 at an irregular, always positive speed."""
    if n_frames < 2:
        return np.zeros(n_frames)
    raw = rng.uniform(-1.0, 1.0, n_frames - 1)
    speed = 1.0 + irregularity * uniform_filter1d(raw, 3, mode="nearest") * 1.5
    speed = np.clip(speed, 0.15, None)
    return np.concatenate([[0.0], np.cumsum(speed)]) / speed.sum()


def wild_motion(
    centre: np.ndarray,
    n_frames: int,
    cap: CaptureConfig,
    rng: np.random.Generator,
    *,
    in_view: Callable[[np.ndarray], bool],
    heights_m: Callable[[np.ndarray], float],
    up: np.ndarray,
) -> tuple[np.ndarray, float]:
    """Motions (n_frames, 4, 4) of hand and object for the steady frames, and the total turn
    aimed at (deg): a turn about one random axis (either way) by ``a``, then back past the
    start by ``total - a``, at an irregular speed, with a few degrees of wobble about the
    other axes and up to ``cap.translation_m`` of translation per axis.

    The total is drawn in ``cap.rotation_deg``; a draw that leaves the view or cannot be
    lifted clear of the table (by up to ``cap.max_lift_m``) first loses translation, then
    another axis is drawn, and every 10 draws the total shrinks by 0.85 (never below the
    range's low end).
    """
    lo, hi = cap.rotation_deg
    total = rng.uniform(lo, hi)
    for draw in range(MOTION_DRAWS * 2):
        if draw and draw % 10 == 0:
            total = max(lo, total * 0.85)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        first = total * rng.uniform(0.5, 1.0) * rng.choice([-1.0, 1.0])
        back = first - np.sign(first) * total  # ends at first - total (one sign further)
        turn_at = rng.uniform(0.35, 0.75)
        taus = _time_warp(n_frames, cap.speed_irregularity, rng)
        wobble_axes = rng.normal(size=(2, 3))
        wobble_axes -= (wobble_axes @ axis)[:, None] * axis
        wobble = rng.uniform(-3.0, 3.0, 2)
        shift_dir = rng.uniform(-1.0, 1.0, 3) * cap.translation_m
        shift_freq = rng.uniform(0.3, 1.0, 3)
        for shrink in (1.0, 0.6, 0.3, 0.0):
            Ms = np.empty((n_frames, 4, 4))
            for i, tau in enumerate(taus):
                if tau <= turn_at:
                    angle = first * smoothstep(tau / turn_at)
                else:
                    angle = first + (back - first) * smoothstep((tau - turn_at) / (1 - turn_at))
                rotvec = np.radians(angle) * axis + np.radians(
                    (wobble * np.sin(np.pi * tau)) @ wobble_axes)
                shift = shrink * shift_dir * np.sin(np.pi * shift_freq * tau)
                R = Rotation.from_rotvec(rotvec).as_matrix()
                Ms[i] = make_T(R, centre + shift - R @ centre)
            lifted = lift(Ms, np.array([heights_m(M) for M in Ms]), up, cap.max_lift_m)
            if lifted is not None and all(in_view(M) for M in lifted):
                return lifted, float(total)
    raise StageError("synth", f"no motion turning the hand {lo:g}-{hi:g} deg stays in view and "
                     f"above the table in {2 * MOTION_DRAWS} draws")

