"""Speed of stage 4 (build_contactmap) on the issue's size: a 30k-vertex mesh, 12 views.

    OMP_NUM_THREADS=1 .venv/bin/python bench/contactmap_speed.py [--vertices 30000] [--views 12]

The object is a bumpy ellipsoid of about ``--vertices`` vertices on a turntable seen by a
320 x 256 thermal camera from 40 deg above the platter; contact is a few Gaussian blobs,
rendered into each view as ambient + 5 K x contact with 0.05 K noise. Prints the median
wall time over ``--repeat`` runs and the MAE against the rendered contact.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import trimesh

from graspcap.tasks.contact.build_contactmap import PRESETS, build_contactmap
from graspcap.tasks.core.geometry import inv_T, make_T, rot_z
from graspcap.tasks.core.render import render

WIDTH, HEIGHT = 320, 256
K_TH = np.array([[360.0, 0.0, WIDTH / 2], [0.0, 360.0, HEIGHT / 2], [0.0, 0.0, 1.0]])
AMBIENT_K, RISE_K, NOISE_K = 295.0, 5.0, 0.05


def bumpy_ellipsoid(n_vertices: int, rng: np.random.Generator) -> trimesh.Trimesh:
    count = int(np.sqrt(n_vertices / 2))  # uv_sphere has about 2 count^2 vertices
    mesh = trimesh.creation.uv_sphere(radius=1.0, count=[count, count])
    v = mesh.vertices * [0.05, 0.035, 0.08]
    v *= 1 + 0.05 * np.sin(7 * mesh.vertices[:, [0]]) * np.cos(5 * mesh.vertices[:, [2]])
    v[:, 2] -= v[:, 2].min()
    return trimesh.Trimesh(v, mesh.faces, process=False)


def contact_blobs(vertices: np.ndarray, rng: np.random.Generator, blobs: int = 5) -> np.ndarray:
    upper = vertices[vertices[:, 2] > 0.3 * vertices[:, 2].max()]
    centres = upper[rng.choice(len(upper), blobs, replace=False)]
    d = np.linalg.norm(vertices[:, None] - centres[None], axis=-1).min(1)
    return np.exp(-((d / 0.008) ** 2))


def look_at_turntable(distance_m: float = 0.6, elevation_deg: float = 40.0) -> np.ndarray:
    e = np.radians(elevation_deg)
    c = np.array([0.0, -distance_m * np.cos(e), distance_m * np.sin(e)])
    z = -c / np.linalg.norm(c)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return inv_T(make_T(np.stack([x, np.cross(z, x), z], axis=1), c))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--vertices", type=int, default=30000)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    mesh = bumpy_ellipsoid(args.vertices, rng)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    contact = contact_blobs(V, rng)
    T_color_turntable, T_turntable_o = look_at_turntable(), np.eye(4)
    views = []
    for k in range(args.views):
        angle = 2 * np.pi * k / args.views
        hits = render([(V, F)], [T_color_turntable @ rot_z(angle) @ T_turntable_o], K_TH, WIDTH,
                      HEIGHT)
        temp = np.where(hits.mesh_index == 0, AMBIENT_K + RISE_K * hits.interpolate(0, F, contact),
                        AMBIENT_K - 0.3)
        views.append(((temp + NOISE_K * rng.standard_normal(temp.shape)).astype(np.float32), angle))
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        cm = build_contactmap(V, F, views, K_TH, np.eye(4), T_color_turntable, T_turntable_o,
                              PRESETS["default"], image_size=(WIDTH, HEIGHT))
        times.append(time.perf_counter() - t0)
    mae = float(np.abs(cm.contact[cm.observed] - contact[cm.observed]).mean())
    print("| mesh vertices | views | median time (s) | min (s) | MAE on observed | coverage "
          "| target |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {len(V)} | {args.views} | {statistics.median(times):.2f} | {min(times):.2f} | "
          f"{mae:.3f} | {cm.coverage:.2f} | <= 2 s |")


if __name__ == "__main__":
    main()
