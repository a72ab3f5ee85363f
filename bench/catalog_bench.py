"""Time the catalog: a 1M-row frames read vs plain Parquet, contact-map access, build commits.

    .venv/bin/python bench/catalog_bench.py [--sessions 200] [--frames-per-session 5000]

Version 1 is one build of SESSIONS x FRAMES frames (1M rows by default); version 2 is a
100-session build of 300 frames each (50 rewritten, 50 new). Prints a markdown table.
Frame values are random normals, which do not compress: real poses make smaller files.
The frames read alternates catalog and plain-pyarrow reads (``--repeats`` each) and compares
medians; contact maps are read through the catalog and, for comparison, through zarr's
synchronous API (the reader before format 2), interleaved so both see the same load.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import zarr
from deltalake import DeltaTable

import graspcap.catalog as gc
from graspcap.schemas.tables import SESSIONS_SCHEMA
from graspcap.tasks.core.geometry import from_rotvec

OBJECTS = {"mug": 2000, "drill": 3000, "bowl": 1500}


def make_build(ids: list[str], frames: int, seed: int, build_id: str) -> gc.BuildCommit:
    rng = np.random.default_rng(seed)
    n_f = frames * len(ids)
    sessions, arrays, meshes = [], {}, {}
    for i, sid in enumerate(ids):
        obj = list(OBJECTS)[i % len(OBJECTS)]
        T = from_rotvec(rng.normal(size=3), rng.normal(size=3))
        sessions.append({
            "session_id": sid, "participant": f"p{i % 20:02d}", "object_id": obj,
            "intent": "use", "hand": "right", "status": "ok", "error": None,
            "keypoint_backend": "openpose_json", "keypoint_frames_detected": frames,
            "steady_from": 10, "T_w_o_stage1": T, "T_adj": T, "T_w_p": T,
            "T_turntable_o_scan": T, "hand_scale": 1.0, "joint_angles_rad": rng.normal(size=20),
            "joints_w": rng.normal(size=63), "joints_fit_w": rng.normal(size=63),
            **{f.name: float(rng.uniform()) for f in SESSIONS_SCHEMA
               if f.name.startswith("qa_") and pa.types.is_floating(f.type)},
            "qa_flags": [], "qa_notes": [],
            "input_digest": f"{seed}-{i}", "code_version": "bench", "build_id": build_id,
            "config_digest": "c" * 64,
        })
        n = OBJECTS[obj]
        arrays[sid] = gc.SessionArrays(
            rng.uniform(size=n).astype(np.float32), rng.uniform(size=n) > 0.1,
            rng.normal(size=(778, 3)).astype(np.float32),
            rng.integers(0, 778, (1538, 3)).astype(np.int32), rng.normal(size=(21, 3)))
        if obj not in meshes:
            mrng = np.random.default_rng(n)
            meshes[obj] = gc.ObjectMesh(mrng.normal(size=(n, 3)).astype(np.float32),
                                        mrng.integers(0, n, (2 * n, 3)).astype(np.int32))
    frames = {
        "session_id": np.repeat(ids, frames).tolist(),
        "frame": np.tile(np.arange(frames), len(ids)),
        **{c: rng.normal(size=(n_f, 16)) for c in ("T_w_c", "T_c_o", "T_c_p")},
        "camera_solved": np.ones(n_f, dtype=bool),
        **dict.fromkeys(("camera_reason", "hand_reason", "object_reason"), [None] * n_f),
        "hand_used": np.ones(n_f, dtype=bool), "object_supported": np.ones(n_f, dtype=bool),
        "object_depth_agreement": np.full(n_f, 0.97),  # no draw: the stream stays as it was
        "joints_2d_px": rng.normal(size=(n_f, 42)), "keypoint_conf": rng.uniform(size=(n_f, 21)),
        "joints_c": rng.normal(size=(n_f, 63)), "reproj_err_px": rng.uniform(size=(n_f, 21)),
        "build_id": [build_id] * n_f,
    }
    info = gc.BuildInfo(build_id=build_id, code_version="bench", config_digest="c" * 64)
    return gc.BuildCommit(info, sessions, frames, arrays, meshes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=200)
    parser.add_argument("--frames-per-session", type=int, default=5000)
    parser.add_argument("--reads", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5, help="frames reads per side")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        cat = gc.open(tmp, create=True)
        ids = [f"s{i:05d}" for i in range(args.sessions)]
        build = make_build(ids, args.frames_per_session, 0, "big")
        t0 = time.perf_counter()
        cat.commit(build)
        rows.append((f"commit {len(ids)} sessions x {args.frames_per_session} frames",
                     f"{time.perf_counter() - t0:.1f} s", ""))
        del build

        pin = json.loads(cat.versions().to_pylist()[0]["table_versions"])["frames"]
        files = DeltaTable(str(cat.layout.table("frames")), version=pin).file_uris()
        cat_s, pq_s = [], []
        for i in range(2 * args.repeats):  # alternate, and start with either side
            first_cat = i % 2 == 0
            for side in ("cat", "pq") if first_cat else ("pq", "cat"):
                t0 = time.perf_counter()
                if side == "cat":
                    n = cat.table("frames", 1).num_rows
                else:
                    pq.read_table(files)
                (cat_s if side == "cat" else pq_s).append(time.perf_counter() - t0)
        ratio = statistics.median(pq_s) / statistics.median(cat_s)
        rows.append((f"read frames v1 ({n:,} rows): catalog / plain pq.read_table (medians)",
                     f"{statistics.median(cat_s):.2f} s / {statistics.median(pq_s):.2f} s",
                     f"throughput ratio {ratio:.2f} (target >= 0.8); of best runs "
                     f"{min(pq_s) / min(cat_s):.2f}"))

        rng = np.random.default_rng(1)
        cat.contactmap(ids[0], 1)  # builds the per-version session index once
        index = cat._sessions_index(1)
        times, old = [], []
        for sid in rng.choice(ids, args.reads):
            t0 = time.perf_counter()
            cat.contactmap(str(sid), 1)
            times.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            path = cat.layout.array_group(index[str(sid)]["contact_digest"])
            group = zarr.open_group(str(path), mode="r", zarr_format=3, use_consolidated=True)
            group["values"][...], group["observed"][...]
            old.append(time.perf_counter() - t0)
        rows.append(("contact map random access (median, p90)",
                     f"{statistics.median(times) * 1e3:.2f} ms",
                     f"p90 {np.percentile(times, 90) * 1e3:.2f} ms (target median <= 5 ms)"))
        rows.append(("same reads through zarr.open_group (the reader before format 2)",
                     f"{statistics.median(old) * 1e3:.2f} ms",
                     f"p90 {np.percentile(old, 90) * 1e3:.2f} ms"))

        ids2 = ids[:50] + [f"n{i:05d}" for i in range(50)]
        build = make_build(ids2, 300, 2, "small")
        t0 = time.perf_counter()
        cat.commit(build)
        rows.append(("commit 100 sessions x 300 frames (50 replace, 50 new) onto v1",
                     f"{time.perf_counter() - t0:.1f} s", ""))
        fresh = gc.open(tmp)
        t0 = time.perf_counter()
        fresh.commit(make_build([f"m{i:05d}" for i in range(100)], 300, 3, "third"))
        rows.append(("commit 100 new sessions x 300 frames", f"{time.perf_counter() - t0:.1f} s",
                     ""))
    print("| measurement | time | note |")
    print("|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
