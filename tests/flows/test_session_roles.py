"""The role digests a session's stage keys are made of, remembered across processes
(``flows.session_roles.SessionRoles``): used only while every file the manifest names has the stamp
it had, so a changed file, a replaced file or a retargeted link re-digests the session."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from graspcap.flows import cached
from graspcap.flows.cached import cache_key, session_files
from graspcap.flows.session_roles import SessionRoles, manifest_names
from graspcap.flows.workarea import WorkArea
from graspcap.schemas.session import SessionManifest
from graspcap.tasks.pipeline import STAGES, configs_for
from graspcap.tasks.session.load_session import Session
from tests.flow_fixtures import PRESET

OLD_NS = 1_700_000_000_000_000_000
"""An mtime long past: a file this old is not racily fresh (``workarea.is_racy``)."""


def _age(root: Path) -> None:
    for path in sorted(root.rglob("*"), reverse=True):
        if not path.is_symlink():
            os.utime(path, ns=(OLD_NS, OLD_NS))


def _new_process() -> None:
    """Forget what this process remembered, as a new build process would not have it."""
    cached._FILES.clear()
    cached._MANIFESTS.clear()
    cached._MANIFEST_DIGESTS.clear()
    WorkArea._memo.clear()
    WorkArea._folders.clear()


def _key(session: Path, work: WorkArea, roles: SessionRoles | None) -> str | None:
    return cache_key("load_session", session, configs_for(PRESET)["load_session"], {}, work,
                     None if roles is None else roles.digests)


def _flip_last_byte(path: Path) -> None:
    """One different byte, the size kept (the file is written in place: a new mtime)."""
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))


def _assert_digested_again(session: Path, work: WorkArea, before: str | None) -> SessionRoles:
    """In a new process the memo is not used, and the key is the one computed from scratch,
    not ``before``."""
    _new_process()
    roles = SessionRoles(work, session)
    assert roles.digests == {}
    after = _key(session, work, roles)
    _new_process()
    assert after == _key(session, work, None) != before
    return roles


@pytest.fixture
def session(synth_root, tmp_path) -> Path:
    """A private copy of one fixture session, every file aged past the racy window."""
    src = sorted(p for p in synth_root.iterdir() if p.is_dir())[0]
    dest = shutil.copytree(src, tmp_path / "session")
    _age(dest)
    return dest


def test_manifest_names_are_the_files_load_session_lists(synth_root):
    for folder in sorted(p for p in synth_root.iterdir() if p.is_dir()):
        manifest = SessionManifest.model_validate(
            json.loads((folder / "session.json").read_text()))
        loaded = Session(folder.resolve(), manifest)
        names = manifest_names(manifest)
        assert {role: [loaded.path(n) for n in ns] for role, ns in names.items()} \
            == loaded.input_files() == session_files(folder)
        assert sum(map(len, names.values())) > 3 * manifest.grasp.count


def test_an_unchanged_session_is_keyed_without_listing_its_files(session, tmp_path,
                                                                 monkeypatch):
    work = WorkArea(tmp_path / "work")
    fresh = _key(session, work, None)
    roles = SessionRoles(work, session)
    assert roles.digests == {} and _key(session, work, roles) == fresh
    roles.save()
    assert len(list((tmp_path / "work" / "digests").glob("roles-*.json"))) == 1
    _new_process()

    def no_listing(*_args, **_kwargs):
        raise AssertionError("the session's files were listed")

    monkeypatch.setattr(cached, "session_files", no_listing)
    monkeypatch.setattr(WorkArea, "files_digest", no_listing)
    again = SessionRoles(work, session)
    assert set(again.digests) >= set(STAGES["load_session"].reads)
    assert _key(session, work, again) == fresh
    reader = SessionRoles(WorkArea.reader(tmp_path / "work"), session)  # --plan reads it too
    assert reader.digests == again.digests


def test_a_changed_file_or_manifest_is_digested_again(session, tmp_path):
    work = WorkArea(tmp_path / "work")
    roles = SessionRoles(work, session)
    before = _key(session, work, roles)
    roles.save()
    frame = sorted((session / "grasp" / "depth").iterdir())[3]
    _flip_last_byte(frame)
    os.utime(frame, ns=(OLD_NS + 1, OLD_NS + 1))  # still old, but another mtime_ns
    _assert_digested_again(session, work, before).save()
    manifest = json.loads((session / "session.json").read_text())  # rewritten, same meaning:
    (session / "session.json").write_text(json.dumps(manifest, indent=3))  # a new stamp
    os.utime(session / "session.json", ns=(OLD_NS + 2, OLD_NS + 2))
    _new_process()
    assert SessionRoles(work, session).digests == {}


def test_a_retargeted_link_with_identical_names_sizes_and_mtimes_is_digested_again(
        session, tmp_path):
    """The frames folder is a link; the folder it points to is swapped for a copy whose files
    have the same names, sizes and mtimes and one different byte: only the inodes tell."""
    depth = session / "grasp" / "depth"
    shutil.move(depth, session / "grasp" / "depth_a")
    shutil.copytree(session / "grasp" / "depth_a", session / "grasp" / "depth_b")
    _flip_last_byte(sorted((session / "grasp" / "depth_b").iterdir())[2])
    _age(session)
    depth.symlink_to("depth_a")
    work = WorkArea(tmp_path / "work")
    roles = SessionRoles(work, session)
    before = _key(session, work, roles)
    roles.save()
    depth.unlink()
    depth.symlink_to("depth_b")
    _assert_digested_again(session, work, before)


def test_role_digests_are_not_kept_while_a_file_is_racily_fresh_or_for_a_reader(session,
                                                                                 tmp_path):
    (session / "object.ply").touch()  # modified just now
    work = WorkArea(tmp_path / "work")
    roles = SessionRoles(work, session)
    _key(session, work, roles)
    roles.save()
    assert not list((tmp_path / "work" / "digests").glob("roles-*.json"))
    _age(session)
    reader = SessionRoles(WorkArea.reader(tmp_path / "work"), session)
    _key(session, reader.work, reader)
    reader.save()
    assert not list((tmp_path / "work" / "digests").glob("roles-*.json"))
