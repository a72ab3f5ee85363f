"""A 20-DoF kinematic human hand: keypoints, collision capsules and a surface mesh.

The degrees of freedom follow GraspIt!'s HumanHand20DOF (Miller & Allen 2004;
``models/robots/HumanHand/HumanHand20DOF.xml`` in graspit-simulator/graspit):
a 6-DoF palm pose ``T_w_p`` plus, per finger, an abduction and a flexion at the
base and two more flexions; the thumb has its own base (CMC) with its own axes.
Only that structure and the joint ranges were used as reference; the geometry
here is procedural and the numbers are our own (see ``_LIMITS_DEG``).

Bone lengths are adult means of the phalanges after Buryanov & Kotiuk,
"Proportions of hand segments", Int. J. Morphol. 28(3):755-758, 2010 (rounded);
metacarpal placement was chosen so that wrist-to-middle-fingertip is about
0.183 m and index-to-little MCP about 0.072 m at ``scale = 1``.

Palm frame ``p``: origin at the wrist (keypoint 0), +y towards the middle MCP
(keypoint 9), +z the palmar normal, x = y cross z (towards the thumb for a
right hand, away from it for a left hand). Keypoints 0, 1, 5, 9, 13, 17 are
fixed in the palm. Flexion positive bends towards the palm (+z); abduction positive turns a finger
towards the thumb side (radial) and the thumb's metacarpal away from the palm
(palmar abduction). The left hand is the mirror image (x -> -x) with the same
angle meaning. One global ``scale`` multiplies every length, radii included; the
per-subject shape ``bone_scale`` (20 per-bone length factors, ``hand.shape``) stretches each
bone on top of it: the keypoints move along the bones, each phalanx's surface is stretched
along its bone (its end sphere moves), and the palm follows its moved knuckles (the base
spheres move with their bases, the others by the linear map that best moves the finger bases).
Radii are not part of the shape.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from graspcap.tasks.hand.mesh import sphere_hull, tapered_capsule

MODEL_VERSION = "hand_model/1"
_EYE4 = np.eye(4)
_EYE4.setflags(write=False)
_ONES20 = np.ones(20)
_ONES20.setflags(write=False)

FINGERS = ("thumb", "index", "middle", "ring", "little")
ANGLE_NAMES: tuple[str, ...] = tuple(
    f"{finger}_{dof}"
    for finger in FINGERS
    for dof in ("abduction", "flexion1", "flexion2", "flexion3")
)
KEYPOINT_NAMES: tuple[str, ...] = (
    "wrist",
    "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
    "index_mcp", "index_pip", "index_dip", "index_tip",
    "middle_mcp", "middle_pip", "middle_dip", "middle_tip",
    "ring_mcp", "ring_pip", "ring_dip", "ring_tip",
    "little_mcp", "little_pip", "little_dip", "little_tip",
)  # fmt: skip
RIGID_PALM_POINTS = (0, 1, 5, 9, 13, 17)
FINGERTIPS = (4, 8, 12, 16, 20)
KEYPOINT_PARENTS = (-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19)
"""Parent keypoint of each keypoint (-1 for the wrist)."""
SKELETON: tuple[tuple[int, int], ...] = tuple(
    (parent, k) for k, parent in enumerate(KEYPOINT_PARENTS) if parent >= 0
)
"""The 20 (parent, child) keypoint pairs of the skeleton, wrist to fingertips."""

# --- anatomy at scale 1 (right hand, palm frame, metres) ----------------------------------

_BASE_M = np.array(
    [
        [0.024, 0.030, 0.012],  # thumb CMC (keypoint 1)
        [0.026, 0.090, 0.002],  # index MCP (5)
        [0.000, 0.095, 0.000],  # middle MCP (9): defines +y
        [-0.022, 0.089, 0.002],  # ring MCP (13)
        [-0.046, 0.079, 0.006],  # little MCP (17)
    ]
)
_SEGMENT_LENGTH_M = np.array(
    [
        [0.045, 0.032, 0.025],  # thumb: metacarpal, proximal, distal
        [0.0398, 0.0224, 0.0158],  # index: proximal, middle, distal phalanx
        [0.0446, 0.0263, 0.0174],
        [0.0414, 0.0257, 0.0173],
        [0.0327, 0.0181, 0.0160],
    ]
)
_RADIUS_M = np.array(
    [
        [0.0120, 0.0110, 0.0095, 0.0085],  # thumb: CMC, MCP, IP, tip
        [0.0115, 0.0095, 0.0085, 0.0080],  # fingers: MCP, PIP, DIP, tip
        [0.0120, 0.0098, 0.0088, 0.0082],
        [0.0115, 0.0093, 0.0084, 0.0078],
        [0.0105, 0.0088, 0.0080, 0.0075],
    ]
)
_WRIST_RADIUS_M = 0.014
# Palm solid: hull of spheres (centre, radius): wrist, wrist sides, mid palm (thenar and
# hypothenar), thumb base, knuckles. Half-thickness 14 mm mid palm, 10.5-12 mm at the knuckles.
_PALM_SPHERES = np.array(
    [
        [0.000, 0.000, 0.000, _WRIST_RADIUS_M],
        [0.016, 0.004, 0.000, 0.013],
        [-0.018, 0.004, 0.000, 0.013],
        [0.018, 0.050, 0.000, 0.014],
        [-0.030, 0.050, 0.002, 0.014],
        *[[*_BASE_M[f], _RADIUS_M[f, 0]] for f in range(5)],
    ]
)

# Rest orientation of each finger's base frame: columns are the local x (lateral,
# radial side), y (along the bone) and z (palmar) axes in the palm frame.
_FAN_DEG = (4.0, 0.0, -5.0, -10.0)  # index, middle, ring, little; positive towards the thumb


def _finger_base_rotation(fan_deg: float) -> np.ndarray:
    a = np.radians(fan_deg)
    y = np.array([np.sin(a), np.cos(a), 0.0])
    z = np.array([0.0, 0.0, 1.0])
    return np.stack([np.cross(y, z), y, z], axis=1)


def _thumb_base_rotation() -> np.ndarray:
    # Metacarpal pointing out radially and slightly palmar; the thumb pad is pronated
    # 60 degrees from the palm normal towards the index finger.
    y = np.array([0.58, 0.80, 0.16])
    y /= np.linalg.norm(y)
    pad = np.array([-np.sin(np.radians(60.0)), 0.0, np.cos(np.radians(60.0))])
    z = pad - (pad @ y) * y
    z /= np.linalg.norm(z)
    return np.stack([np.cross(y, z), y, z], axis=1)


_BASE_R = np.stack([_thumb_base_rotation(), *[_finger_base_rotation(a) for a in _FAN_DEG]])
_BASE_RT = np.ascontiguousarray(_BASE_R.transpose(0, 2, 1)[None])  # (1, 5, 3, 3) for row vectors

# Joint limits in degrees (abduction, flexion1, flexion2, flexion3). GraspIt's HumanHand20DOF
# uses -10..90 for every finger flexion and symmetric abduction (+-20, 10, 20, 30); we use
# anatomical active ranges: MCP hyperextension to -20, PIP to 100, DIP to 80, index abducting
# more radially and ring/little more ulnarly. The thumb CMC is parametrised differently from
# GraspIt's (its two CMC axes are not ours), so only thumb MCP/IP are comparable (0..90, 0..100).
_LIMITS_DEG = np.array(
    [
        [[-15, 45], [-20, 50], [-10, 75], [-15, 85]],  # thumb: CMC abd, CMC flex, MCP, IP
        [[-15, 25], [-20, 90], [-5, 100], [-10, 80]],  # index
        [[-12, 12], [-20, 90], [-5, 100], [-10, 80]],  # middle
        [[-20, 15], [-20, 90], [-5, 100], [-10, 80]],  # ring
        [[-35, 15], [-20, 90], [-5, 100], [-10, 80]],  # little
    ],
    dtype=float,
)

_PART_NAMES: tuple[str, ...] = ("palm",) + tuple(
    f"{finger}_{bone}"
    for finger, bones in zip(
        FINGERS,
        [("metacarpal", "proximal", "distal")] + [("proximal", "middle", "distal")] * 4,
        strict=True,
    )
    for bone in bones
)
PART_BONES: tuple[tuple[int, int], ...] = tuple(
    (1 + 4 * f + j, 2 + 4 * f + j) for f in range(5) for j in range(3)
)
"""(start, end) keypoint of each part after the palm, in ``PART_NAMES`` order from index 1."""

SURFACE_OFFSET_M: np.ndarray = np.concatenate([[_WRIST_RADIUS_M], _RADIUS_M.reshape(-1)])
"""(21,) Distance at scale 1 from each keypoint (a joint centre or the fingertip's centre)
to the skin: the radius of the hand surface there. Multiply by ``scale``."""
SURFACE_OFFSET_M.setflags(write=False)


TEMPLATE_BONE_LENGTHS_M = np.concatenate(
    [np.linalg.norm(_BASE_M, axis=1)[:, None], _SEGMENT_LENGTH_M], axis=1
).reshape(20)
"""(20,) Bone lengths at scale 1 and unit ``bone_scale``, metres, ``SKELETON`` order."""
TEMPLATE_BONE_LENGTHS_M.setflags(write=False)


class HandSide(StrEnum):
    """Which hand; the left is the right mirrored in the palm frame's x."""

    RIGHT = "right"
    LEFT = "left"


@dataclass(frozen=True)
class HandMesh:
    """A posed hand surface: closed parts concatenated.

    vertices : (n, 3) float, faces : (m, 3) int (outward), part : (n,) int into
    ``HandModel.PART_NAMES``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    part: np.ndarray


@dataclass(frozen=True)
class Capsules:
    """Collision capsules: segment ``start`` (k, 3) to ``end`` (k, 3), ``radius`` (k,),
    ``part`` (k,) int into ``HandModel.PART_NAMES`` (several for the palm, one per phalanx)."""

    start: np.ndarray
    end: np.ndarray
    radius: np.ndarray
    part: np.ndarray


def _check_shape(bone_scale: np.ndarray | None) -> np.ndarray:
    f = check_bone_scale(bone_scale)
    if f.shape != (20,):
        raise ValueError(f"bone_scale must be (20,) here, got {f.shape}")
    return f


def _check_angles(angles: np.ndarray) -> np.ndarray:
    angles = np.asarray(angles, dtype=float)
    if angles.shape != (20,):
        raise ValueError(f"angles must be (20,), got {angles.shape}")
    return angles


def check_bone_scale(bone_scale: np.ndarray | None) -> np.ndarray:
    """(20,) per-bone length factors (``SKELETON`` order); ``None`` is the template (ones).
    A batch (b, 20), one shape per pose, passes too (``keypoints_batch``)."""
    if bone_scale is None:
        return _ONES20
    bone_scale = np.asarray(bone_scale, dtype=float)
    if (bone_scale.ndim not in (1, 2) or bone_scale.shape[-1] != 20
            or not np.all(np.isfinite(bone_scale)) or np.any(bone_scale <= 0)):
        raise ValueError(f"bone_scale must be (20,) positive finite factors, got {bone_scale!r}")
    return bone_scale


def _keypoints_palm(angles: np.ndarray, bone_scale: np.ndarray | None = None) -> np.ndarray:
    """Right-hand keypoints (b, 21, 3) in the palm frame at scale 1 for angles (b, 20).

    ``bone_scale`` (20,) multiplies each bone's template length, in ``SKELETON`` order (bone
    ``k - 1`` ends at keypoint ``k``): per finger the wrist-to-base vector (the palm's
    proportions) and the three segments."""
    b = len(angles)
    a = angles.reshape(b, 5, 4)
    f = check_bone_scale(bone_scale).reshape(-1, 5, 4)  # (1 or b, 5, 4)
    if len(f) not in (1, b):
        raise ValueError(f"bone_scale has {len(f)} shapes for {b} poses")
    base = _BASE_M * f[:, :, :1]  # (1 or b, 5, 3)
    phi = np.cumsum(a[:, :, 1:], axis=2)  # (b, 5, 3) accumulated flexion
    local = _directions(a[:, :, :1], phi) * (_SEGMENT_LENGTH_M * f[:, :, 1:])[..., None]
    chain = np.cumsum(local @ _BASE_RT, axis=2)  # (b, 5, 3, 3) palm-frame bone vectors summed
    fingers = np.empty((b, 5, 4, 3))
    fingers[:, :, 0] = base
    fingers[:, :, 1:] = base[:, :, None] + chain
    points = np.zeros((b, 21, 3))
    points[:, 1:] = fingers.reshape(b, 20, 3)
    return points


def _directions(abduction: np.ndarray, flexion: np.ndarray) -> np.ndarray:
    """Bone direction in a finger's base frame: (..., 3) for matching (...) angles."""
    cf = np.cos(flexion)
    out = np.empty(np.broadcast_shapes(np.shape(abduction), np.shape(flexion)) + (3,))
    out[..., 0] = np.sin(abduction) * cf
    out[..., 1] = np.cos(abduction) * cf
    out[..., 2] = np.sin(flexion)
    return out


