"""A session whose manifest a stage may read only through the fields it declares
(``Stage.fields`` in ``tasks/pipeline.py``): what its cache key covers is what it can read."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from graspcap.tasks.session.load_session import Session


class UndeclaredManifestField(RuntimeError):
    """A stage read a ``session.json`` field its ``Stage.fields`` does not declare: its cache
    key would not cover that field, so a change to it would serve a stale result."""


ALWAYS_FIELDS = ("session_id",)
"""Fields every stage may read (messages name the session), so every stage's key covers them."""


class _FieldGuard:
    """A read-only view of a manifest model that lets through only the declared dotted fields
    (and anything below one); a model above a declared field is itself a guarded view, and its
    methods run on the view, so what they read is checked too."""

    __slots__ = ("_model", "_prefix", "_fields", "_stage")

    def __init__(self, model: BaseModel, prefix: str, fields: frozenset[str], stage: str):
        object.__setattr__(self, "_model", model)
        object.__setattr__(self, "_prefix", prefix)
        object.__setattr__(self, "_fields", fields)
        object.__setattr__(self, "_stage", stage)

    def __getattr__(self, name: str) -> Any:
        model = object.__getattribute__(self, "_model")
        if name not in type(model).model_fields:
            attr = getattr(type(model), name, None)
            if callable(attr) and not name.startswith("__"):
                return attr.__get__(self)  # a method: its reads go through this view
            raise AttributeError(name)
        path = object.__getattribute__(self, "_prefix") + name
        fields = object.__getattribute__(self, "_fields")
        value = getattr(model, name)
        if path in fields or any(path.startswith(f + ".") for f in fields):
            return value
        if isinstance(value, BaseModel) and any(f.startswith(path + ".") for f in fields):
            return _FieldGuard(value, path + ".", fields, object.__getattribute__(self, "_stage"))
        raise UndeclaredManifestField(
            f"{object.__getattribute__(self, '_stage')}: reads session.json field {path!r}, "
            f"which its Stage.fields in tasks/pipeline.py does not declare (declared: "
            f"{', '.join(sorted(fields))})")

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("a session's manifest is read-only")


class UndeclaredFileRole(RuntimeError):
    """A stage opened a session file of a role its ``Stage.reads`` does not declare: its cache
    key would not cover that file's bytes, so a change to it would serve a stale result."""


def _file_guard(session: Session, roles: Sequence[str], stage: str):
    """``check(path)``: raises :class:`UndeclaredFileRole` unless ``path`` is a file of one of
    ``roles`` (``Session.input_files``; ``session.json`` is read through the field guard)."""
    role_of = {p: r for r, paths in session.input_files().items() for p in paths}
    allowed = frozenset((*roles, "manifest"))

    def check(path: Path) -> None:
        role = role_of.get(path)
        if role not in allowed:
            rel = os.path.relpath(path, session.root)
            what = f"a {role} file" if role else "a file of no role"
            raise UndeclaredFileRole(
                f"{stage}: reads {rel} ({what}), which its Stage.reads in tasks/pipeline.py "
                f"does not declare (declared: {', '.join(sorted(roles)) or 'none'})")

    return check


def restricted(session: Session, fields: Sequence[str], stage: str,
               roles: Sequence[str] | None = None) -> Session:
    """``session`` with manifest access limited to ``fields`` (dotted paths, e.g.
    ``turntable.T_color_turntable``) and :data:`ALWAYS_FIELDS`: reading any other field raises
    :class:`UndeclaredManifestField` naming the stage and the field; with ``roles``
    (``Stage.reads``), opening a file of another role raises :class:`UndeclaredFileRole`."""
    guard = _FieldGuard(session.manifest, "", frozenset((*ALWAYS_FIELDS, *fields)), stage)
    check = None if roles is None else _file_guard(session, roles, stage)
    return Session(root=session.root, manifest=guard, check_read=check)  # type: ignore[arg-type]
