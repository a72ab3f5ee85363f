"""Procedural household objects: signed distance functions meshed by marching cubes.

Every object is a single watertight surface in metres, in its own frame (z up
when standing), with a feature that breaks rotational symmetry (a handle, a
cap off the axis, a trigger head). Meshes are deterministic per name.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from graspcap.tasks.core.errors import StageError

Sdf = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class ObjectMesh:
    """A triangle mesh in the object's frame.

    Attributes
    ----------
    name : str
        Object id written to the manifest.
    vertices : (n, 3) float64
        Metres.
    faces : (m, 3) int64
        Outward-facing triangles.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray


# --- signed distance primitives (negative inside), points (n, 3) -> (n,) ----


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth union with blend radius ``k`` metres."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _cylinder(p: np.ndarray, c: tuple, r: float, half_h: float, round_m: float = 0.0) -> np.ndarray:
    """Capped z-aligned cylinder centred at ``c`` with rounded rims."""
    q = p - np.asarray(c)
    d = np.stack(
        [np.hypot(q[:, 0], q[:, 1]) - (r - round_m), np.abs(q[:, 2]) - (half_h - round_m)], axis=1
    )
    outside = np.linalg.norm(np.maximum(d, 0.0), axis=1)
    return np.minimum(d.max(axis=1), 0.0) + outside - round_m


def _box(p: np.ndarray, c: tuple, half: tuple, round_m: float = 0.0) -> np.ndarray:
    """Axis-aligned box centred at ``c`` with rounded edges."""
    q = np.abs(p - np.asarray(c)) - (np.asarray(half) - round_m)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return outside + np.minimum(q.max(axis=1), 0.0) - round_m


