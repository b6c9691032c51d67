"""Headless Debian Chromium for the report tests (and the README's screenshot): load a page from
disk, read its console and DOM, take a screenshot. No network: the page is a local file, and
every feature that would call out is switched off.

The README's screenshot, after `make demo`:
    .venv/bin/python tests/browser.py demo-out/report.html docs/demo_report.png '#frame=40'
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-extensions", "--disable-default-apps", "--hide-scrollbars"]


def chromium() -> str | None:
    """The Chromium executable, or None when none is installed."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _run(url: str, *extra: str, timeout: float = 90.0) -> subprocess.CompletedProcess:
    exe = chromium()
    if exe is None:
        raise RuntimeError("no chromium")
    with tempfile.TemporaryDirectory(prefix="rngcam-chromium-") as profile:
        return subprocess.run([exe, *FLAGS, f"--user-data-dir={profile}", *extra, url],
                              capture_output=True, text=True, timeout=timeout, check=False)


def load(page: Path, fragment: str = "") -> tuple[str, list[str]]:
    """(the DOM after the page's script ran, the console messages it logged)."""
    res = _run(page.resolve().as_uri() + fragment, "--enable-logging=stderr", "--v=0", "--dump-dom")
    console = [line for line in res.stderr.splitlines() if re.search(r":CONSOLE[:(]", line)]
    return res.stdout, console


def screenshot(page: Path, png: Path, fragment: str = "", size: str = "1200,1400") -> Path:
    """A screenshot of `page` (opened at `fragment`, e.g. '#frame=30') into `png`."""
    png.parent.mkdir(parents=True, exist_ok=True)
    res = _run(page.resolve().as_uri() + fragment, f"--window-size={size}", f"--screenshot={png}")
    if not png.is_file():
        raise RuntimeError(f"chromium wrote no screenshot: {res.stderr[-500:]}")
    return png


if __name__ == "__main__":
    import sys

    if len(sys.argv) not in (3, 4):
        sys.exit("usage: browser.py PAGE.html SHOT.png ['#frame=N']")
    print(screenshot(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3] if len(sys.argv) == 4 else "", "1280,900"))
