"""Stages on valid but unusual input: a reason that names the input and the likely cause (or a
note when the stage can go on), never a raw IndexError (issue 15, item 5)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from graspcap.synth import generate
from graspcap.tasks import pipeline
from graspcap.tasks.contact.build_contactmap import (
    BuildContactmapConfig,
    build_contactmap,
    lowest_peak,
)
from graspcap.tasks.core.errors import StageError, check_mesh
from graspcap.tasks.core.geometry import make_T, pose_error
from graspcap.tasks.core.mesh_proxy import mesh_proxy
from graspcap.tasks.hand_sfm.reconstruct_hand import reconstruct_hand
from graspcap.tasks.keypoints.detect_keypoints import (
    DetectKeypointsConfig,
    corrupt_frames,
    detect_keypoints,
)
from graspcap.tasks.object_pose.register_object import register_object
from graspcap.tasks.object_pose.register_scan import PRESETS as register_scan_presets
from graspcap.tasks.object_pose.register_scan import register_scan
from graspcap.tasks.outputs.qa_metrics import stage_notes
from graspcap.tasks.session.load_session import load_session
from tests.registration_rig import look_at_turntable
from tests.session_factory import write_session

CONFIGS = pipeline.configs_for()


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    """A realistic synthetic session of 32 frames."""
    (root,) = generate(tmp_path_factory.mktemp("synth"), sessions=1, seed=5,
                       difficulty="realistic", frames=32)
    return root


def _variant(src: Path, dst: Path, edit=None) -> Path:
    """A copy of session ``src`` at ``dst`` with ``edit(manifest, folder)`` applied."""
    shutil.copytree(src, dst)
    manifest = json.loads((dst / "session.json").read_text())
    if edit is not None:
        edit(manifest, dst)
    (dst / "session.json").write_text(json.dumps(manifest))
    return dst


def _run(folder: Path, *stages: str, **given) -> dict:
    """Run ``stages`` of ``folder`` in order; ``given`` results stand in for upstream stages
    (no hand is: build_contactmap runs without carrying its map to one)."""
    results = {"load_session": pipeline.run_stage(
        pipeline.STAGES["load_session"], folder, CONFIGS["load_session"], {}),
        "select_steady": None, "fit_hand": None, "estimate_adjustment": None, **given}
    configs = dict(CONFIGS)
    configs["build_contactmap"] = CONFIGS["build_contactmap"].model_copy(
        update={"align_to_hand": False})
    for name in stages:
        results[name] = pipeline.run_stage(pipeline.STAGES[name], folder, configs[name], results)
    return results


def _true_scan_pose(folder: Path) -> SimpleNamespace:
    """A register_scan result holding the generator's true scan pose."""
    truth = json.loads((folder / "ground_truth/truth.json").read_text())
    return SimpleNamespace(T_turntable_o_scan=np.asarray(truth["T_turntable_o_scan"]))


def _zero_thermal(views: list[int] | None):
    """An edit writing all-zero thermal images for ``views`` (None: every view)."""
    def edit(manifest, folder):
        for j in range(len(manifest["scan"]["views"])) if views is None else views:
            path = folder / manifest["scan"]["views"][j]["thermal"]
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(path), np.zeros_like(image))
    return edit


# ------------------------------------------------------------------ build_contactmap


def test_all_zero_thermal_images_fail_naming_the_files(synth, tmp_path):
    folder = _variant(synth, tmp_path / "s", _zero_thermal(None))
    n = len(load_session(folder, check_images=False).manifest.scan.views)
    with pytest.raises(StageError) as err:
        _run(folder, "build_contactmap", register_scan=_true_scan_pose(folder))
    assert str(err.value) == (
        "build_contactmap: no thermal view holds a thermal image: thermal views "
        "0 (scan/thermal/000.png), 1 (scan/thermal/001.png), 2 (scan/thermal/002.png), "
        f"3 (scan/thermal/003.png) and {n - 4} more are all 0 K (no reading); check the scan's "
        "thermal PNGs (centi-kelvin, uint16) and the thermal camera")