def _capsule(p: np.ndarray, a: tuple, b: tuple, r: float) -> np.ndarray:
    """Segment a-b swept by a sphere of radius ``r``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1) - r


def _torus_xz(p: np.ndarray, c: tuple, major: float, minor: float) -> np.ndarray:
    """Torus in the x-z plane (axis along y) centred at ``c``."""
    q = p - np.asarray(c)
    ring = np.hypot(q[:, 0], q[:, 2]) - major
    return np.hypot(ring, q[:, 1]) - minor


# --- the objects -------------------------------------------------------------


def _mug(p: np.ndarray) -> np.ndarray:
    body = _cylinder(p, (0, 0, 0.0475), 0.041, 0.0475, 0.003)
    handle = _torus_xz(p, (0.046, 0, 0.05), 0.026, 0.0065)
    handle = np.maximum(handle, 0.043 - p[:, 0])  # keep the outer half only
    outer = _smin(body, handle, 0.004)
    cavity = _cylinder(p, (0, 0, 0.1), 0.0355, 0.094, 0.003)
    return np.maximum(outer, -cavity)


def _bottle(p: np.ndarray) -> np.ndarray:
    body = _cylinder(p, (0, 0, 0.07), 0.034, 0.07, 0.006)
    shoulder = _capsule(p, (0, 0, 0.14), (0, 0, 0.17), 0.022)
    neck = _cylinder(p, (0.004, 0, 0.182), 0.013, 0.014, 0.002)
    cap = _cylinder(p, (0.006, 0.002, 0.2), 0.0145, 0.009, 0.002)
    label = _box(p, (0.031, 0.0, 0.075), (0.007, 0.02, 0.03), 0.003)  # raised label bump
    d = _smin(body, shoulder, 0.015)
    d = _smin(d, neck, 0.006)
    d = _smin(d, cap, 0.002)
    return _smin(d, label, 0.004)


def _spray_bottle(p: np.ndarray) -> np.ndarray:
    q = p * np.array([1.0, 1.35, 1.0])  # elliptic body
    body = _cylinder(q, (0, 0, 0.065), 0.036, 0.065, 0.008) / 1.2
    neck = _cylinder(p, (0, 0, 0.14), 0.014, 0.012, 0.002)
    head = _box(p, (0.012, 0, 0.165), (0.035, 0.013, 0.018), 0.006)
    nozzle = _capsule(p, (0.04, 0, 0.172), (0.056, 0, 0.172), 0.006)
    trigger = _capsule(p, (0.03, 0, 0.148), (0.036, 0, 0.118), 0.006)
    d = _smin(body, neck, 0.008)
    d = _smin(d, head, 0.005)
    d = _smin(d, nozzle, 0.003)
    return _smin(d, trigger, 0.004)


def _carton(p: np.ndarray) -> np.ndarray:
    box = _box(p, (0, 0, 0.08), (0.045, 0.032, 0.08), 0.008)
    spout = _cylinder(p, (0.018, 0.008, 0.168), 0.012, 0.012, 0.002)
    ridge = _box(p, (-0.02, 0, 0.163), (0.02, 0.03, 0.006), 0.003)
    return _smin(_smin(box, spout, 0.004), ridge, 0.003)


def _drill(p: np.ndarray) -> np.ndarray:
    body = _capsule(p, (-0.06, 0, 0.17), (0.07, 0, 0.17), 0.032)
    chuck = _capsule(p, (0.07, 0, 0.17), (0.11, 0, 0.17), 0.016)
    grip = _capsule(p, (-0.005, 0, 0.14), (-0.03, 0, 0.05), 0.019)
    battery = _box(p, (-0.02, 0, 0.025), (0.05, 0.035, 0.025), 0.008)
    d = _smin(body, chuck, 0.006)
    d = _smin(d, grip, 0.012)
    return _smin(d, battery, 0.01)


def _bulb(p: np.ndarray) -> np.ndarray:
    """A light bulb: glass globe, tapered neck, screw base; a small glass nub breaks the
    symmetry (near-symmetric about z)."""
    globe = np.linalg.norm(p - [0, 0, 0.075], axis=1) - 0.03
    neck = _capsule(p, (0, 0, 0.03), (0, 0, 0.06), 0.016)
    base = _cylinder(p, (0, 0, 0.014), 0.0125, 0.014, 0.002)
    nub = np.linalg.norm(p - [0.0, 0.0, 0.1055], axis=1) - 0.004
    thread = _torus_xz(p[:, [0, 2, 1]], (0, 0.018, 0), 0.0125, 0.0018)  # ring about z
    d = _smin(globe, neck, 0.012)
    d = _smin(d, base, 0.004)
    d = np.minimum(d, thread)
    side = np.linalg.norm(p - [0.024, 0.0, 0.082], axis=1) - 0.008  # the maker's seal
    return _smin(_smin(d, nub, 0.003), side, 0.004)


def _small_box(p: np.ndarray) -> np.ndarray:
    """A small carton (tea, matches) with a flap on one end."""
    box = _box(p, (0, 0, 0.0175), (0.03, 0.0225, 0.0175), 0.003)
    flap = _box(p, (0.031, 0.0, 0.028), (0.004, 0.016, 0.006), 0.0015)
    return _smin(box, flap, 0.002)


def _glass(p: np.ndarray) -> np.ndarray:
    """A wine glass held by its thin stem: foot, 5 mm stem, closed bowl; a chip in the
    foot's rim breaks the symmetry."""
    foot = _cylinder(p, (0, 0, 0.0035), 0.035, 0.0035, 0.0015)
    stem = _capsule(p, (0, 0, 0.004), (0, 0, 0.085), 0.005)
    bowl = _capsule(p, (0, 0, 0.12), (0, 0, 0.15), 0.037)
    bowl = np.maximum(bowl, p[:, 2] - 0.16)  # flat rim
    chip = np.linalg.norm(p - [0.036, 0.0, 0.006], axis=1) - 0.006
    d = _smin(_smin(foot, stem, 0.006), bowl, 0.02)
    return np.maximum(d, -chip)


