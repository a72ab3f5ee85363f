"""What a good session is (``GOOD_IF``) and the QA confusion table built on it."""

from __future__ import annotations

from graspcap.synth.evaluate import GOOD_IF, confusion_markdown, good_session, qa_confusion

GOOD = {"refined_joints_mm": 4.0, "fit_joints_mm": 9.0, "camera_rot_deg": 0.5,
        "camera_trans_mm": 3.0, "frame_object_rot_sym_deg": 1.0,
        "frame_object_trans_sym_mm": 2.0, "object_stage1_rot_sym_deg": 0.3,
        "contact_near_hand_refined": 0.9}


def test_a_session_within_every_tolerance_is_good_and_the_final_hand_is_the_refined_one():
    assert good_session(GOOD) == (True, "")
    # the fitted hand is judged only where no refined one exists
    fit_only = {k: v for k, v in GOOD.items() if k != "refined_joints_mm"}
    good, why = good_session(fit_only)
    assert not good and why == "final_joints_mm 9.00 (good <= 5)"


def test_each_tolerance_and_a_missing_quantity_make_a_session_not_good():
    for name, (limit, op) in GOOD_IF.items():
        key = "refined_joints_mm" if name == "final_joints_mm" else name
        worse = dict(GOOD, **{key: limit * 1.01 if op == "<=" else limit * 0.99})
        good, why = good_session(worse)
        assert not good and why.startswith(f"{name} "), (name, why)
        missing = {k: v for k, v in GOOD.items() if k not in (key, "fit_joints_mm")}
        assert good_session(missing) == (False, f"{name} not measured")
    assert good_session(GOOD, "reconstruct_hand: too few inliers") == (
        False, "stage failed: reconstruct_hand: too few inliers")


def test_confusion_counts_precision_and_yield():
    rows = ([(True, "ok")] * 8 + [(True, "flagged")] * 2 + [(False, "ok")]
            + [(False, "flagged")] * 3 + [(False, "failed")] * 4)
    c = qa_confusion(rows)
    assert c["table"] == {"good": {"ok": 8, "flagged": 2, "failed": 0},
                          "not good": {"ok": 1, "flagged": 3, "failed": 4}}
    assert c["precision"] == 8 / 9 and c["yield"] == 0.8
    text = confusion_markdown(c)
    assert "| good | 8 | 2 | 0 | 10 |" in text and "precision (good among ok) 0.89" in text
    assert qa_confusion([])["precision"] is None
