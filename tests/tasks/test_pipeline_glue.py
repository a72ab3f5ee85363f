"""The stage table's glue: every stage gets its upstream results as ``**up`` and reads only
the ones its ``Stage.upstream`` declares, so a result never shares a name with a module."""

from __future__ import annotations

import inspect
import re

from graspcap.tasks import pipeline

READ = re.compile(r"""up(?:\[|\.get\()\s*["']([a-z_]+)["']""")


def _reads(fn) -> set[str]:
    """The upstream results ``fn`` reads, through the pipeline's helpers that take ``up``."""
    source = inspect.getsource(fn)
    names = set(READ.findall(source))
    for helper in re.findall(r"\b(_[a-z_]+)\(up\)", source):
        names |= _reads(getattr(pipeline, helper))
    return names


def test_glue_takes_results_by_mapping_only():
    for name, stage in pipeline.STAGES.items():
        params = inspect.signature(stage.run).parameters
        if name == "load_session":
            assert list(params) == ["session_dir", "config"]
            continue
        kinds = [p.kind for p in params.values()]
        assert list(params)[:2] == ["session", "config"], name
        assert kinds[2:] == [inspect.Parameter.VAR_KEYWORD], (name, list(params))
        assert list(params)[2] == "up", name


def test_glue_reads_only_declared_upstream_results():
    reads = {name: _reads(stage.run) for name, stage in pipeline.STAGES.items()}
    for name, stage in pipeline.STAGES.items():
        assert reads[name] <= set(stage.upstream) - {"load_session"}, name
    # the helper is followed: qa_metrics' final hand needs fit_hand and the adjustment
    assert {"fit_hand", "refine_grasp", "estimate_adjustment"} <= reads["qa_metrics"]
    assert reads["reconstruct_hand"] == {"detect_keypoints", "select_steady", "joint_solve"}