def _remote(p: np.ndarray) -> np.ndarray:
    """A thin remote control (2 cm thick) with a raised button pad near one end."""
    slab = _box(p, (0, 0, 0.01), (0.085, 0.024, 0.01), 0.006)
    pad = _box(p, (0.05, 0.0, 0.0205), (0.02, 0.014, 0.0015), 0.001)
    return _smin(slab, pad, 0.002)


def _ball(p: np.ndarray) -> np.ndarray:
    """A ball with a small valve bump: nearly symmetric in every direction."""
    sphere = np.linalg.norm(p - [0, 0, 0.035], axis=1) - 0.035
    valve = np.linalg.norm(p - [0.0, 0.033, 0.045], axis=1) - 0.004
    return _smin(sphere, valve, 0.002)


def _can(p: np.ndarray) -> np.ndarray:
    """A drinks can: a cylinder with rims and a pull tab off the axis (near-symmetric)."""
    body = _cylinder(p, (0, 0, 0.06), 0.033, 0.06, 0.005)
    tab = _box(p, (0.012, 0.0, 0.1205), (0.01, 0.005, 0.0012), 0.0008)
    return _smin(body, tab, 0.001)


_SDFS: dict[str, tuple[Sdf, tuple[tuple[float, float, float], tuple[float, float, float]]]] = {
    "mug": (_mug, ((-0.05, -0.05, -0.005), (0.085, 0.05, 0.1))),
    "bottle": (_bottle, ((-0.04, -0.04, -0.005), (0.045, 0.04, 0.215))),
    "spray_bottle": (_spray_bottle, ((-0.04, -0.032, -0.005), (0.07, 0.032, 0.19))),
    "carton": (_carton, ((-0.05, -0.037, -0.005), (0.05, 0.037, 0.185))),
    "drill": (_drill, ((-0.1, -0.045, -0.005), (0.135, 0.045, 0.21))),
    "bulb": (_bulb, ((-0.04, -0.036, -0.003), (0.04, 0.036, 0.113))),
    "small_box": (_small_box, ((-0.034, -0.026, -0.004), (0.04, 0.026, 0.04))),
    "glass": (_glass, ((-0.04, -0.04, -0.003), (0.04, 0.04, 0.163))),
    "remote": (_remote, ((-0.088, -0.027, -0.003), (0.088, 0.027, 0.026))),
    "ball": (_ball, ((-0.038, -0.038, -0.003), (0.038, 0.042, 0.073))),
    "can": (_can, ((-0.036, -0.036, -0.003), (0.036, 0.036, 0.125))),
}

EXTENT_RANGE_M: dict[str, tuple[float, float]] = {
    "mug": (0.10, 0.16), "bottle": (0.16, 0.30), "spray_bottle": (0.15, 0.26),
    "carton": (0.14, 0.26), "drill": (0.18, 0.30), "bulb": (0.08, 0.14),
    "small_box": (0.05, 0.08), "glass": (0.14, 0.20), "remote": (0.14, 0.20),
    "ball": (0.06, 0.10), "can": (0.09, 0.16),
}  # fmt: skip
"""Plausible largest extent of each object (the wild profile scales within it)."""

OBJECT_NAMES: tuple[str, ...] = ("mug", "bottle", "spray_bottle", "carton", "drill")
"""The original five (``synth/2``'s profiles draw from these)."""
ALL_OBJECT_NAMES: tuple[str, ...] = tuple(_SDFS)
"""Every procedural object: the five above, then a light bulb, a small box (held in the fist,
mostly hidden), a wine glass (thin stem) and a remote (thin slab), a ball and a can
(near-symmetric)."""


