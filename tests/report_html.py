"""Reading a build's report page (``catalog/report_page.py``) the way a browser would: its
session rows, links, images and plots, with ``html.parser``."""

from __future__ import annotations

from dataclasses import dataclass, field
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote


@dataclass
class Row:
    session_id: str
    status: str
    text: list[str] = field(default_factory=list)
    links: list[str] = field(default_factory=list)
    images: list[str] = field(default_factory=list)


@dataclass
class Page:
    rows: list[Row] = field(default_factory=list)
    links: list[str] = field(default_factory=list)
    images: list[str] = field(default_factory=list)
    plots: int = 0
    limit_lines: int = 0
    text: list[str] = field(default_factory=list)

    def row_text(self, session_id: str, status: str | None = None) -> str:
        return " ".join(t for r in self.rows if r.session_id == session_id
                        and (status is None or r.status == status) for t in r.text)


class _Parser(HTMLParser):
    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.page = Page()
        self.row: Row | None = None
        self.depth = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "tr" and "data-session" in a:
            self.row = Row(a["data-session"] or "", a.get("data-status") or "")
            self.page.rows.append(self.row)
        if tag == "a" and a.get("href"):
            self.page.links.append(a["href"])
            if self.row is not None:
                self.row.links.append(a["href"])
        if tag == "img" and a.get("src"):
            self.page.images.append(a["src"])
            if self.row is not None:
                self.row.images.append(a["src"])
        if tag == "svg" and "plot" in (a.get("class") or ""):
            self.page.plots += 1
        if tag == "line" and (a.get("class") or "").startswith("limit-"):
            self.page.limit_lines += 1

    def handle_endtag(self, tag: str) -> None:
        if tag == "tr":
            self.row = None

    def handle_data(self, data: str) -> None:
        self.page.text.append(data)
        if self.row is not None:
            self.row.text.append(data)


def parse(path: Path) -> Page:
    parser = _Parser()
    parser.feed(path.read_text(encoding="utf-8"))
    return parser.page


def check_page(path: Path) -> Page:
    """Parse ``path`` and assert what every report page holds: no http(s) URL anywhere,
    every link and image a file beside it (relative, existing), failed rows first."""
    text = path.read_text(encoding="utf-8")
    assert "http://" not in text and "https://" not in text
    page = parse(path)
    for ref in page.links + page.images:
        if ref.startswith("#"):
            continue
        assert "://" not in ref and not ref.startswith("/"), ref
        assert (path.parent / unquote(ref)).is_file(), ref
    order = {"failed": 0, "flagged": 1, "ok": 2}
    ranks = [order[r.status] for r in page.rows]
    assert ranks == sorted(ranks), [(r.session_id, r.status) for r in page.rows]
    return page
