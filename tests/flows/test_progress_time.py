"""What `graspcap build` shows while and after it runs: the ETA, the wall time since the
process started, and no Prefect telemetry notice across the bars."""

from __future__ import annotations

import io
import os
import pty
import subprocess
import sys
import time

import pytest

from graspcap.flows.progress import ConsoleProgress, StageEvent
from graspcap.flows.report import BuildReport
from tests.flow_fixtures import PRESET, copy_catalog


def test_progress_lines_carry_sessions_done_total_and_an_eta():
    now = [0.0]
    stream = io.StringIO()
    console = ConsoleProgress(stream, tty=False, clock=lambda: now[0])
    events = [("a", "s1", 1, False, 0), ("b", "s1", 2, False, 0), ("a", "s2", 3, True, 1),
              ("b", "s2", 4, True, 2)]
    etas = []
    with console:
        for t, (sid, stage, done, session_done, sessions_done) in zip(
                (10.0, 20.0, 30.0, 40.0), events, strict=True):
            now[0] = t
            event = StageEvent(sid, stage, "Completed", done, 4, session_done, sessions_done, 2)
            etas.append(console.eta(event))
            console(event)
    # the rate is measured from the first event (10 s per task), not from the start
    assert etas == ["ETA …", "ETA 0:00:20", "ETA 0:00:10", ""]
    assert stream.getvalue().splitlines() == [
        "[   30.0 s] a: all stages done (session 1/2, task 3/4, ETA 0:00:10)",
        "[   40.0 s] b: all stages done (session 2/2, task 4/4)"]


def test_the_bars_show_the_eta_on_a_terminal():
    now = [0.0]
    stream = io.StringIO()
    with ConsoleProgress(stream, tty=True, clock=lambda: now[0]) as console:
        for t, done in ((100.0, 1), (3700.0, 2)):
            now[0] = t
            console(StageEvent("a", f"s{done}", "Completed", done, 4, False, 0, 1))
        console._bars.refresh()
    assert "ETA 2:00:00" in stream.getvalue()  # (3700 - 100) s per task, two left


def test_the_summary_gives_the_wall_time_and_the_flows_part():
    report = BuildReport("b1", None, 3, (), {"total": 0.31}, {})
    assert report.summary().splitlines()[1].endswith("; 0.3 s")
    report.seconds["wall"] = 21.04
    assert report.summary().splitlines()[1].endswith("; 21.0 s wall (0.3 s in the build flow)")


def test_the_wall_time_counts_from_the_process_start():
    import graspcap.cli
    from graspcap.flows.commands import process_seconds

    # the process started before graspcap.cli was imported, whatever the machine's load
    assert process_seconds() >= time.perf_counter() - graspcap.cli.STARTED > 0
    assert process_seconds(time.perf_counter()) >= 0


def test_build_command_prints_its_wall_time(warm, synth_root, tmp_path, capsys):
    from graspcap.flows.commands import run_build

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    started = time.perf_counter()
    assert run_build([synth_root], catalog, PRESET, started=started) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if " s wall (" in x)
    wall, _, flow = line.rpartition("; ")[2].partition(" s wall (")
    assert flow.endswith(" s in the build flow)"), line
    assert float(wall) >= float(flow.split(" ")[0])


def _in_a_terminal(code: str, env: dict[str, str]) -> str:
    """What ``python -c code`` prints on a pseudo-terminal (Prefect's notice needs one)."""
    leader, follower = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=follower, stdout=follower,
                            stderr=follower, env=env, close_fds=True)
    os.close(follower)
    out = b""
    while True:
        try:
            chunk = os.read(leader, 4096)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        out += chunk
    proc.wait(timeout=120)
    os.close(leader)
    return out.decode(errors="replace")


def test_no_prefect_telemetry_notice_in_a_new_catalog(tmp_path):
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("PREFECT_") and k != "DO_NOT_TRACK"}
    notice = "Prefect collects anonymous usage data"
    bare = _in_a_terminal("import prefect", {**env, "PREFECT_HOME": str(tmp_path / "bare")})
    if notice not in bare:
        pytest.skip("Prefect shows no telemetry notice here (a CI environment?), so its "
                    "absence proves nothing")
    ours = _in_a_terminal(
        "from graspcap.flows.runtime import configure; "
        f"configure({str(tmp_path / 'work')!r}); import prefect; print('imported')", env)
    assert "imported" in ours and notice not in ours


def test_configure_turns_client_telemetry_off_unless_the_user_set_it(tmp_path, monkeypatch):
    from graspcap.flows.runtime import configure

    monkeypatch.setattr(os, "environ", dict(os.environ))
    os.environ.pop("DO_NOT_TRACK", None)
    assert configure(tmp_path / "work")["DO_NOT_TRACK"] == "1"
    assert os.environ["DO_NOT_TRACK"] == "1"
    os.environ["DO_NOT_TRACK"] = "0"
    assert "DO_NOT_TRACK" not in configure(tmp_path / "work")
    assert os.environ["DO_NOT_TRACK"] == "0"
