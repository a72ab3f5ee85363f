"""Placing the hand on the object and closing the fingers until they touch.

GraspIt-style autograsp on the object's signed distance: the palm is pushed
against a surface point (palmar normal into the object, random roll), then each
finger's three flexions close together; a phalanx that touches freezes the
joints proximal to it while the distal ones keep closing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from graspcap.synth.config import SynthConfig
from graspcap.synth.objects import ObjectMesh
from graspcap.synth.wild_hand import WildHand
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import make_T, transform_points
from graspcap.tasks.hand.model import FINGERTIPS, SURFACE_OFFSET_M, HandModel

# Palm point (palm frame, scale 1) pressed against the object: mid palm, palmar skin.
_PALM_CONTACT_P = np.array([-0.005, 0.05, 0.014])
_FLEX_SPEED = np.array([1.0, 1.15, 0.85])  # flexion1, 2, 3 closing rates
_STEP_RAD = np.radians(4.0)
_MIN_STEP_RAD = np.radians(0.1)
_SPHERES_PER_BONE = 6


@dataclass(frozen=True)
class Grasp:
    """A hand grasping the object, in the object's frame.

    Attributes
    ----------
    T_o_p : (4, 4) float
        Palm pose in the object frame.
    angles_rad : (20,) float
        Final joint angles (fingers touching).
    open_angles_rad : (20,) float
        Pre-shape before closing (same abductions, fingers extended).
    scale : float
        Hand scale.
    touching : (5,) bool
        Fingers whose distal phalanx touches the object.
    penetration_m : float
        Deepest hand-surface sample (vertices, face centres) inside the object (>= 0).
    """

    T_o_p: np.ndarray
    angles_rad: np.ndarray
    open_angles_rad: np.ndarray
    scale: float
    touching: np.ndarray
    penetration_m: float


class ObjectSdf:
    """Signed distance to a watertight object (negative inside), Open3D ray casting."""

    def __init__(self, obj: ObjectMesh):
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(obj.vertices.astype(np.float32), obj.faces.astype(np.uint32))

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Signed distances (n,) of ``points`` (n, 3) in the object frame."""
        q = o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        return self._scene.compute_signed_distance(q).numpy().astype(np.float64)


