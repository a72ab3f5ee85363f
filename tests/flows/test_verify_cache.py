"""``graspcap build --verify N``: cached stages re-run and compared with their stored results."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from graspcap.flows.verify_cache import difference, verify_build
from tests.flow_fixtures import PRESET, copy_catalog

CHEAP = ("select_steady", "crosscheck_sfm", "fit_hand", "propagate_poses")


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in root.rglob("*")}


def test_difference_allows_float_noise_and_names_the_first_real_difference():
    @dataclasses.dataclass
    class R:
        a: np.ndarray
        n: int
        d: dict

    base = R(np.array([1.0, 2.0]), 3, {"x": [1.5, 2]})
    assert difference(base, R(np.array([1.0, 2.0 + 1e-12]), 3, {"x": [1.5, 2]})) is None
    assert difference(base, R(np.array([1.0, 2.1]), 3, {"x": [1.5, 2]})) == (
        "result.a: arrays differ")
    assert difference(base, R(base.a, 4, {"x": [1.5, 2]})) == "result.n: 3 != 4"
    assert difference(base, R(base.a, 3, {"x": [1.5, 3]})) == "result.d.x[1]: 2 != 3"
    assert difference(base, R(base.a[:1], 3, base.d)) == (
        "result.a: array float64(2,) != float64(1,)")


def test_verify_matches_an_honest_cache_and_finds_a_key_that_misses_a_change(
        warm, synth_root, tmp_path, monkeypatch):
    from graspcap.tasks import pipeline

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    before = _tree(catalog)
    honest = verify_build([synth_root], catalog, 3, PRESET, seed=1, stages=CHEAP)
    assert len(honest) == 3 and all(v.match for v in honest), honest
    assert _tree(catalog) == before  # nothing written
    # a change the key cannot see: the stage now computes another result under the same key
    original = pipeline.STAGES["fit_hand"]

    def drifted(session, config, **kw):
        fit = original.run(session, config, **kw)
        return dataclasses.replace(fit, angles_rad=np.asarray(fit.angles_rad) + 0.01)

    monkeypatch.setitem(pipeline.STAGES, "fit_hand", dataclasses.replace(original, run=drifted))
    found = verify_build([synth_root], catalog, 5, PRESET, stages=("fit_hand",))
    assert len(found) == 2  # one fit_hand per session: every candidate
    assert [(v.match, v.how) for v in found] == [(False, "result.angles_rad: arrays differ")] * 2
