"""The dataset card (``README.md``) an export carries: what is in it, how good it is, how to read
it, under which licence, and which method made it."""

from __future__ import annotations

import re
from collections import Counter
from typing import Any

import pyarrow as pa

from graspcap.schemas.tables import (
    CATALOG_FORMAT_NAME,
    CATALOG_FORMAT_VERSION,
    TABLE_SCHEMAS,
    ZARR_LAYOUT,
)

DEFAULT_LICENCE = "unspecified — set it before sharing"

METHOD_TITLE = "Towards Markerless Grasp Capture"
METHOD_AUTHORS = ("Samarth Brahmbhatt", "Charles C. Kemp", "James Hays")
METHOD_URL = "https://contactdb.cc.gatech.edu/grasp_capture.html"
"""The method's paper, as its LaTeX source gives them (``shared/seeds/
towards-markerless-grasp-capture.tex``: ``\\title``, ``\\author`` and the URL of its
abstract); the source names no venue or year, so the citation gives none."""

TOP_REASONS = 10
_NUMBER = re.compile(r"(?<![\w.])[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?(?!\w)")
"""A number standing alone (not the 1 of ``stage1``)."""


def citation_bibtex() -> str:
    """The method's citation as BibTeX."""
    return ("@misc{brahmbhatt_markerless_grasp_capture,\n"
            f"  title  = {{{METHOD_TITLE}}},\n"
            f"  author = {{{' and '.join(METHOD_AUTHORS)}}},\n"
            f"  howpublished = {{\\url{{{METHOD_URL}}}}}\n}}")


def reason_pattern(text: str) -> str:
    """A reason with its numbers replaced by ``#`` (reasons that differ only in their
    measurements count as one)."""
    return _NUMBER.sub("#", text.splitlines()[0] if text else "").strip()


def qa_summary(sessions: pa.Table) -> dict[str, Any]:
    """Status counts and the most common flag and failure reasons (as patterns)."""
    rows = sessions.select(["status", "qa_flags", "error"]).to_pylist()
    status = Counter(r["status"] for r in rows)
    flags = Counter(reason_pattern(f) for r in rows for f in (r["qa_flags"] or []))
    errors = Counter(reason_pattern(r["error"]) for r in rows if r["error"])
    return {"sessions": len(rows), "ok": status.get("ok", 0),
            "flagged": status.get("flagged", 0), "failed": status.get("failed", 0),
            "flag_reasons": flags.most_common(TOP_REASONS),
            "failure_reasons": errors.most_common(TOP_REASONS)}


def _md(text: Any) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _meta(f: pa.Field, key: str) -> str:
    return (f.metadata or {}).get(key.encode(), b"").decode()


def _counts_table(sessions: pa.Table, key: str, frames: dict[str, int]) -> list[str]:
    rows = sessions.select(["session_id", key, "status"]).to_pylist()
    by: dict[str, Counter] = {}
    nframes: Counter = Counter()
    for r in rows:
        by.setdefault(r[key], Counter())[r["status"]] += 1
        nframes[r[key]] += frames.get(r["session_id"], 0)
    lines = [f"| {key} | sessions | ok | flagged | failed | frames |", "|---|---|---|---|---|---|"]
    for value in sorted(by):
        c = by[value]
        lines.append(f"| {_md(value)} | {sum(c.values())} | {c['ok']} | {c['flagged']} | "
                     f"{c['failed']} | {nframes[value]} |")
    return lines


def _columns(name: str, schema: pa.Schema) -> list[str]:
    known = TABLE_SCHEMAS.get(name)
    lines = [f"### `{name}`", "", "| column | type | unit | shape | description |",
             "|---|---|---|---|---|"]
    for f in schema:
        ref = known.field(f.name) if known is not None and f.name in known.names else f
        lines.append(f"| `{f.name}` | {_md(f.type)} | {_md(_meta(ref, 'unit')) or '-'} | "
                     f"{_md(_meta(ref, 'shape')) or '-'} | {_md(_meta(ref, 'doc'))} |")
    return lines + [""]


def _arrays() -> list[str]:
    lines = ["### Arrays", "", "| kind.array | dtype | shape | unit | description |",
             "|---|---|---|---|---|"]
    for kind, spec in ZARR_LAYOUT.items():
        for name, a in spec.arrays.items():
            shape = "x".join(str(s) for s in a.shape)
            lines.append(f"| `{kind}.{name}` | {a.dtype} | {shape} | {a.unit or '-'} | "
                         f"{_md(a.doc)} |")
    return lines + [""]


