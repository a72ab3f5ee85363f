"""The build work area: stage results stored by cache key, file digests remembered.

Stage results can hold big arrays, so they never travel through Prefect's
result store: a stage's result is pickled (protocol 5, numpy buffers written
as they are) into ``<root>/results/<stage>/<key>.pkl`` and tasks hand each
other a small :class:`ResultRef` (path + content digest). Writes are atomic
(temporary file, then rename), so a killed build never leaves a half result.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

_CHUNK = 1 << 20


@dataclass(frozen=True)
class ResultRef:
    """Where a stage result lives and what its bytes hash to."""

    stage: str
    key: str
    path: str
    digest: str
    build_id: str
    """The build whose run produced the result (differs from the current build on a cache hit)."""


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


class WorkArea:
    """Results and digests under one root folder (default: the catalog's ``work/``)."""

    def __init__(self, root: Path | str):
        self.root = Path(root)
        (self.root / "results").mkdir(parents=True, exist_ok=True)
        self._digest_index = self.root / "digests"
        self._digest_index.mkdir(exist_ok=True)

    # --- file digests -----------------------------------------------------------------------
    def file_digest(self, path: Path) -> str:
        """sha256 of a file's bytes, remembered by (path, size, mtime) so unchanged files are
        not hashed again on every build."""
        st = os.stat(path)
        ident = f"{Path(path).resolve()}|{st.st_size}|{st.st_mtime_ns}"
        memo = self._digest_index / hashlib.sha256(ident.encode()).hexdigest()[:32]
        if memo.exists():
            return memo.read_text()
        digest = sha256_file(Path(path))
        _atomic_write(memo, digest.encode())
        return digest

    def files_digest(self, paths: list[Path]) -> str:
        """One digest over many files (names relative order kept)."""
        h = hashlib.sha256()
        for p in paths:
            h.update(str(p).encode())
            h.update(self.file_digest(p).encode())
        return h.hexdigest()

    # --- results ----------------------------------------------------------------------------
    def result_path(self, stage: str, key: str) -> Path:
        return self.root / "results" / stage / f"{key}.pkl"

    def save(self, stage: str, key: str, result: Any, build_id: str) -> ResultRef:
        data = pickle.dumps(result, protocol=5)
        path = self.result_path(stage, key)
        _atomic_write(path, data)
        return ResultRef(stage, key, str(path), hashlib.sha256(data).hexdigest(), build_id)

    def lookup(self, stage: str, key: str) -> Path | None:
        path = self.result_path(stage, key)
        return path if path.exists() else None

    @staticmethod
    def load(ref: ResultRef) -> Any:
        with open(ref.path, "rb") as f:
            return pickle.load(f)


def _atomic_write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def canonical_json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
