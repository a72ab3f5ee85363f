"""``graspcap catalog vacuum --work``: delete cached stage results no build will look up again.

A stored result (``results/<stage>/<key>.pkl`` and its ``<key>.json`` record) is kept when

* the newest build of a session used it (``builds.jsonl``: each build records in ``keys`` the
  result every stage used, run or cached, for the sessions whose keys changed; folded oldest
  to newest, from the ``builds-keys.json`` snapshot on, they give each session's keys as its
  newest build used them, ``flows/build_log.py``): what an unchanged rebuild looks up;
* it is the latest run of a stage for a session (the key manifests under
  ``results/<stage>/latest/``): the results a build that failed as a whole left for the next
  one, and what ``--plan`` diffs against;
* or it was written less than ``min_age_s`` ago (a build running now may have just made it).

Everything else goes: results of configs, code or inputs that have since changed, and the
unkeyed (``uncached-*``) results of past builds. Remembered failures (``<key>.failed.json``,
a few hundred bytes each: they let an unchanged rebuild replay a failure instead of making a
new version), key manifests, file digests and Prefect's database are not touched. When the
newest build's record has no ``keys`` (a graspcap from before them wrote it) nothing is removed:
run a build first. Prefect-free.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from graspcap.flows.build_log import session_keys
from graspcap.flows.workarea import BUILDS_LOG, TEMP_PREFIX

MIN_AGE_S = 3600.0
"""Results written more recently than this are kept whatever the records say."""


class WorkVacuumRefused(ValueError):
    """The work area cannot be cleaned safely (the message says why and what to do)."""


@dataclass(frozen=True)
class WorkVacuumReport:
    """What ``vacuum_work`` kept and removed."""

    removed_results: int
    freed_bytes: int
    kept_results: int
    kept_bytes: int
    removed_by_stage: dict[str, int]
    prefect_bytes: int = 0
    """Size of Prefect's home in the work area (its database of runs), not touched."""

    def text(self) -> str:
        stages = ", ".join(f"{s} {n}" for s, n in self.removed_by_stage.items())
        prefect = (f"; Prefect's run history ({self.prefect_bytes / 1e6:.2f} MB in "
                   "work/prefect) is not touched" if self.prefect_bytes else "")
        return (f"work area: removed {self.removed_results} cached stage result(s)"
                + (f" ({stages})" if stages else "")
                + f", {self.freed_bytes:,} bytes ({self.freed_bytes / 1e6:.2f} MB) freed; kept "
                f"{self.kept_results} ({self.kept_bytes / 1e6:.2f} MB): those each session's "
                "newest build used, its latest run of each stage, and those of the last hour"
                + prefect)


def needed_keys(work: Path) -> dict[str, set[str]]:
    """``{stage: keys}`` to keep (module docstring); raises :class:`WorkVacuumRefused` when
    the newest build's record does not say which results it used."""
    needed: dict[str, set[str]] = {}
    sessions, newest = session_keys(work)
    if newest is not None and not isinstance(newest.get("keys"), dict):
        raise WorkVacuumRefused(
            f"{work / BUILDS_LOG}: the newest build ({newest.get('build_id')}) did not "
            "record which stage results it used (written by an older graspcap), so nothing is "
            "removed; run `graspcap build` once, then vacuum --work again")
    for stages in sessions.values():
        for stage, key in stages.items():
            needed.setdefault(stage, set()).add(key)
    for manifest in (work / "results").glob("*/latest/*.json"):
        try:
            key = json.loads(manifest.read_text()).get("key")
        except (OSError, ValueError, AttributeError, RecursionError):
            continue
        if isinstance(key, str):
            needed.setdefault(manifest.parent.parent.name, set()).add(key)
    return needed


def vacuum_work(work: Path | str, min_age_s: float = MIN_AGE_S) -> WorkVacuumReport:
    """Delete the cached stage results of ``work`` (a catalog's ``work/``) that no build
    needs (module docstring); each result's record first, so a reader never takes a record
    whose pickle is gone."""
    work = Path(work)
    if not (work / "results").is_dir():
        return WorkVacuumReport(0, 0, 0, 0, {})
    needed = needed_keys(work)
    now = time.time()
    removed = freed = kept = kept_bytes = 0
    by_stage: dict[str, int] = {}
    for folder in sorted(p for p in (work / "results").iterdir() if p.is_dir()):
        keep = needed.get(folder.name, set())
        for record in sorted(folder.glob("*.json")):
            if record.name.endswith(".failed.json") or record.name.startswith(TEMP_PREFIX):
                continue
            key = record.name.removesuffix(".json")
            pickle = folder / f"{key}.pkl"
            files = [f for f in (record, pickle) if f.exists()]
            size = sum(f.stat().st_size for f in files)
            young = any(now - f.stat().st_mtime < min_age_s for f in files)
            if key in keep or young:
                kept += 1
                kept_bytes += size
                continue
            for f in files:  # the record first: a lookup without it is a miss
                f.unlink(missing_ok=True)
            removed += 1
            freed += size
            by_stage[folder.name] = by_stage.get(folder.name, 0) + 1
        for pickle in sorted(folder.glob("*.pkl")):  # a killed writer's, never recorded
            if (pickle.with_suffix(".json").exists() or pickle.stem in keep
                    or now - pickle.stat().st_mtime < min_age_s):
                continue
            freed += pickle.stat().st_size
            pickle.unlink(missing_ok=True)
            removed += 1
            by_stage[folder.name] = by_stage.get(folder.name, 0) + 1
    prefect = sum(f.stat().st_size for f in (work / "prefect").rglob("*") if f.is_file())
    return WorkVacuumReport(removed, freed, kept, kept_bytes, by_stage, prefect)