def _features(features: dict[str, dict], docs: dict[str, tuple[str, str]]) -> list[str]:
    lines = ["### LeRobot features (`data/`)", "",
             "| feature | dtype | shape | unit | description |", "|---|---|---|---|---|"]
    for name, spec in features.items():
        unit, doc = docs.get(name, ("", ""))
        lines.append(f"| `{name}` | {spec['dtype']} | {'x'.join(map(str, spec['shape']))} | "
                     f"{_md(unit) or '-'} | {_md(doc)} |")
    return lines + [""]


def render_card(*, catalog_uri: str, version: int, info: dict, sessions: pa.Table,
                frame_counts: dict[str, int], schemas: dict[str, pa.Schema],
                files: list[str], licence: str, layout_note: str,
                features: dict[str, dict] | None = None,
                feature_docs: dict[str, tuple[str, str]] | None = None) -> str:
    """The card's Markdown. ``schemas``: the catalog tables whose columns it documents
    (name -> schema); ``files``: what the export holds; ``layout_note``: how it is laid out;
    ``features`` (and their ``(unit, doc)``): a LeRobot layout's data columns."""
    qa = qa_summary(sessions)
    participants = sorted(set(sessions["participant"].to_pylist()))
    objects = sorted(set(sessions["object_id"].to_pylist()))
    intents = sorted(set(sessions["intent"].to_pylist()))
    tags = ", ".join(info.get("tags") or []) or "none"
    out = [
        f"# Grasp capture dataset: catalog version {version}", "",
        f"Exported from the graspcap catalog `{catalog_uri}`, version {version} (tags: {tags}; "
        f"build `{info['build_id']}`, committed {info['time_utc'].isoformat()}); catalog "
        f"format `{CATALOG_FORMAT_NAME}` {CATALOG_FORMAT_VERSION}.", "",
        f"- **Licence**: {licence}",
        f"- **Sessions**: {qa['sessions']} ({qa['ok']} ok, {qa['flagged']} flagged, "
        f"{qa['failed']} failed), **frames**: {sum(frame_counts.values())}",
        f"- **Objects** ({len(objects)}): {', '.join(objects)}",
        f"- **Participants** ({len(participants)}): {', '.join(participants)}",
        f"- **Intents** ({len(intents)}): {', '.join(intents)}", "",
        "## Layout", "", layout_note, "",
        *[f"- `{f}`" for f in files], "",
        "## Objects", "", *_counts_table(sessions, "object_id", frame_counts), "",
        "## Participants", "", *_counts_table(sessions, "participant", frame_counts), "",
        "## Intents", "", *_counts_table(sessions, "intent", frame_counts), "",
        "## Quality (QA)", "",
        f"{qa['ok']} session(s) ok, {qa['flagged']} flagged, {qa['failed']} failed. Flagged "
        "sessions have every result but a QA metric crossed a flag limit (`qa_flags` says "
        "which); failed ones have no results (`error` says why). Numbers in the reasons below "
        "are written `#`.", "",
        "Most common flag reasons:", "",
        *([f"- {n} x {_md(r)}" for r, n in qa["flag_reasons"]] or ["- none"]), "",
        "Most common failure reasons:", "",
        *([f"- {n} x {_md(r)}" for r, n in qa["failure_reasons"]] or ["- none"]), "",
        "## Conventions", "",
        "- `T_a_b` is a 4x4 homogeneous transform that maps a point from frame `b` into frame "
        "`a`: `p_a = T_a_b @ p_b`; stored as 16 float64 in row-major order.",
        "- Metres and radians throughout (2D keypoints in pixels).",
        "- Cameras follow the OpenCV convention: x right, y down, z forward. The world frame "
        "`w` is the colour camera's; `c` is a frame's virtual camera, `o` the object, `p` the "
        "palm.",
        "- 3D joints are 21 x 3 (63 values), 2D keypoints 21 x 2 (42 values), in the "
        "21-keypoint OpenPose/MediaPipe order.",
        "- Mesh arrays (`hand_mesh`, `object_mesh`, `contact`) are in the object's frame.", "",
        "## Columns and units", "",
        *(_features(features, feature_docs or {}) if features else []),
        *[line for name, schema in schemas.items() for line in _columns(name, schema)],
        *_arrays(),
        "## Normalisation statistics", "",
        "`stats.json` (LeRobot layout: `meta/stats.json`) holds count, mean, std, min, max, "
        "p01 and p99 of every numeric quantity: scalar columns per row, poses by their "
        "translation per coordinate, joints per coordinate (pooled over the 21 joints), other "
        "vectors per element; nulls and NaN left out.", "",
        "## Citation", "",
        f"The method: {', '.join(METHOD_AUTHORS)}. *{METHOD_TITLE}*. {METHOD_URL}", "",
        "```bibtex", citation_bibtex(), "```", "",
    ]
    return "\n".join(out)


__all__ = ["DEFAULT_LICENCE", "METHOD_AUTHORS", "METHOD_TITLE", "citation_bibtex",
           "qa_summary", "reason_pattern", "render_card"]