def _segment_rotations(angles: np.ndarray) -> np.ndarray:
    """(5, 3, 3, 3) rotation palm <- segment for finger f, segment j (columns x, y, z)."""
    a = angles.reshape(5, 4)
    phi = np.cumsum(a[:, 1:], axis=1)  # (5, 3) accumulated flexion
    ca, sa = np.cos(a[:, 0])[:, None], np.sin(a[:, 0])[:, None]
    cp, sp = np.cos(phi), np.sin(phi)
    zero = np.zeros_like(cp)
    # Rz(-abduction) @ Rx(phi): columns are the local x, y, z axes
    x = np.stack([ca + zero, -sa + zero, zero], axis=-1)
    y = np.stack([sa * cp, ca * cp, sp], axis=-1)
    z = np.stack([-sa * sp, -ca * sp, cp], axis=-1)
    local = np.stack([x, y, z], axis=-1)  # (5, 3, 3, 3)
    return np.einsum("fab,fjbc->fjac", _BASE_R, local)


def _palm_capsules(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Palm as five capsules: wrist region to each knuckle, and wrist to the thumb base, for
    per-bone factors ``f`` (5, 4) (the starts follow the palm's linear map)."""
    starts = np.array(
        [[0.010, 0.010, 0.004], [0.012, 0.018, 0.0], [0.0, 0.018, 0.0],
         [-0.012, 0.018, 0.0], [-0.022, 0.018, 0.002]]
    )  # fmt: skip
    ends = _BASE_M * f[:, :1]
    radii = np.array([0.012, 0.0125, 0.0130, 0.0125, 0.0120])
    return starts @ _palm_map(f).T, ends, radii


def _palm_map(f: np.ndarray) -> np.ndarray:
    """(3, 3) linear map of the palm for per-bone factors ``f`` (5, 4): least squares from the
    template's finger bases (index to little) to the moved ones; identity for the template."""
    if np.all(f[:, 0] == 1.0):
        return np.eye(3)
    src = _BASE_M[1:]
    A, *_ = np.linalg.lstsq(src, src * f[1:, :1], rcond=None)  # src @ A ~ dst
    return A.T


class HandModel:
    """The 20-DoF hand of one side. Immutable; every method is pure.

    Angles are (20,) radians in ``ANGLE_NAMES`` order; ``T_w_p`` (4, 4) maps the
    palm frame into the world; ``scale`` multiplies every length.
    """

    PART_NAMES: tuple[str, ...] = _PART_NAMES
    __slots__ = ("side", "lower_rad", "upper_rad", "_mirror", "_template")

    def __init__(self, side: HandSide = HandSide.RIGHT):
        side = HandSide(side)
        lower = np.radians(_LIMITS_DEG[:, :, 0].reshape(-1))
        upper = np.radians(_LIMITS_DEG[:, :, 1].reshape(-1))
        lower.setflags(write=False)
        upper.setflags(write=False)
        object.__setattr__(self, "side", side)
        object.__setattr__(self, "lower_rad", lower)
        object.__setattr__(self, "upper_rad", upper)
        object.__setattr__(self, "_mirror", side is HandSide.LEFT)
        object.__setattr__(self, "_template", _mesh_template())

    def __setattr__(self, name, value):
        raise AttributeError("HandModel is immutable")

    def __repr__(self) -> str:
        return f"HandModel(side={self.side.value!r})"

    # --- angles -------------------------------------------------------------------------

    def rest_angles(self) -> np.ndarray:
        """(20,) A flat, open hand (all zeros), inside the joint limits."""
        return np.zeros(20)

    def clip(self, angles: np.ndarray) -> np.ndarray:
        """(20,) or (b, 20) angles clipped into the joint limits."""
        return np.clip(np.asarray(angles, dtype=float), self.lower_rad, self.upper_rad)

    # --- keypoints ----------------------------------------------------------------------

    def keypoints_batch(
        self,
        angles: np.ndarray,
        T_w_p: np.ndarray = _EYE4,
        scale: float = 1.0,
        bone_scale: np.ndarray | None = None,
    ) -> np.ndarray:
        """Keypoints (b, 21, 3) in the world for angles (b, 20); one ``T_w_p``, ``scale`` and
        ``bone_scale`` ((20,) per-bone length factors on top of ``scale``, ``SKELETON``
        order; or (b, 20), one shape per pose; None = the template's proportions)."""
        angles = np.asarray(angles, dtype=float)
        if angles.ndim != 2 or angles.shape[1] != 20:
            raise ValueError(f"angles must be (b, 20), got {angles.shape}")
        return self._to_world(_keypoints_palm(angles, bone_scale), T_w_p, scale)

    def keypoints(
        self,
        angles: np.ndarray,
        T_w_p: np.ndarray = _EYE4,
        scale: float = 1.0,
        bone_scale: np.ndarray | None = None,
    ) -> np.ndarray:
        """Keypoints (21, 3) in the world, in ``KEYPOINT_NAMES`` order."""
        return self.keypoints_batch(_check_angles(angles)[None], T_w_p, scale, bone_scale)[0]

    def _to_world(self, points_p: np.ndarray, T_w_p: np.ndarray, scale: float) -> np.ndarray:
        """Right-hand palm-frame points (..., 3) -> mirrored if left, scaled, into the world."""
        if self._mirror:
            points_p = points_p * np.array([-1.0, 1.0, 1.0])
        T = np.asarray(T_w_p, dtype=float)
        return scale * points_p @ T[:3, :3].T + T[:3, 3]

    # --- surfaces -----------------------------------------------------------------------

    def capsules(
        self,
        angles: np.ndarray,
        T_w_p: np.ndarray = _EYE4,
        scale: float = 1.0,
        bone_scale: np.ndarray | None = None,
    ) -> Capsules:
        """Five palm capsules (part 0) then one per phalanx (parts 1..15), in the world, for
        the shape ``bone_scale`` (None: the template's)."""
        f = _check_shape(bone_scale)
        kp_p = _keypoints_palm(_check_angles(angles)[None], f)[0]  # right hand, scale 1
        palm_start, palm_end, palm_r = _palm_capsules(f.reshape(5, 4))
        bones = np.array(PART_BONES)
        start = np.concatenate([palm_start, kp_p[bones[:, 0]]])
        end = np.concatenate([palm_end, kp_p[bones[:, 1]]])
        ends_r = np.stack([_RADIUS_M[:, :3].reshape(-1), _RADIUS_M[:, 1:].reshape(-1)])
        radius = np.concatenate([palm_r, ends_r.mean(axis=0)]) * scale
        part = np.concatenate([np.zeros(len(palm_r), int), np.arange(1, 16)])
        return Capsules(
            start=self._to_world(start, T_w_p, scale),
            end=self._to_world(end, T_w_p, scale),
            radius=radius,
            part=part,
        )

    def mesh(
        self,
        angles: np.ndarray,
        T_w_p: np.ndarray = _EYE4,
        scale: float = 1.0,
        bone_scale: np.ndarray | None = None,
    ) -> HandMesh:
        """The posed surface: 16 closed parts (palm, 15 phalanges) concatenated, in the world,
        for the shape ``bone_scale`` (None: the template's). Same vertex count and faces for
        every shape and pose."""
        angles = _check_angles(angles)
        f = _check_shape(bone_scale)
        tmpl = self._template
        kp = _keypoints_palm(angles[None], f)[0]  # right hand, scale 1
        R = np.concatenate([np.eye(3)[None], _segment_rotations(angles).reshape(15, 3, 3)])
        origin = np.concatenate([np.zeros((1, 3)), kp[np.array(PART_BONES)[:, 0]]])
        local = tmpl.vertices
        if bone_scale is not None:
            local = local + _shape_offsets(f.reshape(5, 4))
        v = np.einsum("nij,nj->ni", R[tmpl.part], local) + origin[tmpl.part]
        faces = tmpl.faces[:, ::-1] if self._mirror else tmpl.faces
        return HandMesh(vertices=self._to_world(v, T_w_p, scale), faces=faces, part=tmpl.part)


def _sphere_of(vertices: np.ndarray, spheres: np.ndarray) -> np.ndarray:
    """Which of ``spheres`` (k, 4: centre, radius) each hull vertex (n, 3) was sampled from:
    the one whose surface (as ``sphere_hull`` samples it, radius times a common factor) is
    nearest."""
    d = np.linalg.norm(vertices[:, None] - spheres[None, :, :3], axis=2) / spheres[None, :, 3]
    ratio = np.median(d.min(axis=1))  # the samples' common distance in radii (about 1.01)
    return np.argmin(np.abs(d - ratio), axis=1)


_SHAPE_PARTS: dict[str, np.ndarray] = {}
"""The template's per-vertex shape handles: ``palm_sphere`` (palm vertices' sphere in
``_PALM_SPHERES``), ``end`` (phalanx vertices on the end sphere, bool) over all vertices."""


def _shape_offsets(f: np.ndarray) -> np.ndarray:
    """(n, 3) offsets of the template's vertices, each in its part's frame, for per-bone
    factors ``f`` (5, 4): a phalanx's end sphere moves along the bone (+y) by its change of
    length; a palm sphere on a finger base moves with the base; the other palm spheres by the
    palm's linear map (``_palm_map``)."""
    tmpl = _mesh_template()
    out = np.zeros_like(tmpl.vertices)
    dl = (_SEGMENT_LENGTH_M * (f[:, 1:] - 1.0)).reshape(15)  # parts 1..15
    end = _SHAPE_PARTS["end"]
    out[end, 1] = dl[tmpl.part[end] - 1]
    centres = _PALM_SPHERES[:, :3]
    moved = centres @ _palm_map(f).T
    moved[-5:] = _BASE_M * f[:, :1]
    palm = tmpl.part == 0
    out[palm] = (moved - centres)[_SHAPE_PARTS["palm_sphere"]]
    return out


def _build_template() -> HandMesh:
    """Unposed parts, each in its own frame (the palm in the palm frame), scale 1."""
    parts = [sphere_hull(_PALM_SPHERES[:, :3], _PALM_SPHERES[:, 3])]
    for f in range(5):
        for j in range(3):
            parts.append(
                tapered_capsule(_SEGMENT_LENGTH_M[f, j], _RADIUS_M[f, j], _RADIUS_M[f, j + 1])
            )
    offsets = np.cumsum([0] + [len(v) for v, _ in parts])
    vertices = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets[:-1], strict=True)])
    part = np.repeat(np.arange(len(parts)), [len(v) for v, _ in parts])
    palm_sphere = _sphere_of(vertices[part == 0], _PALM_SPHERES)
    end = np.zeros(len(vertices), bool)
    for k in range(1, 16):
        f, j = divmod(k - 1, 3)
        ends = np.array([[0.0, 0.0, 0.0, _RADIUS_M[f, j]],
                         [0.0, _SEGMENT_LENGTH_M[f, j], 0.0, _RADIUS_M[f, j + 1]]])
        end[part == k] = _sphere_of(vertices[part == k], ends) == 1
    for arr in (vertices, faces, part, palm_sphere, end):
        arr.setflags(write=False)
    _SHAPE_PARTS.update(palm_sphere=palm_sphere, end=end)
    return HandMesh(vertices=vertices, faces=faces, part=part)


_TEMPLATE: HandMesh | None = None


def _mesh_template() -> HandMesh:
    global _TEMPLATE
    if _TEMPLATE is None:
        _TEMPLATE = _build_template()
    return _TEMPLATE


__all__ = [
    "ANGLE_NAMES", "FINGERS", "FINGERTIPS", "KEYPOINT_NAMES", "KEYPOINT_PARENTS", "MODEL_VERSION",
    "PART_BONES", "RIGID_PALM_POINTS", "SKELETON", "SURFACE_OFFSET_M", "Capsules", "HandMesh",
    "TEMPLATE_BONE_LENGTHS_M", "HandModel", "HandSide", "check_bone_scale",
]  # fmt: skip
