"""Errors a stage raises on purpose, with a reason a person can act on."""

from __future__ import annotations


class StageError(Exception):
    """A deterministic failure (bad input, a solver that cannot converge).

    Never retried: running the same stage on the same input fails the same way.
    The message names the session, file and field where they are known.
    """

    def __init__(self, stage: str, reason: str, *, session: str | None = None):
        self.stage = stage
        self.reason = reason
        self.session = session
        where = f"session {session}: " if session else ""
        super().__init__(f"{where}{stage}: {reason}")


def check_mesh(stage: str, vertices, faces, *, name: str = "the object mesh") -> None:
    """Raise :class:`StageError` naming ``name`` (the mesh file) when ``vertices (n, 3)`` and
    ``faces (m, 3)`` are not a usable triangle mesh: non-finite vertices, no face, a face index
    outside ``0..n-1``, or no face of non-zero area. Stages call it before the mesh is first
    used, so that no accepted mesh ends in a raw ``IndexError`` or ``ValueError``."""
    import numpy as np

    V, F = np.asarray(vertices), np.asarray(faces)
    if V.ndim != 2 or V.shape[1:] != (3,) or len(V) == 0:
        raise StageError(stage, f"{name}: vertices must be (n, 3) with n > 0, got {V.shape}")
    if F.ndim != 2 or F.shape[1:] != (3,) or len(F) == 0:
        raise StageError(stage, f"{name}: faces must be triangles (m, 3) with m > 0, got "
                                f"{F.shape} (a point cloud, or polygons not triangulated?)")
    bad_v = ~np.isfinite(V).all(axis=1)
    if bad_v.any():
        raise StageError(stage, f"{name}: {int(bad_v.sum())} vertex(es) not finite (first "
                                f"{int(np.flatnonzero(bad_v)[0])})")
    if not np.issubdtype(F.dtype, np.integer):
        raise StageError(stage, f"{name}: face indices must be integers, got {F.dtype}")
    out = (F < 0) | (F >= len(V))
    if out.any():
        rows = np.flatnonzero(out.any(axis=1))
        first, index = int(rows[0]), int(F[rows[0]][out[rows[0]]][0])
        raise StageError(
            stage,
            f"{name}: {len(rows)} face(s) index vertices that do not exist (face {first} has "
            f"index {index}; the mesh has {len(V)} vertices, 0..{len(V) - 1}): a truncated or "
            "corrupt mesh file",
        )
    tri = V[F].astype(float)
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not (area2 > 0).any():
        raise StageError(stage, f"{name}: no face has a non-zero area (all {len(F)} faces are "
                                "degenerate)")
