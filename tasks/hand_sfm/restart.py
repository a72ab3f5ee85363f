"""When ``reconstruct_hand`` solves again from the depth, and which result it keeps.

The first solve starts from the two-view geometry of the pixels (``hand_sfm.two_view_init``).
Two ways it ends in a wrong hand: it fails a plausibility check (``hand_sfm.sanity``: the stage
would raise), or it passes them while few depth readings agree with it (a wrong minimum of a
small, distant hand that the pixels alone explain). Either way the solve runs again from the
depth initialisation (``hand_sfm.depth_init``); the checks stay, so a restart that is wrong too
fails the same way, and the error then names both reasons.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import replace
from typing import Any

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.hand_sfm.solve import STAGE


def depth_shares(rec: Any) -> tuple[float, float]:
    """Shares of a reconstruction's sampled depth readings that agree with its
    reprojection-only solve's scale and with the result itself (range factors of the final
    solve, within ``range_gate_sigmas`` of it; with ``depth_use = scale`` the first again)."""
    d = rec.diagnostics
    n = max(d.scale_samples, 1)
    final = d.range_factor.sum() if d.range_factor.any() else d.scale_inliers
    return d.scale_inliers / n, float(final) / n


def solve_with_restarts(
    solve: Callable[[], Any],
    restarts: Callable[[], Iterable[Callable[[], Any]]],
    *,
    enabled: bool,
    min_share: float,
    margin: float,
) -> Any:
    """``solve()``, or a restart when it fails or ``min(depth_shares) < min_share``.

    ``restarts()`` yields the restart solves in order (none when the depth initialisation
    is impossible). After a failure the first restart that succeeds is returned; after a
    depth-disagreeing success the first restart whose result ``margin`` more of the depth
    readings agree with, else the first solve. A returned restart carries the reason in
    ``diagnostics.restarted_after``.
    """

    def restarted(rec: Any, reason: str) -> Any:
        return replace(rec, diagnostics=replace(rec.diagnostics, restarted_after=reason))

    try:
        first = solve()
    except StageError as failed:
        if not enabled:
            raise
        reasons = []
        for attempt in restarts():
            try:
                return restarted(attempt(), failed.reason)
            except StageError as e:
                reasons.append(e.reason)
        if not reasons:
            raise
        raise StageError(
            STAGE, f"{failed.reason} (restarted from the depth-backprojected joints: "
            f"{reasons[-1]})",
        ) from failed
    share = min(depth_shares(first))
    if not enabled or share >= min_share:
        return first
    for attempt in restarts():
        try:
            again = attempt()
        except StageError:
            continue
        if depth_shares(again)[1] >= depth_shares(first)[1] + margin:
            return restarted(again, f"only {share:.0%} of the depth readings agreed with the hand")
    return first
