"""Synthetic capture rig: sessions written to the contract, with ground truth.

``generate`` writes N sessions (session i seeded by ``[seed, i]``), optionally
in a process pool with results identical to a single process.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

from graspcap.synth.config import PRESETS, STAGE_VERSION, Difficulty, SynthConfig
from graspcap.synth.objects import ALL_OBJECT_NAMES, OBJECT_NAMES, procedural_object
from graspcap.synth.session import generate_session


def config_for(profile: Difficulty | str = "realistic",
               frames: int | None = None) -> SynthConfig:
    """The preset of ``profile`` (a :data:`PRESETS` name), with ``frames`` overriding the video
    length when given."""
    cfg = PRESETS[Difficulty(profile).value]
    if frames is None:
        return cfg
    return SynthConfig.model_validate({**cfg.model_dump(), "frames": int(frames)})  # validated


def generate(out: Path, *, sessions: int, seed: int, difficulty: Difficulty | str = "realistic",
             frames: int | None = None, objects: Sequence[Path] | None = (),
             workers: int = 1, profile: Difficulty | str | None = None) -> list[Path]:
    """Write ``sessions`` synthetic sessions under ``out``; returns their directories in order.

    Session ``i`` uses ``np.random.default_rng([seed, i])`` and, when ``objects``
    are given, the mesh ``objects[i % len(objects)]`` (else a procedural object).
    ``profile`` (a :data:`PRESETS` name) wins over ``difficulty``, its older name.
    """
    cfg = config_for(difficulty if profile is None else profile, frames)
    objects = [Path(p) for p in (objects or ())]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(out, [int(seed), i], cfg, objects[i % len(objects)] if objects else None)
            for i in range(sessions)]
    if workers <= 1 or sessions <= 1:
        return [generate_session(*job) for job in jobs]
    with ProcessPoolExecutor(min(workers, sessions), mp_context=get_context("spawn")) as pool:
        return list(pool.map(generate_session, *zip(*jobs, strict=True)))


__all__ = [
    "ALL_OBJECT_NAMES", "OBJECT_NAMES", "PRESETS", "STAGE_VERSION", "Difficulty", "SynthConfig",
    "config_for", "generate", "generate_session", "procedural_object",
]  # fmt: skip