def test_a_blank_view_is_left_out_with_a_note(synth, tmp_path):
    """One all-zero view among 15: the map is the one built without that view."""
    def drop_view_3(manifest, folder):
        del manifest["scan"]["views"][3]

    blank = _variant(synth, tmp_path / "blank", _zero_thermal([3]))
    pose = _true_scan_pose(blank)
    cm = _run(blank, "build_contactmap", register_scan=pose)["build_contactmap"]
    without = _variant(synth, tmp_path / "without", drop_view_3)
    ref = _run(without, "build_contactmap", register_scan=pose)["build_contactmap"]
    assert cm.notes == ("thermal view 3 (scan/thermal/003.png) is all 0 K (no reading): "
                        "left out",)
    assert cm.per_view_visible[3] == 0
    assert np.array_equal(cm.contact, ref.contact)
    assert np.array_equal(cm.observed, ref.observed)
    assert ref.notes == ()


def test_a_constant_view_is_left_out_and_zero_kelvin_pixels_are_not_read(synth, tmp_path):
    def edit(manifest, folder):
        views, cam = manifest["scan"]["views"], manifest["thermal_camera"]
        cv2.imwrite(str(folder / views[0]["thermal"]),
                    np.full((cam["height"], cam["width"]), 29_500, np.uint16))
        for j in (1, 2):  # the left half of two views reads 0 K
            path = folder / views[j]["thermal"]
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            image[:, : image.shape[1] // 2] = 0
            cv2.imwrite(str(path), image)

    folder = _variant(synth, tmp_path / "s", edit)
    cm = _run(folder, "build_contactmap", register_scan=_true_scan_pose(folder))[
        "build_contactmap"]
    assert cm.notes == ("thermal view 0 (scan/thermal/000.png) is one constant 295.00 K (no "
                        "thermal contrast: a blank or placeholder frame): left out",)
    assert np.nanmin(cm.temperature_k) > 250.0  # no 0 K sample reached a vertex


def test_one_scan_view_builds_with_a_note_on_what_it_covers(synth, tmp_path):
    def one_view(manifest, folder):
        manifest["scan"]["views"] = manifest["scan"]["views"][:1]

    folder = _variant(synth, tmp_path / "s", one_view)
    results = _run(folder, "register_scan", "build_contactmap")
    cm = results["build_contactmap"]
    share = round(100 * cm.coverage)
    assert 10 <= share <= 60
    assert cm.notes == (f"one thermal view only: the contact map covers what one view sees "
                        f"({share} % of the vertices observed)",)
    assert f"build_contactmap: {cm.notes[0]}" in stage_notes(results)


def test_one_temperature_has_its_ambient_peak():
    """A histogram of one bin used to index past its end (IndexError: index 2)."""
    assert lowest_peak(np.full(40, 295.0), 0.05, 0.2) == 295.0
    assert lowest_peak(np.array([295.0, 295.02]), 0.05, 0.2) == pytest.approx(295.01)


# ------------------------------------------------------------------ meshes


def test_face_index_out_of_range_names_the_mesh_in_every_stage(synth, tmp_path):
    session = load_session(synth, check_images=False)
    V, F = session.read_mesh()
    bad = F.copy()
    bad[7, 1] = len(V) + 2
    why = (f"object_mesh {session.manifest.object_mesh}: 1 face(s) index vertices that do not "
           f"exist (face 7 has index {len(V) + 2}; the mesh has {len(V)} vertices, "
           f"0..{len(V) - 1}): a truncated or corrupt mesh file")
    name = f"object_mesh {session.manifest.object_mesh}"
    depth = session.read_depth_m(session.manifest.stage1.depth)
    K, T_ct = session.color_K, session.T_color_turntable
    with pytest.raises(StageError, match=re.escape(f"register_object: {why}")):
        register_object(depth, K, T_ct, V, bad, mesh_name=name)
    with pytest.raises(StageError, match=re.escape(f"register_scan: {why}")):
        register_scan([(depth, 0.0)], K, T_ct, V, bad, mesh_name=name)
    cam = session.manifest.thermal_camera
    views = [(np.full((cam.height, cam.width), 295.0), 0.0)]
    with pytest.raises(StageError, match=re.escape(f"build_contactmap: {why}")):
        build_contactmap(V, bad, views, np.asarray(cam.K), np.eye(4), T_ct, np.eye(4),
                         mesh_name=name)
    negative = F.copy()
    negative[0, 0] = -1
    with pytest.raises(StageError, match="face 0 has index -1"):
        check_mesh("s", V, negative)
    with pytest.raises(StageError, match="no face has a non-zero area"):
        check_mesh("s", V, np.zeros((3, 3), np.int64))
    with pytest.raises(StageError, match=r"faces must be triangles \(m, 3\)"):
        check_mesh("s", V, np.zeros((0, 3), np.int64))


# ------------------------------------------------------------------ register_scan


def test_views_at_the_same_angle_are_used_and_noted(synth, tmp_path):
    """View 1 claims view 0's angle: both are used; the note gives each one's fitness, so the
    wrongly labelled one (it fits much worse) can be found."""
    def same_angle(manifest, folder):
        views = manifest["scan"]["views"]
        views[1]["angle_deg"] = views[0]["angle_deg"]

    folder = _variant(synth, tmp_path / "s", same_angle)
    results = _run(folder)
    results["register_scan"] = scan = pipeline.run_stage(
        pipeline.STAGES["register_scan"], folder, register_scan_presets["fast"], results)
    fit = scan.per_view_fitness
    assert fit[0] > 0.8 and fit[1] < 0.5
    assert scan.notes == (
        f"2 scan views share angle_deg 0: view 0 (scan/depth/000.png), view 1 "
        f"(scan/depth/001.png) (fitness under the final pose {fit[0]:.2f}, {fit[1]:.2f}); all "
        "used (a view that fits much worse than its twin has a wrong angle_deg)",)
    assert f"register_scan: {scan.notes[0]}" in stage_notes(results)


# ------------------------------------------------------------------ detect_keypoints


def _hand(x0: float, y0: float, conf: float = 0.8) -> np.ndarray:
    """A hand-like (21, 3): five fingers of four joints fanned out from a wrist."""
    h = np.zeros((21, 3))
    h[0, :2] = x0, y0
    for f in range(5):
        a = np.radians(-60 + 30 * f)
        for j in range(4):
            r = 6.0 + 3.0 * j
            h[1 + 4 * f + j, :2] = x0 + r * np.sin(a), y0 - r * np.cos(a)
    h[:, 2] = conf
    return h


def _keypoint_session(tmp_path: Path, frames: list[list[dict]], **overrides) -> Path:
    """A factory session whose keypoint files hold ``frames[i]`` as their ``people``."""
    folder = write_session(tmp_path / "s", frames=len(frames), **overrides)
    for i, people in enumerate(frames):
        path = folder / f"grasp/keypoints/{i:06d}_keypoints.json"
        path.write_text(json.dumps({"version": 1.3, "people": people}))
    return folder


def _person(right=None, left=None) -> dict:
    flat = lambda h: [] if h is None else np.asarray(h).ravel().tolist()  # noqa: E731
    return {"hand_right_keypoints_2d": flat(right), "hand_left_keypoints_2d": flat(left)}


def test_keypoint_files_of_the_other_hand_fail_saying_so(tmp_path):
    folder = _keypoint_session(tmp_path, [[_person(left=_hand(40, 40))]] * 6)
    with pytest.raises(StageError) as err:
        detect_keypoints(load_session(folder), DetectKeypointsConfig())
    assert str(err.value) == (
        "session p01-box-use-01: detect_keypoints: the keypoint files hold the other hand: "
        "6 of 6 frames have hand_left_keypoints_2d, none has hand_right_keypoints_2d "
        "(session.json says hand: right); check `hand` in session.json (e.g. "
        "grasp/keypoints/000000_keypoints.json)")


def test_keypoints_far_outside_the_image_are_not_detections(tmp_path):
    far = _hand(40, 40)
    far[:, 0] = 1e8
    frames = [[_person(right=_hand(40 + i, 40))] for i in range(8)]
    frames[2] = frames[5] = [_person(right=far)]
    folder = _keypoint_session(tmp_path, frames)
    kp = detect_keypoints(load_session(folder), DetectKeypointsConfig())
    assert kp.off_image_frames == (2, 5)
    assert (kp.keypoints[[2, 5]] == 0).all() and kp.frames_with_hand == 6
    notes = {n.frame: n for n in kp.notes}
    assert notes[2].file == "grasp/keypoints/000002_keypoints.json"
    assert notes[2].message == (
        "people[0] keypoint(s) " + str(list(range(21))) + " (e.g. at 1e+08, 40 px) far outside "
        "the 80x60 image; treated as not detected")
    assert kp.qa_notes() == [
        "detect_keypoints: 2 frame(s) had keypoints far outside the image, treated as not "
        "detected (grasp/keypoints/000002_keypoints.json, grasp/keypoints/000005_keypoints.json)"]


def test_too_few_frames_left_says_why(tmp_path):
    """Keypoints off the image in all but 3 frames: select_steady's failure says so, and
    reconstruct_hand's when steady_from is given."""
    far = _hand(40, 40)
    far[:, 1] = -1e8
    frames = [[_person(right=_hand(40, 40) if i < 3 else far)] for i in range(8)]
    folder = _keypoint_session(tmp_path, frames)
    results = _run(folder, "detect_keypoints")
    with pytest.raises(StageError) as err:
        pipeline.run_stage(pipeline.STAGES["select_steady"], folder, CONFIGS["select_steady"],
                           results)
    assert str(err.value) == (
        "select_steady: cannot detect the steady phase: fewer than 5 frames have >= 6 detected "
        "joints; of 8 frames, 3 have a right hand detected; 5 had keypoints far outside the "
        "image (grasp/keypoints/000003_keypoints.json, grasp/keypoints/000004_keypoints.json, "
        "grasp/keypoints/000005_keypoints.json, grasp/keypoints/000006_keypoints.json, "
        "grasp/keypoints/000007_keypoints.json)")
    with pytest.raises(StageError, match=r"no keypoint detected .* in frames 3\.\.7; of 8 "
                                         r"frames, 3 have a right hand detected; 5 had"):
        reconstruct_hand(results["detect_keypoints"].keypoints, np.eye(3), 3,
                         np.zeros((8, 60, 80)), np.zeros(21),
                         why_missing=results["detect_keypoints"].missing_summary())


def test_two_people_pick_deterministically_and_are_counted(tmp_path):
    """The first detection is the most confident hand, then the one nearest the previous;
    the order of people in the files does not change the pick."""
    mine = [_hand(20 + i, 30, 0.9) for i in range(6)]
    other = [_hand(60 - i, 30, 0.5) for i in range(6)]
    frames = [[_person(right=other[i]), _person(right=mine[i])] if i in (0, 2, 3) else
              [_person(right=mine[i])] for i in range(6)]
    picks = []
    for k, order in enumerate((frames, [list(reversed(p)) for p in frames])):
        kp = detect_keypoints(load_session(_keypoint_session(tmp_path / f"{k}", order)),
                              DetectKeypointsConfig())
        assert kp.multi_candidate_frames == 3
        assert kp.qa_notes() == [
            "detect_keypoints: 3 of 6 frames had more than one right hand (several people); "
            "the one nearest the previous frame's hand was used (the most confident at the "
            "first)"]
        picks.append(kp.keypoints)
    assert np.array_equal(picks[0], picks[1])
    assert np.allclose(picks[0], np.array(mine))


def test_one_corrupt_keypoint_file_is_dropped_and_named(synth, tmp_path):
    """A shuffled frame and a collapsed one among 32: dropped with notes naming their files,
    the steady onset as without them."""
    clean = _run(synth, "detect_keypoints", "select_steady")

    def corrupt(manifest, folder):
        for frame, how in ((12, "shuffle"), (25, "collapse")):
            path = folder / manifest["grasp"]["keypoints"].format(index=frame)
            doc = json.loads(path.read_text())
            hand = np.array(doc["people"][0]["hand_right_keypoints_2d"]).reshape(21, 3)
            if how == "shuffle":
                hand[:, :2] = hand[np.random.default_rng(1).permutation(21), :2]
            else:
                hand[:, :2] = hand[0, :2]
            doc["people"][0]["hand_right_keypoints_2d"] = hand.ravel().tolist()
            path.write_text(json.dumps(doc))

    folder = _variant(synth, tmp_path / "s", corrupt)
    results = _run(folder, "detect_keypoints", "select_steady")
    kp = results["detect_keypoints"]
    assert kp.corrupt_frames == (12, 25)
    assert (kp.keypoints[[12, 25]] == 0).all()
    assert kp.qa_notes() == [
        "detect_keypoints: 2 frame(s) whose joints do not form the hand of their neighbours were "
        "dropped (grasp/keypoints/000012_keypoints.json, grasp/keypoints/000025_keypoints.json)"]
    notes = {n.frame: n.message for n in kp.notes}
    assert "shuffled or garbage" in notes[12] and "(all at one point)" in notes[25]
    assert results["select_steady"].steady_from == clean["select_steady"].steady_from
    assert corrupt_frames(clean["detect_keypoints"].keypoints, DetectKeypointsConfig()) == {}


def test_keypoint_notes_reach_the_qa_notes():
    kp = SimpleNamespace(qa_notes=lambda: ["detect_keypoints: a"])
    scan = SimpleNamespace(notes=("b",))
    contact = SimpleNamespace(notes=("c",))
    assert stage_notes({"detect_keypoints": kp, "register_scan": scan,
                        "build_contactmap": contact}) == [
        "detect_keypoints: a", "register_scan: b", "build_contactmap: c"]
    assert "detect_keypoints" in pipeline.STAGES["qa_metrics"].upstream


# ------------------------------------------------------------------ very fine meshes


def test_mesh_proxy_stands_for_every_vertex_within_its_cell():
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.05)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)
    proxy = mesh_proxy(V, F, 2000)
    assert not proxy.is_original and 500 <= len(proxy.faces) <= 2000
    assert proxy.of_vertex.shape == (len(V),) and proxy.of_vertex.max() == len(proxy.vertices) - 1
    moved = np.linalg.norm(V - proxy.vertices[proxy.of_vertex], axis=1)
    assert moved.max() <= np.sqrt(3) * proxy.voxel_m
    assert len(np.unique(np.sort(proxy.faces, axis=1), axis=0)) == len(proxy.faces)
    same = mesh_proxy(V, F, len(F))
    assert same.is_original and same.vertices is not None and np.array_equal(same.faces, F)
    assert np.array_equal(same.of_vertex, np.arange(len(V)))


