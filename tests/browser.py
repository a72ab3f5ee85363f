"""A real headless Chromium for the tests that look at pages (the Prefect UI of ``graspcap
serve``, the build's report page), driven over the DevTools protocol with ``websockets`` (a
Prefect dependency): no Selenium, no Playwright, nothing downloaded.

    with HeadlessChromium() as browser:
        browser.open("http://127.0.0.1:4200/runs")
        text = browser.wait_for_text("graspcap-build", timeout_s=60)
        png = browser.screenshot()

The browser is the Debian package (``chromium-headless-shell`` or ``chromium``; ``make setup``
installs the first where apt can), or the binary named by ``GRASPCAP_CHROMIUM``;
:func:`find_chromium` says why there is none, for the tests' skip reason.
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

CANDIDATES = ("chromium-headless-shell", "chromium", "google-chrome", "chrome")


def find_chromium() -> tuple[str | None, str]:
    """(the browser's path, "") or (None, why there is none)."""
    named = os.environ.get("GRASPCAP_CHROMIUM")
    if named:
        found = shutil.which(named)
        return (found, "") if found else (None, f"GRASPCAP_CHROMIUM={named} is not executable")
    for name in CANDIDATES:
        found = shutil.which(name)
        if found:
            return found, ""
    return None, (f"no headless browser ({', '.join(CANDIDATES)}) on PATH: `make setup` installs "
                  "the Debian package chromium-headless-shell where apt can, or set "
                  "GRASPCAP_CHROMIUM")


class BrowserError(RuntimeError):
    """The browser did not start, or a DevTools command failed."""


class HeadlessChromium:
    """One headless Chromium process with one page, for the duration of a ``with`` block."""

    def __init__(self, binary: str | None = None, width: int = 1280, height: int = 900,
                 start_timeout_s: float = 60.0):
        if binary is None:
            binary, why = find_chromium()
            if binary is None:
                raise BrowserError(why)
        self.binary, self.width, self.height = binary, width, height
        self.start_timeout_s = start_timeout_s
        self._ids = itertools.count(1)
        self._proc: subprocess.Popen | None = None
        self._ws: Any = None
        self._profile: tempfile.TemporaryDirectory | None = None

    def __enter__(self) -> HeadlessChromium:
        from websockets.sync.client import connect

        self._profile = tempfile.TemporaryDirectory(prefix="graspcap-chromium-",
                                                    ignore_cleanup_errors=True)
        profile = Path(self._profile.name)
        self._proc = subprocess.Popen(
            [self.binary, "--headless", "--no-sandbox", "--disable-gpu",
             "--disable-dev-shm-usage", "--no-first-run", "--hide-scrollbars",
             "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0",
             f"--user-data-dir={profile}", f"--window-size={self.width},{self.height}",
             "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            port = self._devtools_port(profile / "DevToolsActivePort")
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
                pages = [t for t in json.load(r) if t.get("type") == "page"]
            if not pages:
                raise BrowserError("the browser opened no page")
            self._ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None,
                               open_timeout=20)
            self.send("Page.enable")
            self.send("Runtime.enable")
            self.send("Emulation.setDeviceMetricsOverride", width=self.width,
                      height=self.height, deviceScaleFactor=1, mobile=False)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        if self._ws is not None:
            self._ws.close()
            self._ws = None
        if self._proc is not None:  # its own process group: the wrapper script's browser,
            _signal_group(self._proc, signal.SIGTERM)  # its zygotes and GPU process too
            try:
                self._proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                _signal_group(self._proc, signal.SIGKILL)
                self._proc.wait()
            deadline = time.monotonic() + 10  # the group's last members, still writing the
            while _signal_group(self._proc, 0) and time.monotonic() < deadline:  # profile
                time.sleep(0.1)
            _signal_group(self._proc, signal.SIGKILL)
            self._proc = None
        if self._profile is not None:
            self._profile.cleanup()
            self._profile = None

    def _devtools_port(self, port_file: Path) -> int:
        deadline = time.monotonic() + self.start_timeout_s
        while time.monotonic() < deadline:
            if self._proc is not None and self._proc.poll() is not None:
                raise BrowserError(f"{self.binary} exited with {self._proc.returncode}")
            try:
                first = port_file.read_text().splitlines()[0]
                return int(first)
            except (OSError, IndexError, ValueError):
                time.sleep(0.1)
        raise BrowserError(f"{self.binary} did not open its DevTools port within "
                           f"{self.start_timeout_s:g} s")

    def send(self, method: str, **params: Any) -> dict:
        """One DevTools command; its result (events that arrive meanwhile are dropped)."""
        if self._ws is None:
            raise BrowserError("the browser is not open (use it in a with block)")
        call = next(self._ids)
        self._ws.send(json.dumps({"id": call, "method": method, "params": params}))
        while True:
            msg = json.loads(self._ws.recv(timeout=60))
            if msg.get("id") == call:
                if "error" in msg:
                    raise BrowserError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def open(self, url: str) -> None:
        """Navigate to ``url`` (returns once the navigation is committed, not rendered)."""
        result = self.send("Page.navigate", url=url)
        if result.get("errorText"):
            raise BrowserError(f"{url}: {result['errorText']}")

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (awaited when it is a promise)."""
        result = self.send("Runtime.evaluate", expression=expression, returnByValue=True,
                           awaitPromise=True)
        if "exceptionDetails" in result:
            raise BrowserError(f"{expression[:60]}: {result['exceptionDetails']}")
        return result.get("result", {}).get("value")

    def text(self) -> str:
        """The page's visible text."""
        return self.evaluate("document.body ? document.body.innerText : ''") or ""

    def wait_for_text(self, needle: str, timeout_s: float = 60.0,
                      refuse: tuple[str, ...] = ()) -> str:
        """The page's text once it contains ``needle``; raises (with the text) when any of
        ``refuse`` shows first or ``timeout_s`` passes."""
        deadline = time.monotonic() + timeout_s
        text = ""
        while time.monotonic() < deadline:
            text = self.text()
            bad = [r for r in refuse if r in text]
            if bad:
                raise BrowserError(f"the page shows {bad[0]!r}:\n{text[:2000]}")
            if needle in text:
                return text
            time.sleep(0.5)
        raise BrowserError(f"{needle!r} not on the page after {timeout_s:g} s:\n{text[:2000]}")

    def screenshot(self, full_page: bool = False) -> bytes:
        """The page as PNG bytes: the viewport, or the whole page's height (``full_page``)."""
        params: dict[str, Any] = {"format": "png"}
        if full_page:
            size = self.send("Page.getLayoutMetrics")["cssContentSize"]
            params["clip"] = {"x": 0, "y": 0, "width": self.width,
                              "height": max(self.height, int(size["height"])), "scale": 1}
            params["captureBeyondViewport"] = True
        return base64.b64decode(self.send("Page.captureScreenshot", **params)["data"])


def _signal_group(proc: subprocess.Popen, sig: int) -> bool:
    """``sig`` to the process group ``proc`` leads (started with ``start_new_session``);
    False when the group has no process left (``sig`` 0 only asks)."""
    try:
        os.killpg(proc.pid, sig)
        return True
    except ProcessLookupError:
        return False


def main(argv: list[str] | None = None) -> int:
    """``python -m tests.browser URL OUT.png``: a screenshot of a page (how
    ``docs/report_page.png`` is made), as a 256-colour PNG to keep it small."""
    import argparse
    import io

    from PIL import Image

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("url")
    ap.add_argument("out", type=Path)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=900)
    ap.add_argument("--full", action="store_true", help="the whole page's height")
    ap.add_argument("--wait", default="", help="text to wait for before the screenshot")
    args = ap.parse_args(argv)
    with HeadlessChromium(width=args.width, height=args.height) as browser:
        browser.open(args.url)
        if args.wait:
            browser.wait_for_text(args.wait)
        png = browser.screenshot(full_page=args.full)
    image = Image.open(io.BytesIO(png)).convert("RGB").quantize(colors=256)
    image.save(args.out, optimize=True)
    print(f"{args.out}: {image.width} x {image.height}, {args.out.stat().st_size} bytes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
