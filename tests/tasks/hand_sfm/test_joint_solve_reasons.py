"""When the solve from the depth chain's start fails and so does the retry without the
chain, the refusal names both reasons (the chain's was hidden: wild [80625, 16] read only
"no start for the joint solve") and the staged path's once."""

from __future__ import annotations

import numpy as np
import pytest

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.hand.model import HandSide
from graspcap.tasks.hand_sfm import joint_solve as js


def _refusal(monkeypatch, solve_fails, cfg: js.JointSolveConfig | None = None) -> str:
    """The reason joint_solve refuses with when the staged path fails ("too noisy") and every
    solve from a start fails by ``solve_fails``."""
    def staged_fails(*args, **kwargs):
        raise StageError("reconstruct_hand", "too noisy")

    monkeypatch.setattr(js.reconstruct_stage, "reconstruct_hand", staged_fails)
    monkeypatch.setattr(js, "solve_from_start", solve_fails)
    extra = () if cfg is None else (cfg,)
    with pytest.raises(StageError) as exc:
        js.joint_solve(np.zeros((8, 21, 3)), np.eye(3), 0, lambda i, uv: np.zeros(len(uv)),
                       HandSide.RIGHT, *extra)
    return exc.value.reason


def test_both_starts_failing_name_both_reasons(monkeypatch):
    def solve_fails(*args, **kwargs):
        cfg, staged = args[5], args[8]
        why = "no metric scale (chain)" if cfg.chain_start else "no start (depth)"
        raise StageError(js.STAGE, f"{why}; the staged path: {staged}")

    reason = _refusal(monkeypatch, solve_fails)
    assert reason.startswith("no start (depth); from the depth chain's start: no metric "
                             "scale (chain); the staged path: ")
    assert reason.count("too noisy") == 1


def test_without_the_chain_the_one_reason_stands(monkeypatch):
    def solve_fails(*args, **kwargs):
        raise StageError(js.STAGE, "no start (depth)")

    cfg = js.JointSolveConfig(chain_start=False)
    assert _refusal(monkeypatch, solve_fails, cfg) == "no start (depth)"


def test_the_same_reason_twice_is_told_once(monkeypatch):
    def solve_fails(*args, **kwargs):  # no chain start: the depth start fails both times
        raise StageError(js.STAGE, f"no start (depth); the staged path: {args[8]}")

    reason = _refusal(monkeypatch, solve_fails)
    assert reason.startswith("no start (depth); the staged path: ")
    assert "chain" not in reason
