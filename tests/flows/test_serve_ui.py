"""``graspcap serve`` as a user meets it: its UI in a real headless browser lists the builds'
flow runs and their logs, its printed command starts a build from another shell, and it
prints one line per finished run."""

from __future__ import annotations

import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from graspcap.flows.commands import run_line, serve_banner
from graspcap.flows.runtime import server_env
from tests.browser import HeadlessChromium, find_chromium
from tests.flow_fixtures import PRESET, copy_catalog

API_ERROR = "Can't connect to Server API"


def test_the_supervised_servers_ui_calls_its_own_api():
    env = server_env("127.0.0.1", 45123, {"PATH": "/bin"})
    assert env["PREFECT_UI_API_URL"] == "http://127.0.0.1:45123/api"  # not 127.0.0.1:4200
    assert (env["PREFECT_SERVER_API_HOST"], env["PREFECT_SERVER_API_PORT"]) == (
        "127.0.0.1", "45123")
    assert env["PREFECT_SERVER_ANALYTICS_ENABLED"] == "false" and env["DO_NOT_TRACK"] == "1"
    assert env["PREFECT_SERVER_UI_SHOW_PROMOTIONAL_CONTENT"] == "false"
    assert env["PATH"] == "/bin"
    # what the user set wins: a proxy in front of the server, analytics on
    mine = server_env("127.0.0.1", 45123, {"PREFECT_UI_API_URL": "https://proxy/api",
                                           "PREFECT_SERVER_ANALYTICS_ENABLED": "true"})
    assert mine["PREFECT_UI_API_URL"] == "https://proxy/api"
    assert mine["PREFECT_SERVER_ANALYTICS_ENABLED"] == "true"


def test_the_banner_names_the_api_in_the_command_it_prints():
    text = serve_banner("http://127.0.0.1:45123/api", "graspcap-build/graspcap-build",
                        "every 60 s")
    assert "Prefect UI:  http://127.0.0.1:45123  (the builds' flow runs: " \
           "http://127.0.0.1:45123/runs)" in text
    assert "Prefect API: http://127.0.0.1:45123/api" in text
    command = text.splitlines()[-1].strip()
    assert command == (f"PREFECT_API_URL=http://127.0.0.1:45123/api {sys.executable} -m prefect "
                       "deployment run graspcap-build/graspcap-build")


def test_one_line_per_finished_run_says_what_the_build_made():
    record = {"build_id": "b1", "catalog_version": 3, "previous_version": 2,
              "report_page": "/c/reports/b1/index.html",
              "summary": {"added": ["s1"], "changed": [], "unchanged": ["s2", "s3"],
                          "failed": {"s4": "reconstruct_hand: only 52 % inliers\nmore"}}}
    line = run_line("brave-ant", "Completed", None, record)
    assert re.fullmatch(
        r"\[\d\d:\d\d:\d\d\] run brave-ant Completed: build b1: catalog version 3: 1 added, "
        r"0 changed, 2 unchanged, 1 failed; FAILED s4: reconstruct_hand: only 52 % inliers; "
        r"report /c/reports/b1/index.html", line), line
    same = run_line("calm-owl", "Completed", None, {
        **record, "catalog_version": None, "report_page": None,
        "summary": {"added": [], "changed": [], "unchanged": ["s1"], "failed": {}}})
    assert same.endswith("build b1: no new version (still 2): 0 added, 0 changed, "
                         "1 unchanged, 0 failed")
    broken = run_line("odd-elk", "Failed", "x", {**record, "error": "the catalog is locked"})
    assert broken.endswith("run odd-elk Failed: build b1 FAILED, nothing committed: the "
                           "catalog is locked")
    crashed = run_line("lost-cat", "Crashed", "Process exited with status code -9.\nmore", None)
    assert crashed.endswith("run lost-cat Crashed: Process exited with status code -9.")


def _clean_env(tmp_path: Path) -> dict[str, str]:
    """The environment of a user's fresh shell: none of the test harness's Prefect settings,
    its own home."""
    home = tmp_path / "home"
    home.mkdir(exist_ok=True)
    return {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")} | {
        "OMP_NUM_THREADS": "1", "HOME": str(home)}


def _lines(proc: subprocess.Popen) -> queue.Queue:
    out: queue.Queue = queue.Queue()

    def pump():
        for line in proc.stdout:
            out.put(line.rstrip("\n"))
        out.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return out


