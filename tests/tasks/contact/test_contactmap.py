"""Stage 4, build_contactmap: a rig session, real ContactDB maps re-rendered, bad inputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh

from graspcap.synth import generate
from graspcap.tasks.contact.build_contactmap import (
    PRESETS,
    STAGE_VERSION,
    AmbientMode,
    BuildContactmapConfig,
    build_contactmap,
    vertex_normals,
    weighted_median,
)
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import make_T, rot_z, transform_points
from graspcap.tasks.core.render import pixel_rays
from graspcap.tasks.session.load_session import load_session
from tests.registration_rig import look_at_turntable

AMBIENT_K, RISE_K, NOISE_K = 295.0, 5.0, 0.05
WIDTH, HEIGHT = 320, 256
K_TH = np.array([[360.0, 0.0, WIDTH / 2], [0.0, 360.0, HEIGHT / 2], [0.0, 0.0, 1.0]])


def contact_scores(contact, truth, observed) -> tuple[float, float, float]:
    """MAE on observed vertices, IoU of contact >= 0.4 on observed vertices, share of
    truth-contacted (>= 0.4) vertices that are observed."""
    a, b = contact[observed] >= 0.4, truth[observed] >= 0.4
    mae = float(np.abs(contact[observed] - truth[observed]).mean())
    iou = float((a & b).sum() / max((a | b).sum(), 1))
    return mae, iou, float(observed[truth >= 0.4].mean())


# ---------------------------------------------------------------- rig session


@pytest.fixture(scope="module")
def rig_session(tmp_path_factory):
    (root,) = generate(tmp_path_factory.mktemp("rig"), sessions=1, seed=3,
                       difficulty="realistic", frames=12)
    return root


def _rig_inputs(root: Path):
    s = load_session(root)
    m = s.manifest
    mesh = trimesh.load(s.path(m.object_mesh), process=False, force="mesh")
    views = [(s.read_thermal_k(v.thermal), float(np.radians(v.angle_deg))) for v in m.scan.views]
    truth = json.loads((root / "ground_truth/truth.json").read_text())
    args = (np.asarray(mesh.vertices), np.asarray(mesh.faces), views, np.array(m.thermal_camera.K),
            np.array(m.thermal_camera.T_color_thermal), np.array(m.turntable.T_color_turntable),
            np.array(truth["T_turntable_o_scan"]))
    size = (m.thermal_camera.width, m.thermal_camera.height)
    return args, size, np.load(root / "ground_truth/contact.npy")


def test_rig_session_matches_truth(rig_session):
    args, size, truth = _rig_inputs(rig_session)
    cm = build_contactmap(*args, PRESETS["default"], image_size=size)
    mae, iou, touched_seen = contact_scores(cm.contact, truth, cm.observed)
    assert mae <= 0.06, mae
    assert iou >= 0.85, iou
    assert touched_seen >= 0.95, touched_seen
    assert not cm.all_ambient
    assert abs(cm.ambient_k - 295.0) < 0.15  # the rig's ambient, never told to the stage
    assert cm.contact.dtype == np.float32 and cm.contact.min() >= 0 and cm.contact.max() <= 1
    assert np.all(cm.contact[~cm.observed] == 0) and np.isnan(cm.temperature_k[~cm.observed]).all()
    assert (cm.n_views_seen[cm.observed] >= 1).all() and (cm.per_view_visible > 0).all()
    # The bottom of an object resting on the platter is never seen: coverage is honest.
    assert 0.4 < cm.coverage < 0.98


def test_wrong_pose_is_worse_than_true_pose(rig_session):
    """The map depends on T_turntable_o_scan: a 90 deg turn scrambles it."""
    args, size, truth = _rig_inputs(rig_session)
    wrong = list(args)
    wrong[6] = args[6] @ rot_z(np.pi / 2)
    cm = build_contactmap(*wrong, image_size=size)
    _, iou, _ = contact_scores(cm.contact, truth, cm.observed)
    assert iou < 0.5, iou


# ------------------------------------------------------ real ContactDB maps


def _load_contactdb(shared_data: Path, name: str):
    m = trimesh.load(shared_data / "contactdb_contactmaps" / name, process=False, force="mesh")
    return (np.asarray(m.vertices, float), np.asarray(m.faces, np.int64),
            m.visual.vertex_colors[:, 0].astype(np.float64) / 255.0)


def render_thermal_views(vertices, faces, contact, T_color_turntable, T_turntable_o, n_views=12,
                         seed=0):
    """Thermal images of a mesh on a turntable: ambient + RISE_K * contact interpolated on
    the hit triangle, background at ambient - 0.3 K, Gaussian noise ``NOISE_K``."""
    rng = np.random.default_rng(seed)
    dirs = pixel_rays(K_TH, WIDTH, HEIGHT).astype(np.float32)
    views = []
    for k in range(n_views):
        angle = 2 * np.pi * k / n_views
        # the thermal camera is the colour one
        T_c_o = T_color_turntable @ rot_z(angle) @ T_turntable_o
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(transform_points(T_c_o, vertices).astype(np.float32),
                            faces.astype(np.uint32))
        ans = scene.cast_rays(o3d.core.Tensor(np.concatenate([np.zeros_like(dirs), dirs], -1)))
        hit = np.isfinite(ans["t_hit"].numpy())
        prim = np.where(hit, ans["primitive_ids"].numpy().astype(np.int64), 0)
        uv = ans["primitive_uvs"].numpy().astype(np.float64)
        c = contact[faces[prim]]  # (h, w, 3)
        value = (1 - uv[..., 0] - uv[..., 1]) * c[..., 0] + uv[..., 0] * c[..., 1] \
            + uv[..., 1] * c[..., 2]
        temp = np.where(hit, AMBIENT_K + RISE_K * value, AMBIENT_K - 0.3)
        temp += NOISE_K * rng.standard_normal(temp.shape)
        views.append((temp.astype(np.float32), angle))
    return views


def _upside_down(vertices) -> np.ndarray:
    """Rest the mesh upside down on the platter: ContactDB's zero-contact region is the
    bottom its own scan never saw, turned up here so ambient can be seen."""
    R = np.diag([1.0, -1.0, -1.0])
    v = vertices @ R.T
    centre = (v.min(0) + v.max(0)) / 2
    return make_T(R, [-centre[0], -centre[1], -v[:, 2].min()])


def test_real_contactdb_apple_rebuilt(shared_data):
    vertices, faces, contact = _load_contactdb(shared_data, "apple_textured.ply")
    T_color_turntable = look_at_turntable(distance_m=0.5, elevation_deg=30.0)
    T_turntable_o = _upside_down(vertices)
    views = render_thermal_views(vertices, faces, contact, T_color_turntable, T_turntable_o, seed=1)
    cm = build_contactmap(vertices, faces, views, K_TH, np.eye(4), T_color_turntable, T_turntable_o,
                          image_size=(WIDTH, HEIGHT))
    mae, iou, _ = contact_scores(cm.contact, contact, cm.observed)
    assert mae <= 0.06, mae
    assert iou >= 0.85, iou
    assert abs(cm.ambient_k - AMBIENT_K) < 0.1, cm.ambient_k
    assert cm.coverage > 0.6, cm.coverage
    assert (cm.per_view_visible > 0).all()

    # The same views with a known ambient and rise (a calibrated rig) agree as well.
    fixed = BuildContactmapConfig(ambient_mode=AmbientMode.FIXED, ambient_k=AMBIENT_K,
                                  rise_mode="fixed", full_rise_k=RISE_K)
    cm_fixed = build_contactmap(vertices, faces, views, K_TH, np.eye(4), T_color_turntable,
                                T_turntable_o, fixed)
    mae_fixed, _, _ = contact_scores(cm_fixed.contact, contact, cm_fixed.observed)
    assert mae_fixed <= 0.03, mae_fixed


def test_real_contactdb_controller_with_measured_ambient(shared_data):
    """The controller's zero-contact vertices sit in places no view here sees (9 % of them are
    observed), so its untouched level (~0.35 in ContactDB's encoding) is all the stage can take
    for ambient; with the room temperature measured (fixed ambient) the map comes back."""
    vertices, faces, contact = _load_contactdb(shared_data, "ps_controller_textured.ply")
    T_color_turntable = look_at_turntable(distance_m=0.5, elevation_deg=30.0)
    T_turntable_o = _upside_down(vertices)
    views = render_thermal_views(vertices, faces, contact, T_color_turntable, T_turntable_o, seed=2)
    cfg = BuildContactmapConfig(ambient_mode=AmbientMode.FIXED, ambient_k=AMBIENT_K)
    cm = build_contactmap(vertices, faces, views, K_TH, np.eye(4), T_color_turntable,
                          T_turntable_o, cfg)
    mae, iou, _ = contact_scores(cm.contact, contact, cm.observed)
    assert mae <= 0.06, mae
    assert iou >= 0.85, iou


# --------------------------------------------------------------- bad inputs


@pytest.fixture(scope="module")
def small_scene():
    """A 5 cm sphere with a warm cap, 6 clean views."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)
    contact = np.clip((v[:, 0] - 0.02) / 0.02, 0, 1)
    T_color_turntable = look_at_turntable(distance_m=0.5, elevation_deg=30.0)
    T_turntable_o = make_T(np.eye(3), [0, 0, 0.05])
    return v, f, contact, T_color_turntable, T_turntable_o


def test_wrong_size_view_is_an_error(small_scene):
    v, f, contact, T_color_turntable, T_turntable_o = small_scene
    views = render_thermal_views(v, f, contact, T_color_turntable, T_turntable_o, n_views=3)
    views[1] = (views[1][0][:-10], views[1][1])
    with pytest.raises(StageError, match="thermal view 1 is 320x246"):
        build_contactmap(v, f, views, K_TH, np.eye(4), T_color_turntable, T_turntable_o)
    with pytest.raises(StageError, match="expected 640x480"):
        build_contactmap(v, f, views[:1], K_TH, np.eye(4), T_color_turntable, T_turntable_o,
                         image_size=(640, 480))


def test_object_nowhere_in_view_is_an_error(small_scene):
    v, f, contact, T_color_turntable, T_turntable_o = small_scene
    views = render_thermal_views(v, f, contact, T_color_turntable, T_turntable_o, n_views=2)
    behind = make_T(np.eye(3), [0.0, 0.0, 5.0])  # turntable 5 m below: never in the image
    with pytest.raises(StageError, match="no thermal view sees the object"):
        build_contactmap(v, f, views, K_TH, np.eye(4), T_color_turntable, behind @ T_turntable_o)


def test_views_without_object_are_only_counted(small_scene):
    """Off the platter centre the object swings out of some views: they see 0 vertices."""
    v, f, contact, T_color_turntable, _ = small_scene
    T_turntable_o = make_T(np.eye(3), [0.3, 0.0, 0.05])
    views = render_thermal_views(v, f, contact, T_color_turntable, T_turntable_o, n_views=8)
    cm = build_contactmap(v, f, views, K_TH, np.eye(4), T_color_turntable, T_turntable_o)
    assert (cm.per_view_visible == 0).any() and (cm.per_view_visible > 0).sum() >= 2
    mae, _, _ = contact_scores(cm.contact, contact, cm.observed)
    assert mae <= 0.06, mae


def test_one_bad_view_cannot_dominate(small_scene):
    """A view whose pixels are all hot (a reflection, a wrong frame) is outvoted."""
    v, f, contact, T_color_turntable, T_turntable_o = small_scene
    views = render_thermal_views(v, f, contact, T_color_turntable, T_turntable_o, n_views=12)
    views[0] = (views[0][0] + 3.0, views[0][1])
    cm = build_contactmap(v, f, views, K_TH, np.eye(4), T_color_turntable, T_turntable_o)
    mae, iou, _ = contact_scores(cm.contact, contact, cm.observed)
    assert mae <= 0.06 and iou >= 0.85, (mae, iou)


def test_all_ambient_scan_is_a_flag(small_scene):
    v, f, _, T_color_turntable, T_turntable_o = small_scene
    views = render_thermal_views(v, f, np.zeros(len(v)), T_color_turntable, T_turntable_o,
                                 n_views=4)
    cm = build_contactmap(v, f, views, K_TH, np.eye(4), T_color_turntable, T_turntable_o)
    assert cm.all_ambient
    assert np.all(cm.contact == 0) and cm.observed.any()
    assert abs(cm.ambient_k - AMBIENT_K) < 0.05


def test_degenerate_faces_are_skipped(small_scene):
    v, f, contact, T_color_turntable, T_turntable_o = small_scene
    views = render_thermal_views(v, f, contact, T_color_turntable, T_turntable_o, n_views=6)
    clean = build_contactmap(v, f, views, K_TH, np.eye(4), T_color_turntable, T_turntable_o)
    # Zero-area faces: a repeated index and three collinear vertices of one edge.
    a, b = f[0, 0], f[0, 1]
    v2 = np.vstack([v, (v[a] + v[b]) / 2])
    extra = np.array([[a, a, b], [a, b, len(v)], [b, b, b]])
    f2 = np.vstack([f, extra])
    cm = build_contactmap(v2, f2, views, K_TH, np.eye(4), T_color_turntable, T_turntable_o)
    assert cm.n_degenerate_faces == 3
    assert np.abs(cm.contact[: len(v)] - clean.contact).max() < 1e-6
    assert not cm.observed[len(v)]  # the vertex on degenerate faces only has no normal
    normals, n_bad = vertex_normals(v2, f2)
    assert n_bad == 3 and np.allclose(np.linalg.norm(normals[: len(v)], axis=1), 1.0)
    with pytest.raises(StageError, match="index vertices"):
        build_contactmap(v, f + len(v), views, K_TH, np.eye(4), T_color_turntable, T_turntable_o)


def test_weighted_median():
    values = np.array([[1.0, 2.0, 100.0], [np.nan, 5.0, np.nan], [np.nan, np.nan, np.nan]])
    weights = np.array([[1.0, 1.0, 1.0], [1.0, 0.2, 1.0], [1.0, 1.0, 1.0]])
    out = weighted_median(values, weights)
    assert out[0] == 2.0 and out[1] == 5.0 and np.isnan(out[2])
    assert weighted_median(np.array([[1.0, 2.0, 3.0]]), np.array([[0.1, 0.1, 5.0]]))[0] == 3.0


def test_config_presets():
    assert STAGE_VERSION == "build_contactmap/4"
    assert set(PRESETS) >= {"default", "fixed_rise"}
    assert PRESETS["default"].digest() != PRESETS["fixed_rise"].digest()
    with pytest.raises(ValueError):
        BuildContactmapConfig(cos_minimum=0.2)