def _march(sdf: Sdf, lo: np.ndarray, hi: np.ndarray, step: float) -> trimesh.Trimesh:
    """Mesh the zero level set of ``sdf`` on a padded grid of spacing ``step`` metres."""
    lo, hi = lo - 2 * step, hi + 2 * step
    axes = [np.arange(a, b + step, step) for a, b in zip(lo, hi, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    values = sdf(grid.reshape(-1, 3)).reshape(grid.shape[:3])
    verts, faces, _, _ = marching_cubes(values, level=0.0, spacing=(step, step, step))
    mesh = trimesh.Trimesh(verts + lo, faces[:, ::-1], process=True)
    mesh.update_faces(mesh.nondegenerate_faces())  # slivers collapsed by the vertex merge
    mesh.remove_unreferenced_vertices()
    if mesh.volume < 0:
        mesh.invert()
    return mesh


@lru_cache(maxsize=16)
def procedural_object(name: str, target_faces: int = 15000) -> ObjectMesh:
    """The named procedural object, meshed to roughly ``target_faces`` (within 5k-30k).

    The frame's origin is the centre of the bounding box's bottom face, z up.
    """
    if name not in _SDFS:
        raise StageError("synth", f"unknown object {name!r}; known: {', '.join(ALL_OBJECT_NAMES)}")
    sdf, (lo, hi) = _SDFS[name]
    lo, hi = np.asarray(lo), np.asarray(hi)
    step = 0.004
    mesh = _march(sdf, lo, hi, step)
    for _ in range(3):  # faces scale with 1 / step^2
        ratio = len(mesh.faces) / target_faces
        if 0.8 < ratio < 1.25:
            break
        step *= np.sqrt(ratio)
        mesh = _march(sdf, lo, hi, step)
    if not mesh.is_watertight or not 5000 <= len(mesh.faces) <= 30000:
        raise StageError("synth", f"object {name}: meshing gave {len(mesh.faces)} faces, "
                         f"watertight={mesh.is_watertight}")
    bounds = mesh.bounds
    origin = np.array([(bounds[0, 0] + bounds[1, 0]) / 2, (bounds[0, 1] + bounds[1, 1]) / 2,
                       bounds[0, 2]])
    return ObjectMesh(name, np.asarray(mesh.vertices) - origin, np.asarray(mesh.faces, np.int64))


def scaled_object(obj: ObjectMesh, extent_m: float) -> ObjectMesh:
    """``obj`` scaled about its origin to largest extent ``extent_m``; its id gains the size
    in millimetres (``bulb-112mm``), as a differently sized object is another object."""
    extent = float((obj.vertices.max(axis=0) - obj.vertices.min(axis=0)).max())
    return ObjectMesh(f"{obj.name}-{round(extent_m * 1000):d}mm",
                      obj.vertices * (extent_m / extent), obj.faces)


def load_object(path: Path) -> ObjectMesh:
    """A mesh file (PLY, OBJ, STL) in metres as an object; its id is the file stem.

    Raises :class:`StageError` when the mesh is not a single watertight surface in metres.
    """
    path = Path(path)
    loaded = trimesh.load(path, force="mesh", process=True, skip_materials=True)
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise StageError("synth", f"{path}: no triangle mesh found")
    extent = float(loaded.extents.max())
    if not 0.01 < extent < 0.5:
        raise StageError("synth", f"{path}: largest extent {extent:.3g} is not an object in "
                         "metres (expected 0.01-0.5 m); convert the units first")
    loaded.merge_vertices(merge_tex=True, merge_norm=True)  # split at UV seams otherwise
    loaded.remove_unreferenced_vertices()
    if not loaded.is_watertight:
        trimesh.repair.fill_holes(loaded)
    if not loaded.is_watertight:
        raise StageError("synth", f"{path}: mesh is not watertight; contact and penetration "
                         "need a closed surface")
    if loaded.volume < 0:
        loaded.invert()
    return ObjectMesh(path.stem, np.asarray(loaded.vertices, float),
                      np.asarray(loaded.faces, np.int64))


def write_object(obj: ObjectMesh, path: Path) -> None:
    """Write ``obj`` as binary PLY with vertices in the order given (contact is per vertex)."""
    mesh = trimesh.Trimesh(obj.vertices, obj.faces, process=False)
    path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="binary"))
