"""pictures: sizes, keypoints where they were detected, contact coloured apart from no contact
and from unobserved, and the depth fallback of a session without colour video."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from graspcap.tasks.outputs.drawing import (
    MODEL_RGB,
    SKIN_RGB,
    UNOBSERVED_RGB,
    colorize_depth,
    confidence_rgb,
    decode_png,
    hand_depth_range,
)
from graspcap.tasks.outputs.pictures import (
    PRESETS,
    Background,
    contact_picture,
    keypoints_picture,
    model_keypoints,
    pictures,
    read_frame,
)
from graspcap.tasks.session.load_session import load_session
from tests.session_factory import DELETE, write_session

SMALL = PRESETS["default"].model_copy(update={"view_px": 96})


def hand_keypoints(rng: np.random.Generator) -> np.ndarray:
    """21 detections (x_px, y_px, conf) in the middle of a 320 x 240 frame (clear of the
    title and the legend), confidence 0.2 .. 1."""
    return np.column_stack([rng.uniform(100, 220, 21), rng.uniform(40, 140, 21),
                            rng.uniform(0.2, 1.0, 21)])


def test_keypoints_picture_size_and_dots_at_the_detections():
    rng = np.random.default_rng(3)
    frame = np.full((240, 320, 3), 90, np.uint8)
    kp = hand_keypoints(rng)
    kp[7, 2] = 0.0  # not detected: not drawn
    out = keypoints_picture(frame, kp, None, title="t")
    assert out.shape == (240, 320 + 240, 3) and out.dtype == np.uint8
    drawn = 0
    for j in np.argsort(-kp[:, 2])[:5]:  # the most confident dots are on top of the others
        x, y = np.rint(kp[j, :2]).astype(int)
        patch = out[y - 1:y + 2, x - 1:x + 2].reshape(-1, 3).astype(int)
        want = np.array(confidence_rgb(kp[j, 2]))
        drawn += bool(np.any(np.abs(patch - want).sum(axis=1) < 60))
    assert drawn >= 4
    x, y = np.rint(kp[7, :2]).astype(int)  # undetected keypoint: its dot is absent
    assert not np.any(np.abs(out[y, x].astype(int) - np.array(confidence_rgb(0.0))).sum() < 30)
    # a model joint (the others not projected) is a cyan cross where it was projected
    model = np.full((21, 2), np.nan)
    model[0] = (40.0, 100.0)
    out = keypoints_picture(frame, kp, model, title="t")
    assert out.shape == (240, 320 + 240, 3)
    assert np.abs(out[100, 40].astype(int) - MODEL_RGB).sum() < 60


def test_depth_fallback_when_the_session_has_no_colour(tmp_path):
    with_color = load_session(write_session(tmp_path / "a"))
    image, bg = read_frame(with_color, 1)
    assert bg == Background.COLOR and image.shape == (60, 80, 3) and image.dtype == np.uint8
    no_color = load_session(write_session(tmp_path / "b", grasp={"color": DELETE}))
    depth, bg = read_frame(no_color, 1)
    assert bg == Background.DEPTH and depth.shape == (60, 80) and depth.dtype == np.float32
    depth = np.kron(depth, np.ones((4, 4), np.float32))  # 320 x 240: room for the overlays
    kp = np.column_stack([np.linspace(100, 220, 21), np.linspace(60, 180, 21), np.ones(21)])
    out = pictures(depth, bg, kp, None, 1, session_id="s")
    img = decode_png(out.keypoints_png)
    assert out.background == Background.DEPTH and out.contact_png is None
    assert img.shape == (240, 320 + 240, 3)
    expected = colorize_depth(depth, hand_depth_range(depth, kp))
    # away from the keypoints, the zoom frame and the text, the left panel is the depth
    assert np.array_equal(img[30:50, 300:316], expected[30:50, 300:316])
    assert np.ptp(expected[depth > 0].astype(int)) > 50  # depth varies: so does the picture


def test_colorize_depth_near_bright_far_dark_missing_black():
    depth = np.tile(np.linspace(0.5, 1.0, 50, dtype=np.float32), (10, 1))
    depth[:, :5] = 0.0
    img = colorize_depth(depth)
    brightness = img.astype(int).sum(axis=2)
    assert np.all(img[:, :5] == 0)
    assert brightness[0, 6] > brightness[0, 25] > brightness[0, 49]


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    contact = np.clip((V[:, 0] / 0.05 - 0.6) / 0.3, 0, 1)  # the +x cap is contacted
    return V, F, contact


def _object_pixels(img: np.ndarray, row: int, size: int) -> np.ndarray:
    """Pixels (k, 3) of view row ``row`` that are not background."""
    band = img[30 + row * size:30 + (row + 1) * size].reshape(-1, 3).astype(int)
    return band[np.abs(band - 245).sum(axis=1) > 15]


def test_contact_picture_colours_contact_apart_from_no_contact_and_unobserved(sphere):
    V, F, contact = sphere
    seen = np.ones(len(V), bool)
    size = SMALL.view_px
    with_contact = contact_picture(V, F, contact, seen, config=SMALL)
    no_contact = contact_picture(V, F, np.zeros(len(V)), seen, config=SMALL)
    unobserved = contact_picture(V, F, contact, np.zeros(len(V), bool), config=SMALL)
    assert with_contact.shape == (30 + size + 34, 4 * size, 3)
    # view 0 looks along -x at the contacted cap: red where contact is, blue elsewhere
    view0 = with_contact[30:30 + size, :size].astype(int)
    centre = view0[size // 2 - 3:size // 2 + 3, size // 2 - 3:size // 2 + 3].reshape(-1, 3)
    assert np.all(centre[:, 0] > centre[:, 2] + 60)  # red
    blank = _object_pixels(no_contact, 0, size)
    assert np.all(blank[:, 2] > blank[:, 0])  # blue: no contact anywhere
    grey = _object_pixels(unobserved, 0, size)
    assert np.all(np.ptp(grey, axis=1) <= 2)  # grey: unobserved, neither blue nor red
    assert np.abs(grey.mean(axis=0) - blank.mean(axis=0)).sum() > 80
    assert grey.max() <= max(UNOBSERVED_RGB)
    # the view opposite the cap (azimuth 180) sees no contact
    back = with_contact[30:30 + size, 2 * size:3 * size].reshape(-1, 3).astype(int)
    back = back[np.abs(back - 245).sum(axis=1) > 15]
    assert np.mean(back[:, 0] > back[:, 2]) < 0.05


def test_contact_picture_with_the_hand_adds_a_row_in_skin_colour(sphere):
    V, F, contact = sphere
    box = trimesh.creation.box(extents=(0.03, 0.03, 0.03))
    hand = (np.asarray(box.vertices) + [0.065, 0.0, 0.0], np.asarray(box.faces))
    size = SMALL.view_px
    img = contact_picture(V, F, contact, np.ones(len(V), bool), hand, title="s", config=SMALL)
    assert img.shape == (30 + 2 * size + 34, 4 * size, 3)
    skin = np.array(SKIN_RGB, float)
    top, bottom = _object_pixels(img, 0, size), _object_pixels(img, 1, size)

    def skin_like(px: np.ndarray) -> np.ndarray:  # a shade of the skin colour
        scale = (px @ skin) / (skin @ skin)
        return np.abs(px - scale[:, None] * skin).sum(axis=1) < 12

    assert skin_like(top).mean() < 0.01  # the top row is the object alone
    assert skin_like(bottom).mean() > 0.05  # the hand shows in the bottom row


def test_model_keypoints_projects_the_hand_into_the_frames_camera():
    """Joints 1 m ahead of frame 12's camera (moved 0.1 m along x) land where K puts them; the
    outliers are that camera's rejected observations; a frame without a camera is an error."""
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    T_w_c = np.stack([np.eye(4)] * 3)
    T_w_c[1, 0, 3] = 0.1
    inlier = np.ones((3, 21), bool)
    inlier[1, [2, 5]] = False
    joints_w = np.zeros((21, 3))
    joints_w[:, 2] = 1.0
    joints_w[:, 0] = np.linspace(-0.1, 0.1, 21)
    px, outlier = model_keypoints(K, 12, np.array([10, 12, 14]), T_w_c, inlier, joints_w)
    np.testing.assert_allclose(px[:, 0], 50 + 100 * (joints_w[:, 0] - 0.1))
    np.testing.assert_allclose(px[:, 1], 40.0)
    assert np.flatnonzero(outlier).tolist() == [2, 5]
    with pytest.raises(ValueError, match="frame 11 has no camera"):
        model_keypoints(K, 11, np.array([10, 12, 14]), T_w_c, inlier, joints_w)


