"""The named pipeline presets: the one table ``--preset`` offers and ``configs_for`` checks.

A pipeline preset is a name; each stage module's ``PRESETS`` says what the name sets for that
stage, and a stage without it keeps its ``default``. This table lists every name a stage
defines (``tasks/pipeline.py`` refuses at import a stage preset missing here, and the tests a
name here that no stage defines), so the command line can offer the names without importing the
stage modules. ``pipeline.preset_stages(name)`` says which stages a preset sets;
:func:`apply_settings` checks and applies ``--set`` overrides.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

from pydantic import ValidationError

from graspcap.tasks.core.config import StageConfig

PIPELINE_PRESETS: dict[str, str] = {
    "default": "every stage's default config",
    "fast": "cheaper detection, registration and refinement (tests, quick looks)",
    "openpose": "noise levels of OpenPose keypoints for select_steady and reconstruct_hand",
    "strict": "stricter SfM outlier and parallax limits, stricter QA bounds",
    "lenient": "looser cross-check and QA bounds",
    "paper": "the paper's method: depth for scale only, palm-then-IK hand fit",
    "noisy": "a robust (Cauchy) hand fit for noisy joints",
    "fitted": "propagate the fitted hand's joints instead of the reconstruction's",
    "images": "MediaPipe on independent images instead of video tracking",
    "from_initialisation": "cross-check pycolmap started from the initialisation",
    "fixed_rise": "a fixed thermal rise threshold for the contact map",
    "strict_visibility": "contact only from vertices seen head-on in two views or more",
    "thorough": "more registration restarts for register_object",
    "always_global": "estimate_adjustment always runs the global registration",
    "large": "bigger QA pictures, more views",
    "joint": "the hand model inside the SfM (joint_solve) for cameras, joints and hand fit",
    "joint_fallback": "the staged hand SfM and fit, the joint solve where they fail",
    "staged": "the staged hand SfM and fit on every session, never the joint solve",
}


class UnknownPreset(ValueError):
    """A preset name that is not in :data:`PIPELINE_PRESETS`."""

    def __init__(self, name: str):
        self.name = name
        super().__init__(f"unknown preset {name!r}; known presets: "
                         f"{', '.join(PIPELINE_PRESETS)}")


def apply_settings(settings: Sequence[str], base: Mapping[str, StageConfig]
                   ) -> dict[str, StageConfig]:
    """``["stage.field=value", ...]`` (``--set``) applied to ``base`` (the configs by stage
    name): the configs of the stages they change, each setting checked against the stage's
    config model: the stage, the field (a dotted path into nested configs) and the value's
    type. The value is read as JSON (``1.5``, ``true``, ``"x"``, ``[1, 2]``), else taken as a
    string (enum values). Raises ``ValueError`` naming the setting and what is wrong with it."""
    out: dict[str, dict[str, Any]] = {}
    configs: dict[str, StageConfig] = {}
    for setting in settings:
        path, sep, raw = setting.partition("=")
        stage, _, field = path.strip().partition(".")
        if not sep or not field:
            raise ValueError(f"--set {setting!r}: expected STAGE.FIELD=VALUE")
        if stage not in base:
            raise ValueError(f"--set {setting!r}: no stage {stage!r}; stages are {list(base)}")
        try:
            value = json.loads(raw)
        except ValueError:
            value = raw
        fields = out.setdefault(stage, {})
        node, model, keys = fields, type(base[stage]), field.split(".")
        for i, key in enumerate(keys):
            known = getattr(model, "model_fields", None)
            if known is None or key not in known:
                where = ".".join([stage, *keys[:i]])
                raise ValueError(f"--set {setting!r}: {where} has no field {key!r}; its fields "
                                 f"are {sorted(known or [])}")
            if i == len(keys) - 1:
                node[key] = value
            else:
                node = node.setdefault(key, {})
                model = known[key].annotation
        merged = _deep_merge(base[stage].model_dump(), fields)
        try:
            configs[stage] = type(base[stage]).model_validate(merged)
        except ValidationError as exc:
            raise ValueError(f"--set {setting!r}: {exc.errors()[0]['msg']}") from None
    return configs


def _deep_merge(a: dict, b: Mapping) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, Mapping) and isinstance(
            out.get(k), dict) else v
    return out
