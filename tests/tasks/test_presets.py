"""Pipeline presets are one checked table; ``--set`` overrides are checked against the model."""

from __future__ import annotations

import pytest

from graspcap.cli import build_parser
from graspcap.flows.commands import run_build
from graspcap.tasks import pipeline
from graspcap.tasks.core.presets import PIPELINE_PRESETS, UnknownPreset, apply_settings


def test_the_table_names_exactly_the_stage_presets():
    defined = {name for stage in pipeline.STAGES.values() for name in stage.presets}
    assert defined == set(PIPELINE_PRESETS)
    assert pipeline.preset_stages("openpose") == ("select_steady", "reconstruct_hand")
    assert pipeline.preset_stages("default") == tuple(pipeline.STAGES)


def test_an_unknown_preset_is_an_error_listing_the_known_ones():
    with pytest.raises(UnknownPreset) as info:
        pipeline.configs_for("fsat")
    assert str(info.value).startswith("unknown preset 'fsat'; known presets: default, fast,")
    assert all(name in str(info.value) for name in PIPELINE_PRESETS)


def test_the_cli_offers_exactly_the_table(capsys):
    parser = build_parser()
    args = parser.parse_args(["build", "x", "--preset", "paper", "--set", "fit_hand.loss=cauchy"])
    assert args.preset == "paper" and args.settings == ["fit_hand.loss=cauchy"]
    with pytest.raises(SystemExit) as info:
        parser.parse_args(["build", "x", "--preset", "fsat"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'fsat'" in err and "'strict_visibility'" in err


def test_settings_override_fields_over_the_preset():
    configs = pipeline.settings_overrides(
        ["reconstruct_hand.huber_k=1.5", "register_object.registration.n_restarts=3",
         "fit_hand.loss=cauchy"], preset="fast")
    assert set(configs) == {"reconstruct_hand", "register_object", "fit_hand"}
    assert configs["reconstruct_hand"].huber_k == 1.5
    fast = pipeline.configs_for("fast")["register_object"]
    assert configs["register_object"] == fast.model_copy(
        update={"registration": fast.registration.model_copy(update={"n_restarts": 3})})
    assert configs["fit_hand"].loss.value == "cauchy"


@pytest.mark.parametrize(("setting", "message"), [
    ("reconstruct_hand.huber_kk=1", "reconstruct_hand has no field 'huber_kk'; its fields"),
    ("register_object.registration.nope=1", "register_object.registration has no field 'nope'"),
    ("nostage.x=1", "no stage 'nostage'; stages are ['load_session'"),
    ("reconstruct_hand.huber_k=abc", "valid number"),
    ("reconstruct_hand", "expected STAGE.FIELD=VALUE"),
])
def test_a_wrong_setting_names_itself(setting, message):
    with pytest.raises(ValueError, match="--set") as info:
        pipeline.settings_overrides([setting])
    assert setting in str(info.value) and message in str(info.value)


def test_build_refuses_a_wrong_setting_before_building(tmp_path, capsys):
    code = run_build([tmp_path], tmp_path / "cat", settings=["fit_hand.nope=1"])
    assert code == 2
    assert "fit_hand has no field 'nope'" in capsys.readouterr().err
    assert not (tmp_path / "cat").exists()


def test_apply_settings_needs_only_the_configs():
    """``core.presets.apply_settings`` on plain configs by stage name (no stage table)."""
    from graspcap.tasks.hand.fit_hand import PRESETS as FIT
    from graspcap.tasks.hand_sfm.select_steady import PRESETS as STEADY

    base = {"fit_hand": FIT["default"], "select_steady": STEADY["default"]}
    out = apply_settings(["fit_hand.loss=cauchy"], base)
    assert out == {"fit_hand": FIT["default"].model_copy(update={"loss": out["fit_hand"].loss})}
    assert out["fit_hand"].loss.value == "cauchy" and base["fit_hand"].loss.value != "cauchy"
    assert apply_settings([], base) == {}
    with pytest.raises(ValueError, match=r"no stage 'qa_metrics'; stages are \['fit_hand', "):
        apply_settings(["qa_metrics.x=1"], base)