# --- the report's pictures: the object at T_c_o, the strip, the reasons, the contact mesh ---

def _box() -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    return np.asarray(box.vertices, float), np.asarray(box.faces, np.int64)


def test_reprojection_picture_outlines_the_object_where_T_c_o_puts_it():
    from graspcap.tasks.outputs.pictures import reprojection_picture

    V, F = _box()
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    T_c_o = np.eye(4)
    T_c_o[:3, 3] = (0.1, 0.0, 0.6)  # centre at pixel (160 + 300 * 0.1 / 0.6, 120) = (210, 120)
    frame = np.zeros((240, 320, 3), np.uint8)
    out = reprojection_picture(frame, V, F, T_c_o, K, title="t")
    assert out.shape == frame.shape
    tinted = out.astype(int).sum(axis=2) > 60  # the silhouette (and the text): lit on black
    assert tinted[120, 210] and tinted[100, 190] and tinted[140, 230]
    # the box's face spans 300 * 0.1 / 0.55 = 55 px at its nearest: nothing lit far left of it
    assert not tinted[60:180, 20:150].any()
    # moved by 10 cm the outline moves with it: the check of T_c_o
    T_c_o[0, 3] = -0.1
    moved = reprojection_picture(frame, V, F, T_c_o, K).astype(int).sum(axis=2) > 60
    assert moved[120, 110] and not moved[120, 210]
    behind = T_c_o.copy()
    behind[2, 3] = -0.6  # behind the camera: nothing drawn, no error
    assert not (reprojection_picture(frame, V, F, behind, K)[30:200] > 0).any()