def test_a_fine_mesh_gets_a_contact_map_per_vertex_through_its_proxy():
    """The map of a 20480-face sphere computed on a proxy of at most 2000 faces: one value per
    vertex in file order, as close to the truth as the map computed on the mesh itself."""
    import trimesh

    from tests.tasks.contact.test_contactmap import K_TH, contact_scores, render_thermal_views

    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.05)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)
    truth = np.clip((V[:, 0] - 0.02) / 0.02, 0, 1)
    T_ct = look_at_turntable(distance_m=0.5, elevation_deg=30.0)
    T_to = make_T(np.eye(3), [0, 0, 0.05])
    views = render_thermal_views(V, F, truth, T_ct, T_to, n_views=6)
    cfg = BuildContactmapConfig(proxy_faces=2000)
    cm = build_contactmap(V, F, views, K_TH, np.eye(4), T_ct, T_to, cfg)
    full = build_contactmap(V, F, views, K_TH, np.eye(4), T_ct, T_to)
    assert cm.contact.shape == (len(V),) and cm.observed.shape == (len(V),)
    assert len(cm.notes) == 1 and re.fullmatch(
        r"object mesh of 20480 faces: visibility and sampling on a proxy of \d+ faces "
        r"\(vertices clustered on a \d\.\d\d mm grid\)", cm.notes[0])
    assert full.notes == ()
    mae, iou, _ = contact_scores(cm.contact, truth, cm.observed)
    assert mae <= 0.06 and iou >= 0.9, (mae, iou)
    assert abs(cm.coverage - full.coverage) <= 0.03
    assert cm.per_view_visible.sum() == cm.n_views_seen.sum()


def test_a_fine_mesh_is_registered_through_its_proxy(synth):
    """register_scan on the session's mesh with a proxy of at most 2000 faces: the true pose."""
    session = load_session(synth, check_images=False)
    V, F = session.read_mesh()
    assert len(F) > 2000
    views = [(session.read_depth_m(v.depth), np.radians(v.angle_deg))
             for v in session.manifest.scan.views]
    cfg = register_scan_presets["fast"].model_copy(update={"proxy_faces": 2000})
    scan = register_scan(views, session.color_K, session.T_color_turntable,
                         V, F, cfg)
    truth = _true_scan_pose(synth).T_turntable_o_scan
    rot_deg, trans_m = pose_error(scan.T_turntable_o_scan, truth)
    assert rot_deg < 3.0 and trans_m < 0.005, (rot_deg, trans_m)
    assert scan.notes[0].startswith(f"object mesh of {len(F)} faces: registered on a proxy of ")
