"""Checks on rigid transforms that both the session schema and the stages need.

``schemas/`` sits below ``tasks/`` (stages import the schema, never the reverse), so what the
manifest validator shares with the stages lives here; ``tasks.core.geometry`` holds the rest.
Conventions: ``T_a_b`` maps points of frame ``b`` into frame ``a`` (4x4, metres).
"""

from __future__ import annotations

import numpy as np


def rigidity_problems(T: np.ndarray, tol: float = 1e-4) -> list[str]:
    """Why ``T`` is not a rigid 4x4 transform; an empty list when it is."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        return [f"shape {T.shape}, expected (4, 4)"]
    if not np.all(np.isfinite(T)):
        return ["contains NaN or infinity"]
    problems = []
    if not np.allclose(T[3], [0, 0, 0, 1], atol=tol):
        problems.append(f"last row {T[3].tolist()}, expected [0, 0, 0, 1]")
    R = T[:3, :3]
    orth_err = float(np.abs(R.T @ R - np.eye(3)).max())
    if orth_err > tol:
        problems.append(f"rotation not orthonormal (max |R^T R - I| = {orth_err:.2g})")
    elif np.linalg.det(R) < 0:
        problems.append("rotation is a reflection (det < 0)")
    return problems
