"""The build report page's drawing: inline SVG plots of the QA metrics (a histogram per metric
with its flag and fail limits, medians across versions) and the small HTML formatters they and
``catalog.report_page`` share. Pure functions of their arguments; no catalog access."""

from __future__ import annotations

import html
import math
from collections.abc import Mapping
from typing import Any

from graspcap.schemas.qa import QaMetric


def esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def num(x: float | None, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:.{digits}g}" if abs(x) >= 1e-3 or x == 0 else f"{x:.2e}"


def level_of(m: QaMetric, value: float | None, limits: Mapping[str, float | None]) -> str:
    """"fail", "flag" or "" for ``value`` of metric ``m`` against its limits."""
    if value is None:
        return ""
    for level in ("fail", "flag"):
        limit = limits.get(level)
        if limit is not None and (value > limit if m.higher_is_worse else value < limit):
            return level
    return ""


COLOURS = {"fail": "#d62728", "flag": "#ff9f1a", "bar": "#4c78a8", "axis": "#444",
           "median": "#4c78a8"}


def _svg_head(width: int, height: int, title: str, heading: str) -> list[str]:
    """The opening of a plot: the element, its tooltip title and its visible heading
    (``heading`` is HTML already escaped)."""
    return [f'<svg class="plot" width="{width}" height="{height}" '
            f'viewBox="0 0 {width} {height}" role="img">',
            f'<title>{esc(title)}</title>', heading]


def _padded_range(values: list[float], pad_share: float) -> tuple[float, float]:
    """(lo, hi) covering ``values``, widened when they are all equal, padded by
    ``pad_share`` of the span on each side."""
    lo, hi = min(values), max(values)
    if hi - lo < 1e-12:
        lo, hi = lo - (abs(lo) * 0.1 or 1.0), hi + (abs(hi) * 0.1 or 1.0)
    pad = (hi - lo) * pad_share
    return lo - pad, hi + pad


def histogram_svg(m: QaMetric, values: list[float], limits: Mapping[str, float | None],
                  width: int = 320, height: int = 170, bins: int = 12) -> str:
    """An inline SVG histogram of ``values`` with the flag (amber) and fail (red) limits as
    dashed lines; the x range covers the values and the limits."""
    marks = [x for x in (limits.get("flag"), limits.get("fail")) if x is not None]
    span = values + marks
    left, right, top, bottom = 36, 10, 22, 30
    pw, ph = width - left - right, height - top - bottom
    parts = _svg_head(width, height, f"{m.label}: histogram over the sessions",
                      f'<text x="{left}" y="14" class="ptitle">{esc(m.label)}'
                      f'{" (" + esc(m.unit) + ")" if m.unit else ""}'
                      f'{" ↑ worse" if m.higher_is_worse else " ↓ worse"}</text>')
    if not span:
        parts.append(f'<text x="{left}" y="{top + ph / 2}">no values</text></svg>')
        return "".join(parts)
    lo, hi = _padded_range(span, 0.05)
    width_bin = (hi - lo) / bins
    counts = [0] * bins
    for x in values:
        counts[min(int((x - lo) / width_bin), bins - 1)] += 1
    peak = max(counts) or 1

    def sx(x: float) -> float:
        return left + (x - lo) / (hi - lo) * pw

    for i, c in enumerate(counts):
        if c:
            h = c / peak * ph
            parts.append(f'<rect x="{sx(lo + i * width_bin) + 0.5:.1f}" '
                         f'y="{top + ph - h:.1f}" width="{pw / bins - 1:.1f}" height="{h:.1f}" '
                         f'fill="{COLOURS["bar"]}"><title>{c} session(s) in '
                         f'[{num(lo + i * width_bin)}, {num(lo + (i + 1) * width_bin)})'
                         '</title></rect>')
    parts.append(f'<line x1="{left}" y1="{top + ph}" x2="{left + pw}" y2="{top + ph}" '
                 f'stroke="{COLOURS["axis"]}"/>')
    parts.append(f'<line x1="{left}" y1="{top}" x2="{left}" y2="{top + ph}" '
                 f'stroke="{COLOURS["axis"]}"/>')
    parts.append(f'<text x="{left - 4}" y="{top + 8}" text-anchor="end">{peak}</text>')
    parts.append(f'<text x="{left - 4}" y="{top + ph}" text-anchor="end">0</text>')
    parts.append(f'<text x="{left}" y="{height - 8}">{num(lo)}</text>')
    parts.append(f'<text x="{left + pw}" y="{height - 8}" text-anchor="end">{num(hi)}</text>')
    for level in ("flag", "fail"):
        x = limits.get(level)
        if x is not None:
            parts.append(f'<line class="limit-{level}" x1="{sx(x):.1f}" y1="{top - 4}" '
                         f'x2="{sx(x):.1f}" y2="{top + ph}" stroke="{COLOURS[level]}" '
                         f'stroke-width="2" stroke-dasharray="5,3"><title>{level} limit '
                         f'{num(x)}</title></line>')
            parts.append(f'<text x="{sx(x):.1f}" y="{top + ph + 12}" text-anchor="middle" '
                         f'fill="{COLOURS[level]}">{level} {num(x)}</text>')
    parts.append("</svg>")
    return "".join(parts)


