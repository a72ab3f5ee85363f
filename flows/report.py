"""What a build did, per session and in total (no Prefect here)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from enum import StrEnum

from graspcap.tasks.session.discover import NOT_A_SESSION


class BuildFailed(RuntimeError):
    """The build committed nothing (the catalog's lock, the disk, the commit itself): not one
    session's fault. Every completed stage result stays in the work area for the next build,
    and the build's record (with ``error``) is in the work area's ``builds.jsonl``."""


class Outcome(StrEnum):
    """What a build did to a session's rows in the catalog."""

    ADDED = "added"
    CHANGED = "changed"
    UNCHANGED = "unchanged"
    FAILED = "failed"
    """Failed; its previous good rows (if any) stay in the catalog."""


@dataclass(frozen=True)
class SessionReport:
    """One session of a build."""

    session_id: str
    session_dir: str
    outcome: Outcome
    status: str
    """The row's status: ok, flagged or failed."""
    error: str | None = None
    failed_stage: str | None = None
    ran: tuple[str, ...] = ()
    """Stages whose body ran in this build."""
    cached: tuple[str, ...] = ()
    """Stages whose result came from the work area."""
    not_run: tuple[str, ...] = ()
    """Stages that did not run because an upstream stage failed."""
    retries: dict[str, int] = field(default_factory=dict)
    """Extra attempts per stage after transient faults."""
    kept_previous: bool = False
    """Failed, and the catalog keeps the session's previous good rows."""
    notes: tuple[str, ...] = ()
    """Failures of aid stages (pictures) that left the session committed."""
    pictures: dict[str, str] = field(default_factory=dict)
    """The session's QA pictures of this build by file name (``keypoints.png``,
    ``contact.ply``, ...): paths relative to the catalog root, content-addressed
    (``CatalogLayout.picture_file``), so the report of every version finds its own."""


@dataclass(frozen=True)
class BuildReport:
    """A build: its id, the catalog version it made (None: nothing to commit), sessions."""

    build_id: str
    catalog_version: int | None
    previous_version: int | None
    sessions: tuple[SessionReport, ...]
    seconds: dict[str, float]
    parameters: dict
    report_page: str | None = None
    """The build's report page (``<catalog>/reports/<build_id>/index.html``); None when it
    could not be written (a warning says why) or the catalog has no version."""
    publication: dict = field(default_factory=dict)
    """Write-audit-publish: ``state`` of the new version (published or staged), its ``audit``
    (``{"passed", "reasons", "compared_to", "measured", "gates"}``), the
    ``published_version`` readers now get by default, and ``optimized`` (a compaction's
    report) when the build compacted the tables."""

    def _ids(self, outcome: Outcome) -> list[str]:
        return [s.session_id for s in self.sessions if s.outcome == outcome]

    @property
    def added(self) -> list[str]:
        return self._ids(Outcome.ADDED)

    @property
    def changed(self) -> list[str]:
        return self._ids(Outcome.CHANGED)

    @property
    def unchanged(self) -> list[str]:
        return self._ids(Outcome.UNCHANGED)

    @property
    def failed(self) -> dict[str, str]:
        return {s.session_id: s.error or "" for s in self.sessions if s.outcome == Outcome.FAILED}

    @property
    def executed(self) -> int:
        """Stage bodies that ran (retried attempts not counted)."""
        return sum(len(s.ran) for s in self.sessions)

    def summary(self) -> str:
        head = (f"build {self.build_id}: " + (
            f"catalog version {self.catalog_version}" if self.catalog_version is not None
            else f"nothing changed, no new catalog version (still {self.previous_version})"))
        lines = [head,
                 f"  {len(self.added)} added, {len(self.changed)} changed, "
                 f"{len(self.unchanged)} unchanged, {len(self.failed)} failed; "
                 f"{self.executed} stage run(s), "
                 f"{sum(len(s.cached) for s in self.sessions)} cache hit(s); "
                 f"{self._time()}", *self.publication_lines()]
        for s in self.sessions:
            if s.outcome == Outcome.FAILED:
                kept = " (previous rows kept)" if s.kept_previous else ""
                lines.append(f"  FAILED {s.session_id}{kept}: {s.error}")
            lines += [f"  note {s.session_id}: {n}" for n in s.notes]
        lines += [f"  SKIPPED {folder}: {NOT_A_SESSION}"
                  for folder in self.parameters.get("not_sessions", ())]
        if self.report_page:
            lines.append(f"  report: {self.report_page}")
        return "\n".join(lines)

    def publication_lines(self) -> list[str]:
        """The audit's outcome and where readers are, for the summary (empty without)."""
        pub = self.publication
        if not pub or self.catalog_version is None:
            return []
        audit = pub.get("audit")
        readers = pub.get("published_version")
        where = (f"readers read version {readers}" if readers is not None
                 else "no version is published")
        if audit is None:
            verdict = "no audit"
        elif audit["passed"]:
            verdict = f"audit passed (compared with version {audit['compared_to']})" \
                if audit["compared_to"] is not None else "audit passed"
        else:
            verdict = "AUDIT FAILED"
        lines = [f"  {pub.get('state', '?')}: {verdict}; {where}"]
        lines += [f"    audit: {r}" for r in (audit or {}).get("reasons", [])]
        if pub.get("state") == "staged":
            lines.append(f"    publish it anyway: graspcap catalog publish {self.catalog_version}"
                         f"; drop it: graspcap catalog reject {self.catalog_version}")
        opt = pub.get("optimized")
        if opt:
            lines.append(f"  compacted the tables: version {opt['version']}, "
                         f"{opt['files_before']} -> {opt['files_after']} file(s)")
        return lines

    def _time(self) -> str:
        """The build's time: its wall time (``seconds["wall"]``: from the start of the
        process, set by ``graspcap build``) and the flow's part of it, else the flow's."""
        flow = self.seconds.get("total", 0.0)
        if "wall" not in self.seconds:
            return f"{flow:.1f} s"
        return f"{self.seconds['wall']:.1f} s wall ({flow:.1f} s in the build flow)"

    def record(self) -> dict:
        """The JSON-able record kept in the catalog's builds table and the work area, its size
        that of what the build did, not of the number of sessions: ``sessions`` has the entry
        of every session but the unchanged ones with nothing else to say (no notes, retries or
        error: :func:`quiet`), which ``unlisted`` counts (``{"sessions": n, "cached": {stage:
        n}, "status": {status: n}}``: their cache hits and row statuses); ``summary`` has the
        ids of the sessions added and changed, the failures' errors, and the number (not the
        ids) of those unchanged. Their pictures and folders are in the records of the builds
        that wrote their rows (the report page takes them from there). Records from before
        this list every session and the unchanged ids; readers take both."""
        listed = tuple(s for s in self.sessions if not quiet(s))
        d = asdict(replace(self, sessions=listed))
        d["summary"] = {"added": self.added, "changed": self.changed,
                        "unchanged": len(self.unchanged), "failed": self.failed}
        cached: dict[str, int] = {}
        status: dict[str, int] = {}
        for s in self.sessions:
            if quiet(s):
                status[s.status] = status.get(s.status, 0) + 1
                for stage in s.cached:
                    cached[stage] = cached.get(stage, 0) + 1
        d["unlisted"] = {"sessions": len(self.sessions) - len(listed), "cached": cached,
                         "status": status}
        return json.loads(json.dumps(d, default=str))


def quiet(s: SessionReport) -> bool:
    """An unchanged session with nothing else to say: counted in a build's record, not listed
    (``BuildReport.record``)."""
    return s.outcome == Outcome.UNCHANGED and not (s.notes or s.retries or s.error)
