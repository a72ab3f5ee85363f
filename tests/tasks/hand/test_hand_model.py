"""The 20-DoF hand model: structure, kinematics, mirror symmetry, surface and proportions."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import open3d as o3d
import pytest
import trimesh
from scipy.optimize import least_squares

from graspcap.tasks.core.geometry import from_rotvec, transform_points, umeyama
from graspcap.tasks.hand.model import (
    ANGLE_NAMES,
    FINGERTIPS,
    KEYPOINT_NAMES,
    KEYPOINT_PARENTS,
    PART_BONES,
    RIGID_PALM_POINTS,
    SURFACE_OFFSET_M,
    HandModel,
    HandSide,
)

SIDES = [HandSide.RIGHT, HandSide.LEFT]
MIRROR = np.diag([-1.0, 1.0, 1.0])


@pytest.fixture(scope="module", params=SIDES, ids=lambda s: s.value)
def model(request) -> HandModel:
    return HandModel(request.param)


def random_angles(model: HandModel, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    size = (20,) if n is None else (n, 20)
    return rng.uniform(model.lower_rad, model.upper_rad, size=size)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return from_rotvec(rng.normal(size=3), rng.uniform(-0.5, 0.5, size=3))


def test_structure_and_limits(model):
    assert len(ANGLE_NAMES) == 20 and len(set(ANGLE_NAMES)) == 20
    assert len(KEYPOINT_NAMES) == 21 and KEYPOINT_NAMES[0] == "wrist"
    assert [KEYPOINT_NAMES[i] for i in FINGERTIPS] == [
        f"{f}_tip" for f in ("thumb", "index", "middle", "ring", "little")
    ]
    assert len(model.PART_NAMES) == 16 and model.PART_NAMES[0] == "palm"
    assert model.lower_rad.shape == model.upper_rad.shape == (20,)
    assert np.all(model.lower_rad < model.upper_rad)
    rest = model.rest_angles()
    assert rest.shape == (20,)
    assert np.all((model.lower_rad <= rest) & (rest <= model.upper_rad))
    # Limits in radians, not degrees: no joint travels more than 150 degrees.
    assert np.all(model.upper_rad - model.lower_rad < np.radians(150))


def _graspit_limits_deg(xml_path) -> dict[str, np.ndarray]:
    """GraspIt chains are index, middle, ring, pinky, thumb; 4 joints each (min, max) in deg."""
    chains = ET.parse(xml_path).getroot().findall("chain")
    limits = [
        np.array([[float(j.find("minValue").text), float(j.find("maxValue").text)]
                  for j in c.findall("joint")])
        for c in chains
    ]  # fmt: skip
    assert len(limits) == 5 and all(lim.shape == (4, 2) for lim in limits)
    return dict(zip(("index", "middle", "ring", "little", "thumb"), limits, strict=True))


def test_limits_agree_with_graspit(shared_data, model):
    """Finger flexion ranges within 20 deg of GraspIt's; abduction total range within 15 deg.

    Chosen differences (documented in hand_model._LIMITS_DEG): MCP hyperextension to -20
    (GraspIt -10), PIP to 100 (90), DIP -10..80 (-10..90); thumb MCP -10..75 (0..90) and IP
    -15..85 (0..100). The thumb CMC is parametrised differently and is not compared.
    """
    graspit = _graspit_limits_deg(shared_data / "graspit_humanhand" / "HumanHand20DOF.xml")
    ours = np.degrees(np.stack([model.lower_rad, model.upper_rad], axis=1)).reshape(5, 4, 2)
    names = ("thumb", "index", "middle", "ring", "little")
    for f, name in enumerate(names):
        flexions = [1, 2, 3] if name != "thumb" else [2, 3]
        for j in flexions:
            g, o = graspit[name][j], ours[f, j]
            assert g[0] <= 0 < g[1] and o[0] <= 0 < o[1], (name, j)  # positive = flexion
            assert np.all(np.abs(o - g) <= 20.0), (name, j, o, g)
        if name != "thumb":
            g, o = graspit[name][0], ours[f, 0]
            assert g[0] < 0 < g[1] and o[0] < 0 < o[1]
            assert abs((o[1] - o[0]) - (g[1] - g[0])) <= 15.0, (name, o, g)


def test_rigid_points_fixed_and_umeyama_recovers_pose(model):
    rng = np.random.default_rng(0)
    rigid = list(RIGID_PALM_POINTS)
    template = model.keypoints(model.rest_angles())[rigid]
    for _ in range(10):
        angles = random_angles(model, rng)
        np.testing.assert_allclose(model.keypoints(angles)[rigid], template, atol=1e-15)
        T_w_p, scale = random_pose(rng), rng.uniform(0.8, 1.25)
        world = model.keypoints(angles, T_w_p, scale)
        T_est, s_est = umeyama(template, world[rigid])
        np.testing.assert_allclose(T_est, T_w_p, atol=1e-9)
        assert abs(s_est - scale) < 1e-9
    # the non-rigid keypoints do move
    moved = model.keypoints(random_angles(model, rng)) - model.keypoints(model.rest_angles())
    assert np.all(np.linalg.norm(np.delete(moved, rigid, axis=0), axis=1) > 1e-4)


def test_palm_frame_convention(model):
    kp = model.keypoints(model.rest_angles())
    np.testing.assert_allclose(kp[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(kp[9][[0, 2]], 0.0, atol=1e-15)  # middle MCP on +y
    assert kp[9][1] > 0.08
    thumb_side = 1.0 if model.side is HandSide.RIGHT else -1.0
    assert thumb_side * kp[1][0] > 0.01 and thumb_side * kp[5][0] > thumb_side * kp[17][0]


def test_bone_lengths_preserved_and_scaled(model):
    rng = np.random.default_rng(1)
    child = np.arange(1, 21)
    parent = np.array(KEYPOINT_PARENTS)[1:]
    rest = model.keypoints(model.rest_angles())
    bones = np.linalg.norm(rest[child] - rest[parent], axis=1)
    assert np.all(bones > 0.014) and np.all(bones < 0.1)
    for _ in range(10):
        scale = rng.uniform(0.8, 1.25)
        kp = model.keypoints(random_angles(model, rng), random_pose(rng), scale)
        np.testing.assert_allclose(
            np.linalg.norm(kp[child] - kp[parent], axis=1), scale * bones, rtol=1e-12
        )


@pytest.mark.parametrize("finger", range(5))
@pytest.mark.parametrize("joint", [1, 2, 3])
def test_flexion_moves_tip_towards_palm(model, finger, joint):
    angles = model.rest_angles()
    before = model.keypoints(angles)[FINGERTIPS[finger]]
    angles[4 * finger + joint] += 0.3
    after = model.keypoints(angles)[FINGERTIPS[finger]]
    assert after[2] - before[2] > 0.002  # palmar side is +z in the palm frame


def test_abduction_moves_fingers_sideways(model):
    thumb_side = 1.0 if model.side is HandSide.RIGHT else -1.0
    for finger in range(1, 5):
        angles = model.rest_angles()
        before = model.keypoints(angles)[FINGERTIPS[finger]]
        angles[4 * finger] += 0.2
        delta = model.keypoints(angles)[FINGERTIPS[finger]] - before
        assert thumb_side * delta[0] > 0.01  # towards the thumb side
        assert abs(delta[2]) < 1e-12 and abs(delta[0]) > 5 * abs(delta[1])
    angles = model.rest_angles()
    before = model.keypoints(angles)[4]
    angles[0] += 0.3  # thumb palmar abduction lifts the thumb off the palm plane
    assert model.keypoints(angles)[4][2] - before[2] > 0.01


def test_thumb_can_pinch_index():
    """Opposition: within the limits the thumb tip reaches the index tip."""
    model = HandModel()
    dofs = np.arange(8)  # thumb and index angles

    def gap(x):
        angles = model.rest_angles()
        angles[dofs] = x
        kp = model.keypoints(angles)
        return kp[4] - kp[8]

    fit = least_squares(gap, np.zeros(8), bounds=(model.lower_rad[dofs], model.upper_rad[dofs]))
    assert np.linalg.norm(fit.fun) < 1e-3


def test_left_is_mirror_of_right():
    rng = np.random.default_rng(2)
    right, left = HandModel(HandSide.RIGHT), HandModel("left")
    angles = random_angles(right, rng)
    T_w_p, scale = random_pose(rng), 1.1
    kp_r, kp_l = right.keypoints(angles), left.keypoints(angles)
    np.testing.assert_allclose(kp_l, kp_r @ MIRROR, atol=1e-15)
    np.testing.assert_allclose(
        left.keypoints(angles, T_w_p, scale), transform_points(T_w_p, scale * kp_l), atol=1e-12
    )
    mesh_r, mesh_l = right.mesh(angles), left.mesh(angles)
    np.testing.assert_allclose(mesh_l.vertices, mesh_r.vertices @ MIRROR, atol=1e-15)
    np.testing.assert_array_equal(mesh_l.faces, mesh_r.faces[:, ::-1])
    caps_r, caps_l = right.capsules(angles), left.capsules(angles)
    np.testing.assert_allclose(caps_l.start, caps_r.start @ MIRROR, atol=1e-15)
    np.testing.assert_allclose(caps_l.radius, caps_r.radius)


def test_batch_equals_single(model):
    rng = np.random.default_rng(3)
    angles = random_angles(model, rng, n=7)
    T_w_p, scale = random_pose(rng), 0.93
    batch = model.keypoints_batch(angles, T_w_p, scale)
    assert batch.shape == (7, 21, 3)
    for row, kp in zip(angles, batch, strict=True):
        np.testing.assert_allclose(kp, model.keypoints(row, T_w_p, scale), atol=1e-15)
    with pytest.raises(ValueError):
        model.keypoints(angles)


def test_clip_and_immutability(model):
    angles = np.concatenate([np.full(10, -5.0), np.full(10, 5.0)])
    clipped = model.clip(angles)
    np.testing.assert_array_equal(clipped[:10], model.lower_rad[:10])
    np.testing.assert_array_equal(clipped[10:], model.upper_rad[10:])
    inside = model.clip(random_angles(model, np.random.default_rng(4)))
    np.testing.assert_array_equal(model.clip(inside), inside)
    with pytest.raises(AttributeError):
        model.side = HandSide.LEFT
    with pytest.raises(ValueError):
        model.lower_rad[0] = 0.0


def _part(mesh, p: int) -> trimesh.Trimesh:
    """Part ``p`` of a HandMesh as its own trimesh (faces whose three vertices are in it)."""
    keep = np.nonzero(mesh.part == p)[0]
    remap = np.full(len(mesh.vertices), -1)
    remap[keep] = np.arange(len(keep))
    faces = remap[mesh.faces[np.all(mesh.part[mesh.faces] == p, axis=1)]]
    return trimesh.Trimesh(mesh.vertices[keep], faces, process=False)


def test_mesh_parts_closed_outward_and_plausible(model):
    rng = np.random.default_rng(5)
    for angles in (model.rest_angles(), random_angles(model, rng)):
        mesh = model.mesh(angles, random_pose(rng), 1.05)
        assert mesh.vertices.shape[1] == 3 and mesh.faces.shape[1] == 3
        assert 1000 <= len(mesh.vertices) <= 8000
        assert np.array_equal(np.unique(mesh.part), np.arange(16))
        parts = [_part(mesh, p) for p in range(16)]
        assert sum(len(p.faces) for p in parts) == len(mesh.faces)  # no face spans two parts
        for name, part in zip(model.PART_NAMES, parts, strict=True):
            assert 50 <= len(part.vertices) <= 1000, name
            assert part.is_watertight and part.is_winding_consistent, name
            assert part.volume > 0, name  # outward-facing
        # every phalanx lies on its bone: surface within 7..12.5 mm of the axis (scaled)
        kp = model.keypoints(angles, np.eye(4), 1.0)
        posed = model.mesh(angles)
        for p, (a, b) in enumerate(PART_BONES, start=1):
            v = posed.vertices[posed.part == p]
            t = np.clip((v - kp[a]) @ (kp[b] - kp[a]) / np.sum((kp[b] - kp[a]) ** 2), 0, 1)
            dist = np.linalg.norm(v - (kp[a] + t[:, None] * (kp[b] - kp[a])), axis=1)
            assert 0.007 < dist.min() and dist.max() < 0.0125, model.PART_NAMES[p]


def _scenes(mesh):
    scenes = []
    for p in np.unique(mesh.part):
        part = _part(mesh, p)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(part.vertices.astype(np.float32)),
            o3d.core.Tensor(part.faces.astype(np.uint32)),
        )
        scenes.append(scene)
    return scenes


def _surface_distance(mesh, points) -> tuple[np.ndarray, np.ndarray]:
    """(distance to the nearest part surface, inside any part) per point (n, 3)."""
    query = o3d.core.Tensor(points.astype(np.float32))
    signed = np.stack([s.compute_signed_distance(query).numpy() for s in _scenes(mesh)])
    return np.abs(signed).min(axis=0), (signed < 0).any(axis=0)


def _skin_distance(mesh, points) -> np.ndarray:
    """Distance (n,) from points to the skin: the part surfaces not inside another part.

    Parts overlap (a phalanx's end cap lies inside its neighbour, knuckles inside the palm),
    so the skin is sampled (2 points per mm^2, fixed seed) and samples inside other parts dropped.
    """
    samples, owner = [], []
    for p in range(16):
        part = _part(mesh, p)
        count = int(part.area / 0.5e-6)
        samples.append(trimesh.sample.sample_surface(part, count, seed=p)[0])
        owner.append(np.full(len(samples[-1]), p))
    samples, owner = np.concatenate(samples), np.concatenate(owner)
    query = o3d.core.Tensor(samples.astype(np.float32))
    inside = np.stack([s.compute_occupancy(query).numpy() > 0.5 for s in _scenes(mesh)])
    inside[owner, np.arange(len(owner))] = False  # a sample is on its own part's surface
    skin = samples[~inside.any(axis=0)]
    return np.linalg.norm(points[:, None] - skin[None], axis=2).min(axis=1)


def test_keypoints_lie_surface_offset_below_the_skin(model):
    flexed = model.rest_angles()
    flexed[1::4] = 0.4  # thumb CMC flexion and every finger's base flexion
    flexed[2::4] = 0.5
    for angles in (model.rest_angles(), flexed):
        mesh, kp = model.mesh(angles), model.keypoints(angles)
        assert np.all(_surface_distance(mesh, kp)[1])  # inside the hand
        np.testing.assert_allclose(_skin_distance(mesh, kp), SURFACE_OFFSET_M, atol=0.3e-3)
    # offsets as documented: fingers 7.5-12 mm, palm/wrist 12-15 mm
    assert np.all((SURFACE_OFFSET_M > 0.0074) & (SURFACE_OFFSET_M < 0.015))
    # any pose, scaled: every keypoint inside the hand and within one offset of a surface
    rng = np.random.default_rng(6)
    angles, T_w_p, scale = random_angles(model, rng), random_pose(rng), 1.2
    dist, inside = _surface_distance(
        model.mesh(angles, T_w_p, scale), model.keypoints(angles, T_w_p, scale)
    )
    assert np.all(inside)
    assert np.all(dist <= scale * SURFACE_OFFSET_M + 0.5e-3)


def test_proportions_at_scale_one(model):
    kp = model.keypoints(model.rest_angles())
    assert 0.18 <= np.linalg.norm(kp[12] - kp[0]) <= 0.19  # wrist to middle fingertip
    assert 0.07 <= np.linalg.norm(kp[5] - kp[17]) <= 0.085  # index MCP to little MCP
    mesh = model.mesh(model.rest_angles())
    extent = np.ptp(mesh.vertices, axis=0)
    assert 0.19 <= extent[1] <= 0.23  # hand length including skin at wrist and tip
    assert 0.085 <= extent[0] <= 0.18  # breadth, thumb spread
    assert 0.025 <= extent[2] <= 0.06  # thickness
    palm = mesh.vertices[mesh.part == 0]
    assert 0.012 <= -palm[:, 2].min() <= 0.015  # dorsal half-thickness
    assert 0.012 <= palm[:, 2].max() <= 0.026  # palmar side, thenar included
    hand_breadth = np.ptp(palm[:, 0])
    assert 0.075 <= hand_breadth <= 0.10


def test_capsules_follow_the_bones(model):
    rng = np.random.default_rng(7)
    angles, T_w_p, scale = random_angles(model, rng), random_pose(rng), 1.1
    caps = model.capsules(angles, T_w_p, scale)
    kp = model.keypoints(angles, T_w_p, scale)
    phalanx = caps.part > 0
    assert caps.start.shape == caps.end.shape == (len(caps.radius), 3)
    np.testing.assert_array_equal(caps.part[phalanx], np.arange(1, 16))
    bones = np.array(PART_BONES)
    np.testing.assert_allclose(caps.start[phalanx], kp[bones[:, 0]], atol=1e-12)
    np.testing.assert_allclose(caps.end[phalanx], kp[bones[:, 1]], atol=1e-12)
    assert 3 <= np.sum(~phalanx) <= 8
    assert np.all((caps.radius > scale * 0.007) & (caps.radius < scale * 0.016))
    # palm capsules are fixed in the palm: same in the palm frame whatever the angles
    base = model.capsules(model.rest_angles())
    np.testing.assert_allclose(
        caps.start[~phalanx], transform_points(T_w_p, scale * base.start[~phalanx]), atol=1e-12
    )


def test_mesh_is_rigidly_transformed(model):
    rng = np.random.default_rng(8)
    angles, T_w_p, scale = random_angles(model, rng), random_pose(rng), 0.9
    np.testing.assert_allclose(
        model.mesh(angles, T_w_p, scale).vertices,
        transform_points(T_w_p, scale * model.mesh(angles).vertices),
        atol=1e-12,
    )


def test_bone_scale_changes_exactly_its_bone_lengths():
    """Per-bone factors multiply the matching parent-to-child distances (straight fingers,
    where a bone length is the keypoint distance) and no other; None is the template."""
    from graspcap.tasks.hand.model import SKELETON, TEMPLATE_BONE_LENGTHS_M

    model = HandModel(HandSide.LEFT)
    angles = model.rest_angles()
    factors = np.linspace(0.85, 1.15, 20)
    kp0 = model.keypoints(angles, scale=1.0)
    kp = model.keypoints(angles, scale=1.0, bone_scale=factors)
    lengths = lambda p: np.array([np.linalg.norm(p[c] - p[a]) for a, c in SKELETON])  # noqa: E731
    np.testing.assert_allclose(lengths(kp0), TEMPLATE_BONE_LENGTHS_M, atol=1e-12)
    np.testing.assert_allclose(lengths(kp), TEMPLATE_BONE_LENGTHS_M * factors, atol=1e-12)
    np.testing.assert_array_equal(model.keypoints(angles, bone_scale=np.ones(20)), kp0)
    with pytest.raises(ValueError, match="bone_scale"):
        model.keypoints(angles, bone_scale=np.ones(19))
