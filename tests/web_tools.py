"""The web tools the tests check us against: the pinned npm packages of tests/npm (PlayCanvas'
splat-transform, the Spark splat viewer and three.js), headless Chromium driven by Playwright,
and a local HTTP server for the pages they open."""
import contextlib
import fcntl
import functools
import http.server
import os
import shutil
import subprocess
import threading
from pathlib import Path

import pytest

from gs_regional.studio.tour import CHROMIUM_ARGS  # software WebGL, no calls to Google's hosts

NPM_TOOLS = Path(__file__).parent / "npm"  # package.json + lock; installed into npm/node_modules (ignored by git)


def npm_tool(relative: str) -> Path:
    """tests/npm/node_modules/`relative`, installed on first use from tests/npm's lock file
    (`npm ci`). Skipped only where node or npm is missing; a failing install fails the test,
    naming the folder."""
    path = NPM_TOOLS / "node_modules" / relative
    if path.exists():
        return path
    npm = shutil.which("npm")
    if not (shutil.which("node") and npm):
        pytest.skip(f"node/npm not found: {relative} (tests/npm) needs Node.js (apt-get install nodejs npm)")
    # One install at a time: test processes running side by side (pytest -n) would race.
    with open(NPM_TOOLS / "node_modules.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not path.exists():
            proc = subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=NPM_TOOLS, capture_output=True,
                                  text=True, timeout=900)
            assert proc.returncode == 0 and path.exists(), f"npm ci in {NPM_TOOLS} failed:\n{proc.stderr[-3000:]}"
    return path


def chromium_path() -> str:
    """Chromium's executable ($CHROMIUM, or the first on PATH); skipped where there is none
    (`make test` installs Debian's package when it runs as root)."""
    for name in (os.environ.get("CHROMIUM"), "chromium", "chromium-browser", "google-chrome"):
        path = name and shutil.which(name)
        if path:
            return path
    pytest.skip("no Chromium installed (Debian: apt-get install chromium; or set CHROMIUM to its executable)")


@contextlib.contextmanager
def browser():
    """A headless Chromium under Playwright (skipped where either is missing)."""
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install playwright)")
    executable = chromium_path()
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # the test's output stays readable
        pass


@contextlib.contextmanager
def serve_folder(folder: Path):
    """`folder` over HTTP on a free localhost port (ES modules and fetch() need http://, not
    file://); yields the base URL."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_QuietHandler, directory=str(folder)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
