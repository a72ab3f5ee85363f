"""The named pipeline presets: the one table ``--preset`` offers and ``configs_for`` checks.

A pipeline preset is a name; each stage module's ``PRESETS`` says what the name sets for that
stage, and a stage without it keeps its ``default``. This table lists every name a stage
defines (``tasks/pipeline.py`` refuses at import a stage preset missing here, and the tests a
name here that no stage defines), so the command line can offer the names without importing the
stage modules. ``pipeline.preset_stages(name)`` says which stages a preset sets.
"""

from __future__ import annotations

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
}


class UnknownPreset(ValueError):
    """A preset name that is not in :data:`PIPELINE_PRESETS`."""

    def __init__(self, name: str):
        self.name = name
        super().__init__(f"unknown preset {name!r}; known presets: "
                         f"{', '.join(PIPELINE_PRESETS)}")
