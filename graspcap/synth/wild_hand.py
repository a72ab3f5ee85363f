"""The wild rig's own hand: a kinematic structure and surface the pipeline's model lacks.

The pipeline fits :class:`graspcap.tasks.hand.model.HandModel` (GraspIt's 20-DoF chain,
fixed knuckles, one global scale, capsules centred on the joints). A rig whose hands are
that model with other numbers makes every fit look better than it is, so the wild
profile draws hands from this separate model instead:

- every bone has its own length (metacarpals included), the palm its own width and
  arch, the fingers their own thickness, the thumb its own base position and opposition;
- the MCP flexion axes are twisted about the bone (fingers converge as they close),
  each phalanx deviates sideways a little, the PIP and DIP axes inherit part of the twist;
- the thumb's CMC turns about two non-orthogonal axes, with a conjunct axial rotation
  (opposition grows as the thumb closes);
- the ring and little metacarpals flex as the fingers close (palm cupping), so their
  knuckles move in the palm;
- the surface is per-segment capsules set off the bone axis towards the back of the
  finger, fingertip keypoints at the end of the finger (not at a sphere's centre), and a
  palm in two parts (the ulnar part moves with the cupping).

It is driven by the same 20 control angles as the pipeline's model (per finger an
abduction and three flexions, in ``ANGLE_NAMES`` order) so that the rig's grasp planner
can close it, and it gives the contract's 21 OpenPose keypoints. Right hands only; the
palm frame follows the model's convention (origin at the wrist, +y towards the middle
MCP, +z palmar, x towards the thumb).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graspcap.synth.config import WildHandConfig
from graspcap.tasks.hand.mesh import sphere_hull
from graspcap.tasks.hand.model import HandMesh, HandSide

MODEL_VERSION = "wild_hand/1"
_EYE4 = np.eye(4)
_EYE4.setflags(write=False)

# --- template at size 1 (right hand, palm frame, metres); our own round numbers ---------

_BASE_M = np.array([
    [0.022, 0.028, 0.010],  # thumb CMC
    [0.025, 0.088, 0.000],  # index MCP
    [0.000, 0.094, 0.000],  # middle MCP (+y)
    [-0.021, 0.087, 0.000],  # ring MCP
    [-0.042, 0.077, 0.000],  # little MCP
])  # fmt: skip
_CMC_M = np.array([  # where each metacarpal starts (its length scales from here)
    [0.010, 0.012, 0.004], [0.010, 0.014, 0.0], [0.0, 0.014, 0.0],
    [-0.008, 0.014, 0.0], [-0.016, 0.014, 0.0],
])  # fmt: skip
_LENGTH_M = np.array([
    [0.046, 0.031, 0.026],  # thumb: metacarpal, proximal, distal (to the tip of the finger)
    [0.040, 0.023, 0.021],  # index: proximal, middle, distal
    [0.045, 0.027, 0.022],
    [0.042, 0.026, 0.022],
    [0.033, 0.019, 0.020],
])  # fmt: skip
_RADIUS_M = np.array([
    [0.0115, 0.0105, 0.0092, 0.0082],  # thumb: CMC, MCP, IP, tip
    [0.0105, 0.0090, 0.0080, 0.0072],  # fingers: MCP, PIP, DIP, tip
    [0.0110, 0.0093, 0.0083, 0.0075],
    [0.0105, 0.0089, 0.0079, 0.0071],
    [0.0095, 0.0082, 0.0074, 0.0067],
])  # fmt: skip
_FAN_DEG = np.array([0.0, 5.0, 0.0, -6.0, -12.0])  # fingers' rest direction (thumb unused)
_SPREAD = np.array([0.0, 1.0, 0.0, -0.8, -1.6])  # share of the session's abduction per finger
_CUP_SHARE = np.array([0.0, 0.0, 0.0, 0.5, 1.0])  # metacarpal flexion with closure
_PALM_HALF_M = 0.014
_LIMITS_DEG = np.array([
    [[-15, 50], [-20, 55], [-10, 75], [-15, 85]],  # thumb: CMC 1, CMC 2, MCP, IP
    [[-15, 25], [-20, 90], [-5, 105], [-10, 85]],
    [[-12, 12], [-20, 90], [-5, 105], [-10, 85]],
    [[-20, 15], [-20, 90], [-5, 105], [-10, 85]],
    [[-35, 15], [-20, 90], [-5, 105], [-10, 85]],
], dtype=float)  # fmt: skip
_THUMB_AXIAL = 0.35  # conjunct axial rotation of the thumb metacarpal per radian of CMC motion

PALM_PARTS = (0, 1, 16)
"""Parts that make the palm side of the grip: radial palm, thumb metacarpal, ulnar palm."""


@dataclass(frozen=True)
class WildHandShape:
    """One hand's identity, at size 1 (``scale`` multiplies every length at posing).

    base_m (5, 3): thumb CMC and finger MCPs (uncupped); length_m (5, 3): phalanges
    (thumb: metacarpal, proximal, distal); radius_m (5, 4): skin radius at each joint and
    the tip; metacarpal (5,): length ratio of each metacarpal; twist_rad (5,): MCP axis
    twist; deviation_rad (5, 3): sideways deviation of each phalanx; opposition_rad,
    abduction_rad, arch_rad, capsule_offset: as in :class:`WildHandConfig`.
    """

    base_m: np.ndarray
    length_m: np.ndarray
    radius_m: np.ndarray
    metacarpal: np.ndarray
    twist_rad: np.ndarray
    deviation_rad: np.ndarray
    opposition_rad: float
    abduction_rad: float
    arch_rad: float
    capsule_offset: float

    @staticmethod
    def template() -> WildHandShape:
        """The template hand (every ratio 1, mid-range angles)."""
        return WildHandShape(_BASE_M.copy(), _LENGTH_M.copy(), _RADIUS_M.copy(), np.ones(5),
                             np.zeros(5), np.zeros((5, 3)), np.radians(60.0), 0.0,
                             np.radians(10.0), 0.1)

    @staticmethod
    def sample(cfg: WildHandConfig, rng: np.random.Generator) -> WildHandShape:
        """A random hand within ``cfg``'s ranges (size excluded: that is the scale)."""
        width = rng.uniform(*cfg.palm_width)
        metacarpal = rng.uniform(*cfg.bone_length, 5)
        base = _CMC_M + metacarpal[:, None] * (_BASE_M - _CMC_M)
        base[:, 0] *= width
        base[0] += rng.uniform(-1, 1, 3) * cfg.thumb_base_shift_m
        arch = np.radians(rng.uniform(*cfg.palm_arch_deg))
        base[1:, 2] += np.abs(base[1:, 0] - base[2, 0]) * np.tan(arch) * 0.6
        base[2, 0] = 0.0  # the middle MCP stays on +y (the palm frame's definition)
        thick = rng.uniform(*cfg.thickness) * rng.uniform(0.95, 1.05, (5, 4))
        return WildHandShape(
            base_m=base,
            length_m=_LENGTH_M * rng.uniform(*cfg.bone_length, (5, 3)),
            radius_m=_RADIUS_M * thick,
            metacarpal=metacarpal,
            twist_rad=np.radians(rng.uniform(*cfg.mcp_twist_deg, 5)),
            deviation_rad=np.radians(rng.uniform(-3.0, 3.0, (5, 3))),
            opposition_rad=float(np.radians(rng.uniform(*cfg.thumb_opposition_deg))),
            abduction_rad=float(np.radians(rng.uniform(*cfg.abduction_deg))),
            arch_rad=float(arch),
            capsule_offset=float(rng.uniform(*cfg.capsule_offset)),
        )

    def bone_lengths_m(self) -> np.ndarray:
        """(20,) lengths at size 1 of the skeleton's bones (``SKELETON`` order, rest pose)."""
        kp = WildHand(self).keypoints(np.zeros(20))
        parents = (-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19)
        return np.array([np.linalg.norm(kp[k] - kp[p]) for k, p in enumerate(parents) if p >= 0])

    @staticmethod
    def from_json(data: dict) -> WildHandShape:
        """The shape :meth:`to_json` wrote (``truth.json``'s ``randomisation.hand_shape``)."""
        return WildHandShape(**{k: np.asarray(v, float) if isinstance(v, list) else float(v)
                                for k, v in data.items()})

    def to_json(self) -> dict:
        """Plain lists and numbers (written into the ground truth)."""
        return {k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else float(v))
                for k, v in self.__dict__.items()}