def depth_in_hand(points: np.ndarray, hand_vertices: np.ndarray, hand_faces: np.ndarray,
                  hand_part: np.ndarray) -> np.ndarray:
    """How deep (n,) each of ``points`` (n, 3) lies inside the posed hand (0 outside).

    Every part of the hand is a closed convex solid, so the depth inside a part
    is the smallest distance to its face planes.
    """
    tri = hand_vertices[hand_faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-18
    offsets = (normals * tri[:, 0]).sum(1)
    face_part = hand_part[hand_faces[:, 0]]
    depth = np.zeros(len(points))
    for k in np.unique(face_part):
        vk = hand_vertices[hand_part == k]
        near = np.flatnonzero(np.all((points > vk.min(0)) & (points < vk.max(0)), axis=1))
        if len(near) == 0:
            continue
        sel = face_part == k
        inside = -(points[near] @ normals[sel].T - offsets[sel]).max(axis=1)
        depth[near] = np.maximum(depth[near], inside)
    return depth


def hand_contact(obj: ObjectMesh, hand_vertices: np.ndarray, hand_faces: np.ndarray,
                 hand_part: np.ndarray) -> np.ndarray:
    """True per-vertex contact (n,) in [0, 1]: 1 within 0.5 mm of (or inside) the hand, ~0 at 5 mm.

    ``hand_*`` is a posed :class:`HandMesh` in the object frame.
    """
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(hand_vertices.astype(np.float32), hand_faces.astype(np.uint32))
    d = scene.compute_distance(o3d.core.Tensor(obj.vertices.astype(np.float32))).numpy()
    d = d.astype(np.float64)
    d[depth_in_hand(obj.vertices, hand_vertices, hand_faces, hand_part) > 0] = 0.0
    return np.where(d <= 0.0005, 1.0, np.exp(-(((d - 0.0005) / 0.0015) ** 2)))


class _Grasper:
    """One object and hand: the moves of the autograsp.

    While closing, a phalanx is probed by spheres along its bone (radius
    interpolated between the joints' skin offsets), far cheaper than its mesh;
    the finished grasp is checked on the full surface mesh.
    """

    def __init__(self, obj: ObjectMesh, hm: HandModel | WildHand, scale: float,
                 cfg: SynthConfig):
        self.obj, self.hm, self.scale, self.cfg = obj, hm, scale, cfg
        self.wild = isinstance(hm, WildHand)
        self.palm_parts = hm.palm_parts if self.wild else (0, 1)
        self.palm_contact_p = hm.palm_contact_p if self.wild else _PALM_CONTACT_P
        self.sdf = ObjectSdf(obj)
        rest = hm.mesh(hm.rest_angles())
        self.part, self.faces = rest.part, rest.faces
        t = np.linspace(0.0, 1.0, _SPHERES_PER_BONE)
        self._t = t
        self._radius = np.array([
            [(1 - t) * SURFACE_OFFSET_M[1 + 4 * f + j] + t * SURFACE_OFFSET_M[2 + 4 * f + j]
             for j in range(3)] for f in range(5)]) * scale  # (5, 3, s)

    def vertices(self, angles: np.ndarray, T_o_p: np.ndarray) -> np.ndarray:
        return self.hm.mesh(angles, T_o_p, self.scale).vertices

    def finger_gaps(self, angles: np.ndarray, T_o_p: np.ndarray, f: int) -> np.ndarray:
        """Smallest skin-to-surface distance (3,) of finger ``f``'s three phalanges."""
        if self.wild:
            start, end, r0, r1 = self.hm.phalanx_capsules(angles, T_o_p, self.scale)
            t = self._t[None, :]
            centres = start[f][:, None] + t[..., None] * (end[f] - start[f])[:, None]
            radius = (1 - t) * r0[f][:, None] + t * r1[f][:, None]
            return (self.sdf(centres.reshape(-1, 3)).reshape(3, -1) - radius).min(axis=1)
        kp = self.hm.keypoints(angles, T_o_p, self.scale)
        a, b = kp[1 + 4 * f: 4 + 4 * f], kp[2 + 4 * f: 5 + 4 * f]
        centres = a[:, None] + self._t[None, :, None] * (b - a)[:, None]  # (3, s, 3)
        d = self.sdf(centres.reshape(-1, 3)).reshape(3, -1) - self._radius[f]
        return d.min(axis=1)

    def surface(self, angles: np.ndarray, T_o_p: np.ndarray,
                parts: tuple[int, ...] | None = None) -> np.ndarray:
        """Hand surface samples (vertices and face centres) of ``parts`` (all when None)."""
        mesh = self.hm.mesh(angles, T_o_p, self.scale)
        faces = mesh.faces if parts is None else mesh.faces[self.face_mask(parts)]
        v = mesh.vertices if parts is None else mesh.vertices[np.isin(self.part, parts)]
        return np.concatenate([v, mesh.vertices[faces].mean(axis=1)])

    def face_mask(self, parts: tuple[int, ...]) -> np.ndarray:
        return np.isin(self.part[self.faces[:, 0]], parts)

    def tip_gaps(self, angles: np.ndarray, T_o_p: np.ndarray) -> np.ndarray:
        """Skin-to-surface distance (5,) at each fingertip."""
        if self.wild:
            _, end, _, r1 = self.hm.phalanx_capsules(angles, T_o_p, self.scale)
            return self.sdf(end[:, 2]) - r1[:, 2]
        tips = self.hm.keypoints(angles, T_o_p, self.scale)[list(FINGERTIPS)]
        return self.sdf(tips) - SURFACE_OFFSET_M[list(FINGERTIPS)] * self.scale

    def penetration(self, angles: np.ndarray, T_o_p: np.ndarray) -> float:
        """Deepest overlap (>= 0, m): hand surface samples in the object, object vertices in
        the hand (a sharp rim can poke through a large flat hand face between samples)."""
        mesh = self.hm.mesh(angles, T_o_p, self.scale)
        depth = -float(self.sdf(self.surface(angles, T_o_p)).min())
        return max(0.0, depth, float(depth_in_hand(self.obj.vertices, mesh.vertices, mesh.faces,
                                                    mesh.part).max()))

    def palm_gap(self, angles: np.ndarray, T_o_p: np.ndarray) -> float:
        """Smallest distance of the palm and thumb metacarpal surfaces to the object."""
        return float(self.sdf(self.surface(angles, T_o_p, self.palm_parts)).min())

    def place_palm(self, point: np.ndarray, normal: np.ndarray, roll: float,
                   open_angles: np.ndarray) -> np.ndarray | None:
        """Palm pose touching ``point``, palmar normal along ``-normal``; None if blocked."""
        z = -normal / np.linalg.norm(normal)
        helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
        y0 = np.cross(z, helper)
        y0 /= np.linalg.norm(y0)
        y = np.cos(roll) * y0 + np.sin(roll) * np.cross(z, y0)
        R = np.stack([np.cross(y, z), y, z], axis=1)

        def pose(gap: float) -> np.ndarray:
            return make_T(R, point - z * gap - R @ (self.palm_contact_p * self.scale))

        palm_p = self.surface(open_angles, np.eye(4), self.palm_parts)  # palm frame

        def gap_at(gap: float, stride: int = 4) -> float:
            return float(self.sdf(transform_points(pose(gap), palm_p[::stride])).min())

        lo, hi = -0.01, 0.06  # gap between the palm point and the surface point
        if gap_at(hi) <= 0:
            return None
        for _ in range(12):  # coarse samples while bisecting ...
            mid = (lo + hi) / 2
            if gap_at(mid) > 0.0005:
                hi = mid
            else:
                lo = mid
        gap = hi - gap_at(hi, 1) + 0.0002  # ... then all samples, one step along the normal
        T = pose(gap)
        if self.sdf(self.vertices(open_angles, T)).min() < -self.cfg.max_penetration_m:
            return None  # the open fingers already cut into the object
        return T

    def close(self, angles: np.ndarray, T_o_p: np.ndarray) -> np.ndarray:
        """Close every finger's flexions until its phalanges touch or reach their limits."""
        angles = angles.copy()
        tol, pen = self.cfg.touch_tolerance_m, self.cfg.max_penetration_m * 0.5
        for f in range(5):
            idx = 4 * f + np.arange(1, 4)
            active = np.ones(3, bool)
            step = _STEP_RAD
            d_prev = self.finger_gaps(angles, T_o_p, f)
            while active.any():
                trial = angles.copy()
                trial[idx[active]] += step * _FLEX_SPEED[active]
                trial = self.hm.clip(trial)
                if np.allclose(trial, angles):
                    break
                d = self.finger_gaps(trial, T_o_p, f)
                if np.any((d < -pen) & (d < d_prev - 1e-6)):  # cutting (deeper) into it
                    if step > _MIN_STEP_RAD:
                        step /= 2
                        continue
                    break
                angles, d_prev = trial, d
                for k in range(3):
                    if d[k] < tol:
                        active[: k + 1] = False
                active &= angles[idx] < self.hm.upper_rad[idx] - 1e-9
        return angles


def plan_grasp(obj: ObjectMesh, hm: HandModel | WildHand, scale: float, up_o: np.ndarray,
               cfg: SynthConfig, rng: np.random.Generator) -> Grasp:
    """A grasp of ``obj`` by a hand of ``scale``, reachable while the object rests on a platter.

    Parameters
    ----------
    up_o : (3,) float
        The platter's up direction in the object frame; the hand neither comes
        from below nor reaches under the object's support plane.

    Raises :class:`StageError` when ``cfg.grasp_attempts`` candidates all fail.
    """
    g = _Grasper(obj, hm, scale, cfg)
    up_o = up_o / np.linalg.norm(up_o)
    floor = float((obj.vertices @ up_o).min()) + 0.003
    normals = _vertex_normals(obj)
    candidates = np.flatnonzero(_open_outside(obj, normals) & (normals @ up_o >= -0.3))
    if len(candidates) == 0:
        raise StageError("synth", f"object {obj.name}: no surface point a palm can reach")
    best: Grasp | None = None
    for _ in range(cfg.grasp_attempts):
        i = int(candidates[rng.integers(len(candidates))])
        roll = rng.uniform(0, 2 * np.pi)
        spread = rng.uniform(-0.08, 0.12)
        open_angles = hm.clip(np.array([
            rng.uniform(0.35, 0.7), rng.uniform(0.0, 0.35), 0.1, 0.05,
            spread + 0.05, -0.05, 0.0, 0.0,
            0.0, -0.05, 0.0, 0.0,
            -spread * 0.8, -0.05, 0.0, 0.0,
            -spread * 1.6 - 0.05, -0.05, 0.0, 0.0,
        ]))
        n = normals[i]
        T_o_p = g.place_palm(obj.vertices[i], n, roll, open_angles)
        if T_o_p is None:
            continue
        angles = g.close(open_angles, T_o_p)
        mesh = hm.mesh(angles, T_o_p, scale)
        if (mesh.vertices @ up_o).min() < floor:
            continue
        if g.wild and _approach_too_low(hm, open_angles, T_o_p, scale, up_o, floor):
            continue
        penetration = g.penetration(angles, T_o_p)
        if penetration > cfg.max_penetration_m:  # back the whole hand off a little, once
            T_o_p = T_o_p @ make_T(np.eye(3), [0, 0, -(penetration - 0.5 * cfg.max_penetration_m)])
            penetration = g.penetration(angles, T_o_p)
        touching = g.tip_gaps(angles, T_o_p) < 0.003
        if penetration > cfg.max_penetration_m or touching.sum() < cfg.min_touching_fingers:
            continue
        grasp = Grasp(T_o_p, angles, open_angles, scale, touching, penetration)
        if touching[0] and touching.sum() >= 4:  # thumb opposing: the common grasp
            return grasp
        best = best or grasp
    if best is None:
        raise StageError("synth", f"object {obj.name}: no grasp with "
                         f"{cfg.min_touching_fingers} touching fingers in "
                         f"{cfg.grasp_attempts} attempts")
    return best


APPROACH_M = 0.04
"""The open hand starts this far back along its palmar normal (the session's approach)."""


def _approach_too_low(hm: WildHand, open_angles: np.ndarray, T_o_p: np.ndarray, scale: float,
                      up_o: np.ndarray, floor: float) -> bool:
    """Whether the open hand, backed off for the approach, reaches under the support plane
    (small objects: the open fingers would sweep through the platter)."""
    back = T_o_p @ make_T(np.eye(3), [0.0, 0.0, -APPROACH_M])
    for T in (T_o_p, back):
        if (hm.mesh(open_angles, T, scale).vertices @ up_o).min() < floor - 0.003:
            return True
    return False


def _open_outside(obj: ObjectMesh, normals: np.ndarray, clearance_m: float = 0.08) -> np.ndarray:
    """(n,) vertices whose normal ray leaves the object without hitting it again within
    ``clearance_m`` (not inside a mug, not under a handle): where a palm can go."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(obj.vertices.astype(np.float32), obj.faces.astype(np.uint32))
    rays = np.concatenate([obj.vertices + 0.001 * normals, normals], axis=1).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return ~(t_hit < clearance_m)


def _vertex_normals(obj: ObjectMesh) -> np.ndarray:
    """Area-weighted outward vertex normals (n, 3)."""
    tri = obj.vertices[obj.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(obj.vertices)
    for k in range(3):
        np.add.at(vn, obj.faces[:, k], fn)
    return vn / (np.linalg.norm(vn, axis=1, keepdims=True) + 1e-18)


def hand_in_object(grasp: Grasp, hm: HandModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The grasping hand's surface (vertices (n, 3), faces, part) in the object frame."""
    mesh = hm.mesh(grasp.angles_rad, grasp.T_o_p, grasp.scale)
    return mesh.vertices, mesh.faces, mesh.part