def versions_svg(m: QaMetric, medians: Mapping[int, float], current: int,
                 limits: Mapping[str, float | None], width: int = 320,
                 height: int = 150) -> str:
    """The metric's median per catalog version (points joined by a line), the report's
    version ringed, the current limits dashed."""
    left, right, top, bottom = 44, 10, 22, 26
    pw, ph = width - left - right, height - top - bottom
    parts = _svg_head(width, height, f"{m.label}: median per version",
                      f'<text x="{left}" y="14" class="ptitle">{esc(m.label)}: median per '
                      'version</text>')
    if not medians:
        parts.append(f'<text x="{left}" y="{top + ph / 2}">no values</text></svg>')
        return "".join(parts)
    vs = sorted(medians)
    lo, hi = _padded_range([medians[v] for v in vs]
                           + [x for x in limits.values() if x is not None], 0.08)
    v0, v1 = vs[0], max(vs[-1], vs[0] + 1)

    def sx(v: float) -> float:
        return left + (v - v0) / (v1 - v0) * pw

    def sy(y: float) -> float:
        return top + ph - (y - lo) / (hi - lo) * ph

    parts.append(f'<line x1="{left}" y1="{top + ph}" x2="{left + pw}" y2="{top + ph}" '
                 f'stroke="{COLOURS["axis"]}"/><line x1="{left}" y1="{top}" x2="{left}" '
                 f'y2="{top + ph}" stroke="{COLOURS["axis"]}"/>')
    for level in ("flag", "fail"):
        y = limits.get(level)
        if y is not None:
            parts.append(f'<line class="limit-{level}" x1="{left}" y1="{sy(y):.1f}" '
                         f'x2="{left + pw}" y2="{sy(y):.1f}" stroke="{COLOURS[level]}" '
                         f'stroke-dasharray="5,3"><title>{level} limit {num(y)}</title></line>')
    points = " ".join(f"{sx(v):.1f},{sy(medians[v]):.1f}" for v in vs)
    parts.append(f'<polyline points="{points}" fill="none" stroke="{COLOURS["median"]}"/>')
    for v in vs:
        r = 5 if v == current else 3
        parts.append(f'<circle cx="{sx(v):.1f}" cy="{sy(medians[v]):.1f}" r="{r}" '
                     f'fill="{COLOURS["median"] if v != current else "#fff"}" '
                     f'stroke="{COLOURS["median"]}" stroke-width="2"><title>version {v}: '
                     f'median {num(medians[v])}</title></circle>')
    parts.append(f'<text x="{left - 4}" y="{top + 8}" text-anchor="end">{num(hi, 2)}</text>')
    parts.append(f'<text x="{left - 4}" y="{top + ph}" text-anchor="end">{num(lo, 2)}</text>')
    parts.append(f'<text x="{left}" y="{height - 8}">v{vs[0]}</text>')
    if len(vs) > 1:
        parts.append(f'<text x="{left + pw}" y="{height - 8}" text-anchor="end">v{vs[-1]}'
                     '</text>')
    parts.append("</svg>")
    return "".join(parts)


__all__ = ["COLOURS", "esc", "histogram_svg", "level_of", "num", "versions_svg"]
