"""Open a local HTML file in headless Chromium (Debian's ``chromium``): screenshot and rendered DOM.

Used by the report tests and by ``cpdetect compare --screenshot``. Flags follow what works on machines
without network: no sandbox (root), no GPU, no background networking.
"""
from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--virtual-time-budget=5000"]


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _run(args: list[str], timeout: float) -> subprocess.CompletedProcess:
    exe = find_chromium()
    if exe is None:
        raise FileNotFoundError("chromium not found (run make setup)")
    with tempfile.TemporaryDirectory() as profile:
        return subprocess.run([exe, *FLAGS, f"--user-data-dir={profile}", *args], capture_output=True,
                              text=True, timeout=timeout)


def dump_dom(html_path: str | Path, timeout: float = 60) -> str:
    """The DOM after the page's load handlers ran."""
    res = _run(["--dump-dom", Path(html_path).resolve().as_uri()], timeout)
    return res.stdout


def screenshot(html_path: str | Path, png_path: str | Path, width: int = 1280, height: int = 1600,
               timeout: float = 60) -> Path:
    png_path = Path(png_path).resolve()
    _run([f"--screenshot={png_path}", f"--window-size={width},{height}", Path(html_path).resolve().as_uri()], timeout)
    if not png_path.exists():
        raise RuntimeError("chromium did not write a screenshot")
    return png_path
