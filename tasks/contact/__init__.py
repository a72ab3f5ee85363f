"""The build_contactmap stage: per-vertex contact from the thermal scan."""
