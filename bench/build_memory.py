"""What a build holds in memory per session until its one commit (issue 21: peak RSS flat in N).

    .venv/bin/python bench/build_memory.py --demo DIR
    .venv/bin/python bench/build_memory.py --commit 50 200 800 [--hand-vertices 5000]

``--demo DIR``: the output folder of ``graspcap demo --out DIR`` (its ``sessions/`` and
``catalog/``, whose work area holds every stage result): ``flows.assemble.assemble`` of its
sessions into a new catalog, all stages cached, once to warm the process's caches (the work
area's loaded results, imports) and once under ``tracemalloc``: the memory the ``Assembled``
holds afterwards (what waits for the commit), per session.

``--commit N ...``: per N, ``Catalog.commit`` of N sessions (``tests/catalog_factory.make_build``
rows, 2 frames each) whose arrays are made on every read, as the build's work-area spill reads
them (a hand mesh of ``--hand-vertices`` vertices and faces, the contact map of the object's
mesh): the peak of ``tracemalloc`` during the commit, in MB and in sessions' worth of arrays.
Flat in N when the commit reads each session's arrays as it writes them.
"""

from __future__ import annotations

import argparse
import gc as pygc
import sys
import tempfile
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import graspcap.catalog as gc  # noqa: E402
from tests.catalog_factory import GeneratedArrays, make_build  # noqa: E402


def assembled_per_session(demo: Path) -> None:
    from graspcap.flows.assemble import assemble
    from graspcap.flows.build import configs_digest, resolve_configs
    from graspcap.flows.cached import session_id_of
    from graspcap.flows.session import settle_session
    from graspcap.flows.workarea import WorkArea

    work = WorkArea(demo / "catalog" / "work")
    configs = resolve_configs("default", None)
    dirs = sorted(p for p in (demo / "sessions").iterdir() if (p / "session.json").exists())
    outcomes, sessions = {}, []
    for d in dirs:
        settled = settle_session(d, configs, work)
        refs = {k: s.ref for k, s in settled.items() if s.state == "Cached"}
        if len(refs) < len(settled):
            sys.exit(f"{d}: not every stage is cached for this code; run graspcap demo again")
        outcomes[str(d)] = (refs, [], list(refs), [], None, None, ())
        sessions.append((d, session_id_of(d)))
    with tempfile.TemporaryDirectory() as tmp:
        cat = gc.open(Path(tmp) / "catalog", create=True)
        build = gc.BuildInfo("bench", "bench", configs_digest(configs))
        assemble(cat, work, build, None, sessions, {}, outcomes)  # caches warm
        pygc.collect()
        tracemalloc.start()
        done = assemble(cat, work, build, None, sessions, {}, outcomes)
        pygc.collect()
        held, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    frames = done.frames.num_rows
    print(f"{len(sessions)} sessions, {frames} frames rows: the Assembled holds {held / 1e6:.3f} "
          f"MB, {held / len(sessions) / 1e6:.3f} MB a session (peak while assembling "
          f"{peak / 1e6:.1f} MB)")


def commit_peak(n: int, vertices: int) -> None:
    ids = [f"p{i:04d}-mug-use-00" for i in range(n)]
    build = make_build(ids, seed=n, frames=2)
    arrays = GeneratedArrays({r["session_id"]: r["object_id"] for r in build.sessions},
                             vertices, faces=2 * vertices)
    one = arrays[ids[0]]
    one_mb = (one.hand_vertices.nbytes + one.hand_faces.nbytes + one.contact.nbytes) / 1e6
    with tempfile.TemporaryDirectory() as tmp:
        cat = gc.open(Path(tmp) / "catalog", create=True)
        pygc.collect()
        tracemalloc.start()
        cat.commit(gc.BuildCommit(build=build.build, sessions=build.sessions,
                                  frames=build.frames, session_arrays=arrays,
                                  object_meshes=build.object_meshes))
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    print(f"N = {n}: commit peak {peak / 1e6:.1f} MB = {peak / 1e6 / one_mb:.1f} sessions' arrays "
          f"({one_mb:.2f} MB a session, {n * one_mb:.0f} MB in all)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo", type=Path, help="a `graspcap demo --out` folder")
    ap.add_argument("--commit", type=int, nargs="*", default=[], help="session counts")
    ap.add_argument("--hand-vertices", type=int, default=5000)
    args = ap.parse_args()
    if args.demo is None and not args.commit:
        ap.error("give --demo DIR and/or --commit N ...")
    if args.demo is not None:
        assembled_per_session(args.demo)
    for n in args.commit:
        commit_peak(n, args.hand_vertices)


if __name__ == "__main__":
    main()
