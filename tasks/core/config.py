"""Base for every stage config: frozen, unknown keys rejected, canonical digest."""

from __future__ import annotations

import hashlib
import json

from pydantic import BaseModel, ConfigDict


class StageConfig(BaseModel):
    """A stage's parameters. Subclasses document every field with ``Field(description=...)``."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True)

    def canonical_json(self) -> str:
        """The config as JSON with sorted keys: equal configs give equal text."""
        return json.dumps(self.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))

    def digest(self) -> str:
        """sha256 of :meth:`canonical_json`, the config's part of a cache key."""
        return hashlib.sha256(self.canonical_json().encode()).hexdigest()