def _rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _frame(y: np.ndarray, z_hint: np.ndarray) -> np.ndarray:
    y = y / np.linalg.norm(y)
    z = z_hint - (z_hint @ y) * y
    z /= np.linalg.norm(z)
    return np.stack([np.cross(y, z), y, z], axis=1)


@dataclass(frozen=True)
class _Pose:
    """A posed hand in the palm frame at size 1: joints (5, 4, 3), segment rotations
    (5, 3, 3, 3), the ulnar palm's rotation and pivot."""

    joints: np.ndarray
    R: np.ndarray
    R_cup: np.ndarray
    pivot: np.ndarray


class WildHand:
    """A posable hand of one :class:`WildHandShape`, right side.

    The same interface as the pipeline's model where the rig needs it: ``keypoints``,
    ``mesh``, ``clip``, ``lower_rad`` / ``upper_rad``, ``rest_angles``; plus
    ``phalanx_capsules`` for the grasp planner's probes.
    """

    side = HandSide.RIGHT
    palm_parts = PALM_PARTS
    version = MODEL_VERSION

    def __init__(self, shape: WildHandShape):
        self.shape = shape
        self.lower_rad = np.radians(_LIMITS_DEG[:, :, 0].reshape(-1))
        self.upper_rad = np.radians(_LIMITS_DEG[:, :, 1].reshape(-1))
        self.palm_contact_p = np.array([-0.004, 0.05, _PALM_HALF_M * shape.radius_m[2, 0]
                                        / _RADIUS_M[2, 0]])
        self._templates = self._build_templates()

    # --- angles -------------------------------------------------------------------------

    def rest_angles(self) -> np.ndarray:
        """(20,) A flat, open hand."""
        return np.zeros(20)

    def clip(self, angles: np.ndarray) -> np.ndarray:
        """(20,) angles clipped into the joint limits."""
        return np.clip(np.asarray(angles, dtype=float), self.lower_rad, self.upper_rad)

    # --- kinematics ---------------------------------------------------------------------

    def _pose(self, angles: np.ndarray) -> _Pose:
        s = self.shape
        a = np.asarray(angles, float).reshape(5, 4)
        joints = np.empty((5, 4, 3))
        R = np.empty((5, 3, 3, 3))
        closure = np.clip(a[1:, 1:].sum() / np.radians(4 * 260.0), 0.0, 1.0)
        cup = s.arch_rad * closure
        pivot = np.array([-0.012, 0.012, 0.0])
        R_cup_little = _rot_y(cup)
        for f in range(5):
            if f == 0:
                R0 = _frame(np.array([0.55, 0.80, 0.22]),
                            np.array([-np.sin(s.opposition_rad), 0.0, np.cos(s.opposition_rad)]))
                base = s.base_m[0]
                n_abd = R0 @ np.array([0.25, 0.0, 1.0])
                R_cmc = _rodrigues(n_abd, -a[0, 0]) @ R0
                n_flex = R_cmc @ np.array([1.0, 0.0, -0.3])
                R1 = _rodrigues(n_flex, a[0, 1]) @ R_cmc
                R1 = R1 @ _rot_y(-_THUMB_AXIAL * (a[0, 0] + a[0, 1]))  # conjunct rotation
            else:
                c = _CUP_SHARE[f] * cup
                R_c = _rot_y(c)
                base = pivot + R_c @ (s.base_m[f] - pivot) if c else s.base_m[f].copy()
                roll = -np.sign(s.base_m[f, 0]) * s.arch_rad * 0.5 if f != 2 else 0.0
                R0 = R_c @ _rot_z(-np.radians(_FAN_DEG[f])) @ _rot_y(roll)
                abd = a[f, 0] + _SPREAD[f] * s.abduction_rad
                R1 = R0 @ _rot_z(-abd) @ _rodrigues(_twisted_x(s.twist_rad[f]), a[f, 1])
            R2 = R1 @ _rodrigues(_twisted_x(s.twist_rad[f] * 0.5), a[f, 2])
            R3 = R2 @ _rodrigues(_twisted_x(s.twist_rad[f] * 0.3), a[f, 3])
            joints[f, 0] = base
            for j, Rj in enumerate((R1, R2, R3)):
                d = s.deviation_rad[f, j]
                bone = s.length_m[f, j] * np.array([np.sin(d), np.cos(d), 0.0])
                joints[f, j + 1] = joints[f, j] + Rj @ bone
                R[f, j] = Rj
        return _Pose(joints, R, R_cup_little, pivot)

    def keypoints(self, angles: np.ndarray, T_w_p: np.ndarray = _EYE4,
                  scale: float = 1.0) -> np.ndarray:
        """(21, 3) OpenPose keypoints in the world (the contract's joint order)."""
        pose = self._pose(angles)
        kp = np.zeros((21, 3))
        kp[1:] = pose.joints.reshape(20, 3)
        return _to_world(kp, T_w_p, scale)

    def phalanx_capsules(self, angles: np.ndarray, T_w_p: np.ndarray = _EYE4,
                         scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                      np.ndarray]:
        """The 15 phalanx capsules (thumb metacarpal first) as sphere centres ``start``,
        ``end`` (5, 3, 3) in the world and radii ``r_start``, ``r_end`` (5, 3)."""
        pose = self._pose(angles)
        loc = self._capsule_local()
        start = np.einsum("fjab,fjb->fja", pose.R, loc[0]) + pose.joints[:, :3]
        end = np.einsum("fjab,fjb->fja", pose.R, loc[1]) + pose.joints[:, :3]
        r = self.shape.radius_m
        return (_to_world(start, T_w_p, scale), _to_world(end, T_w_p, scale),
                r[:, :3] * scale, r[:, 1:] * scale)

    # --- surface ------------------------------------------------------------------------

    def _capsule_local(self) -> np.ndarray:
        """(2, 5, 3, 3) capsule sphere centres in each segment's frame (start, end)."""
        s = self.shape
        out = np.zeros((2, 5, 3, 3))
        for f in range(5):
            for j in range(3):
                d = s.deviation_rad[f, j]
                bone = s.length_m[f, j] * np.array([np.sin(d), np.cos(d), 0.0])
                r0, r1 = s.radius_m[f, j], s.radius_m[f, j + 1]
                out[0, f, j] = [0.0, 0.0, -s.capsule_offset * r0]
                if j == 2:  # the fingertip keypoint is the end of the finger
                    out[1, f, j] = bone * (1 - 0.85 * r1 / np.linalg.norm(bone))
                else:
                    out[1, f, j] = bone
                out[1, f, j, 2] -= s.capsule_offset * r1
        return out

    def _palm_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Radial palm spheres (k, 4) and ulnar palm spheres (k, 4), uncupped, size 1."""
        s = self.shape
        t = s.radius_m[2, 0] / _RADIUS_M[2, 0]  # thickness factor
        w = (s.base_m[1, 0] - s.base_m[4, 0]) / (_BASE_M[1, 0] - _BASE_M[4, 0])
        h = _PALM_HALF_M * t
        radial = np.array([
            [0.0, 0.0, 0.0, 0.014 * t],
            [0.015 * w, 0.006, 0.0, 0.013 * t],
            [0.018 * w, 0.045, 0.002, h * 1.05],  # thenar
            [0.0, 0.055, 0.001, h],
            [*s.base_m[0], s.radius_m[0, 0]],
            [*s.base_m[1], s.radius_m[1, 0]],
            [*s.base_m[2], s.radius_m[2, 0]],
        ])  # fmt: skip
        ulnar = np.array([
            [-0.015 * w, 0.006, 0.0, 0.013 * t],
            [-0.028 * w, 0.045, 0.002, h],  # hypothenar
            [*s.base_m[3], s.radius_m[3, 0]],
            [*s.base_m[4], s.radius_m[4, 0]],
            [-0.006 * w, 0.06, 0.001, h],
        ])  # fmt: skip
        return radial, ulnar

    def _build_templates(self) -> HandMesh:
        """Parts in their own frames: 0 radial palm, 1-15 phalanges, 16 ulnar palm."""
        radial, ulnar = self._palm_spheres()
        loc = self._capsule_local()
        parts = [sphere_hull(radial[:, :3], radial[:, 3])]
        r = self.shape.radius_m
        for f in range(5):
            for j in range(3):
                parts.append(sphere_hull(np.stack([loc[0, f, j], loc[1, f, j]]),
                                         np.array([r[f, j], r[f, j + 1]])))
        parts.append(sphere_hull(ulnar[:, :3], ulnar[:, 3]))
        offsets = np.cumsum([0] + [len(v) for v, _ in parts])
        vertices = np.concatenate([v for v, _ in parts])
        faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets[:-1], strict=True)])
        part = np.repeat(np.arange(len(parts)), [len(v) for v, _ in parts])
        return HandMesh(vertices=vertices, faces=faces, part=part)

    def mesh(self, angles: np.ndarray, T_w_p: np.ndarray = _EYE4, scale: float = 1.0) -> HandMesh:
        """The posed surface (17 closed convex parts) in the world."""
        pose = self._pose(angles)
        tmpl = self._templates
        R = np.concatenate([np.eye(3)[None], pose.R.reshape(15, 3, 3), pose.R_cup[None]])
        origin = np.concatenate([np.zeros((1, 3)), pose.joints[:, :3].reshape(15, 3),
                                 (pose.pivot - pose.R_cup @ pose.pivot)[None]])
        v = np.einsum("nij,nj->ni", R[tmpl.part], tmpl.vertices) + origin[tmpl.part]
        return HandMesh(vertices=_to_world(v, T_w_p, scale), faces=tmpl.faces, part=tmpl.part)


def _twisted_x(twist: float) -> np.ndarray:
    """A flexion axis: the segment's x axis turned by ``twist`` about the bone (y)."""
    return np.array([np.cos(twist), 0.0, -np.sin(twist)])


def _to_world(points_p: np.ndarray, T_w_p: np.ndarray, scale: float) -> np.ndarray:
    T = np.asarray(T_w_p, dtype=float)
    return scale * points_p @ T[:3, :3].T + T[:3, 3]


__all__ = ["MODEL_VERSION", "PALM_PARTS", "WildHand", "WildHandShape"]