def test_strip_spreads_small_frames_across_the_video():
    from graspcap.tasks.outputs.pictures import strip_indices, strip_picture

    assert strip_indices(40, 5) == [0, 10, 20, 29, 39]
    assert strip_indices(3, 5) == [0, 1, 2] and strip_indices(0, 5) == []
    V, F = _box()
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    T_c_o = np.eye(4)
    T_c_o[2, 3] = 0.6
    frames = [(i, np.zeros((240, 320, 3), np.uint8), None, T_c_o if i >= 20 else None)
              for i in strip_indices(40, 5)]
    out = strip_picture(frames, (V, F), K, steady_from=20, height_px=60)
    assert out.shape == (60 + 22, 5 * 80, 3)
    body = out[22:]
    cyan = np.all(np.abs(body.astype(int) - MODEL_RGB) < 60, axis=2)
    assert not cyan[:, :160].any() and cyan[:, 160:].any()  # outlines on steady frames only


def test_reasons_are_written_under_a_picture():
    from graspcap.tasks.outputs.pictures import with_reasons

    img = np.zeros((50, 300, 3), np.uint8)
    assert with_reasons(img, ()) is img
    out = with_reasons(img, ("reprojection RMSE 9.1 px > 8.00 px", "x" * 500), ("a note",))
    assert out.shape == (50 + 10 + 18 * 3, 300, 3) and np.array_equal(out[:50], img)
    assert (out[50:] > 100).any()  # text drawn in the band


def test_contact_ply_colours_every_vertex_by_its_contact():
    import io

    from graspcap.tasks.outputs.drawing import contact_rgb
    from graspcap.tasks.outputs.pictures import contact_ply

    V, F = _box()
    contact = np.linspace(0, 1, len(V))
    observed = np.ones(len(V), bool)
    observed[0] = False
    data = contact_ply(V, F, contact, observed)
    mesh = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    np.testing.assert_allclose(mesh.vertices, V)
    assert np.array_equal(mesh.faces, F)
    colours = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(int)
    assert np.array_equal(colours[0], UNOBSERVED_RGB)
    want = np.clip(contact_rgb(contact[1:]), 0, 255).astype(np.uint8)
    assert np.array_equal(colours[1:], want)