def _wait_line(lines: queue.Queue, seen: list[str], pattern: str, timeout_s: float) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=1)
        except queue.Empty:
            continue
        if line is None:
            break
        seen.append(line)
        if re.search(pattern, line):
            return line
    raise AssertionError(f"no line matching {pattern!r}; serve printed:\n" + "\n".join(seen))


@pytest.mark.slow
def test_serve_shows_the_builds_runs_and_logs_in_a_real_browser(warm, synth_root, tmp_path):
    binary, why = find_chromium()
    if binary is None:
        pytest.skip(why)
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    env = _clean_env(tmp_path)
    # a build from the command line first: its run is in the database serve's server uses
    built = subprocess.run([sys.executable, "-m", "graspcap.cli", "build", str(synth_root),
                            "--catalog", str(catalog), "--preset", PRESET], env=env,
                           cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stdout + built.stderr
    proc = subprocess.Popen([sys.executable, "-m", "graspcap.cli", "serve", str(synth_root),
                             "--catalog", str(catalog), "--preset", PRESET,
                             "--cron", "0 0 1 1 *"], env=env, cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines, seen = _lines(proc), []
    try:
        ui = _wait_line(lines, seen, r"^Prefect UI: ", 300).split()[2]
        command = _wait_line(lines, seen, r"^  PREFECT_API_URL=", 60).strip()
        # pasted in another shell (no Prefect setting of ours in it): starts a build now
        pasted = subprocess.run(["bash", "-c", command], env=env, cwd=tmp_path,
                                capture_output=True, text=True, timeout=300)
        assert pasted.returncode == 0, pasted.stdout + pasted.stderr
        run_id = re.search(r"UUID: ([0-9a-f-]{36})", pasted.stdout).group(1)
        name = re.search(r"Created flow run '([^']+)'", pasted.stdout).group(1)
        done = _wait_line(lines, seen, rf"run {name} ", 600)
        assert re.search(rf"run {name} Completed: build \S+: no new version \(still 1\): 0 "
                         r"added, 0 changed, 2 unchanged, 0 failed", done), done

        import httpx  # the REST API itself: this process's Prefect client is the harness's

        runs = httpx.post(f"{ui}/api/flow_runs/filter", timeout=60, json={  # not the cron's
            "flow_runs": {"state": {"type": {"any_": ["COMPLETED"]}}}}).json()  # next one
        names = sorted(r["name"] for r in runs)
        assert len(names) == 2 and name in names  # the command line's build and this one

        with HeadlessChromium(binary) as browser:
            browser.open(f"{ui}/runs")
            for n in names:
                text = browser.wait_for_text(n, timeout_s=120, refuse=(API_ERROR,))
            assert "Completed" in text
            browser.wait_for_text("graspcap-build", timeout_s=60, refuse=(API_ERROR,))  # flow
            browser.open(f"{ui}/runs/flow-run/{run_id}")  # its log: a line per stage
            text = browser.wait_for_text("load_session Cached", timeout_s=120,
                                         refuse=(API_ERROR,))
            assert "nothing changed, no new catalog version (still 1)" in text  # the summary
            assert "didn't generate logs" not in text
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    port = int(ui.rsplit(":", 1)[1])
    with socket.socket() as s:  # the supervised server is gone with it
        assert s.connect_ex(("127.0.0.1", port)) != 0


def test_the_report_page_opens_from_disk_in_a_real_browser(warm):
    """The build's report page in headless Chromium from ``file://``: every session's row and
    every picture loads (no server; the test of the page's HTML is tests/report_html.py)."""
    binary, why = find_chromium()
    if binary is None:
        pytest.skip(why)
    catalog, report = warm
    page = Path(report.report_page)
    with HeadlessChromium(binary) as browser:
        browser.open(page.as_uri())
        text = browser.wait_for_text("Sessions of version 1", timeout_s=60)
        for sid in report.added:
            assert sid in text
        images = browser.evaluate(  # the thumbnails load lazily: load each now, wait for it
            "Promise.all(Array.from(document.images).map(i => { i.loading = 'eager'; "
            "return i.decode().then(() => [true, i.naturalWidth, i.getAttribute('src')], "
            "() => [false, 0, i.getAttribute('src')]); }))")
        assert images, "no pictures on the page"
        broken = [src for loaded, width, src in images if not (loaded and width > 0)]
        assert broken == [], broken
        png = browser.screenshot()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
