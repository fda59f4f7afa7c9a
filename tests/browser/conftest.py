"""Browser tests: the real app server on a free port, driven by headless Chromium via Python
playwright (Debian's ``/usr/bin/chromium``; never ``playwright install``).

When Chromium or playwright is missing these tests FAIL with a message saying how to install
them; they are never skipped (``scripts/test.sh`` installs Chromium on a fresh machine).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.headless import CHROMIUM, launch

SHOTS_DIR = Path(os.environ.get("PREGRASP_SHOTS_DIR", tempfile.gettempdir())) / "pregrasp-shots"
"""Where the browser tests save their screenshots."""


def pytest_collection_modifyitems(items):
    for item in items:
        if "tests/browser/" in str(item.fspath).replace(os.sep, "/"):
            item.add_marker(pytest.mark.browser)


@pytest.fixture(scope="session")
def chromium() -> str:
    """Path of the Chromium binary; fails (never skips) when it is not installed."""
    if not (os.path.isfile(CHROMIUM) and os.access(CHROMIUM, os.X_OK)):
        pytest.fail(
            f"the browser tests need Chromium at {CHROMIUM}: install it with "
            "`sudo apt-get install -y chromium` (scripts/test.sh does this as root), "
            "or point PREGRASP_CHROMIUM at a Chromium binary",
            pytrace=False,
        )
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        pytest.fail("the browser tests need playwright: pip install -e '.[test]'", pytrace=False)
    return CHROMIUM


@pytest.fixture(scope="module")
def browser_context(chromium) -> Iterator:
    """A persistent headless Chromium context (own temporary profile)."""
    from playwright.sync_api import sync_playwright

    profile = tempfile.mkdtemp(prefix="pregrasp-chromium-")
    with sync_playwright() as p:
        ctx = launch(
            p, profile, chromium, viewport={"width": 1400, "height": 900}, accept_downloads=True
        )
        try:
            yield ctx
        finally:
            ctx.close()
    shutil.rmtree(profile, ignore_errors=True)


@pytest.fixture(scope="module")
def live_app() -> Iterator:
    """The real app on a real ``ViserServer`` (127.0.0.1, free port) on the default object."""
    from app.server import ViewerConfig

    # as `pregrasp view` starts: ghosts off, the best grasp planned in the background
    with app_on_server(ViewerConfig(n_points=5000, plan_on_start=True)) as app:
        yield app


@contextlib.contextmanager
def app_on_server(config) -> Iterator:
    """The app of ``config`` (a ``ViewerConfig``) on a real ``ViserServer`` (127.0.0.1, a free
    port); closed, with its server, on the way out."""
    import viser

    from app.server import run

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        app = run(config, server)
        try:
            yield app
        finally:
            app.close()
    finally:
        server.stop()


@pytest.fixture(scope="module")
def shots_dir() -> Path:
    SHOTS_DIR.mkdir(parents=True, exist_ok=True)
    return SHOTS_DIR


def look_from(client, eye, look, deadline: float) -> None:
    """Move ``client``'s browser camera to ``eye`` looking at ``look`` (world, metres) and wait
    until the browser reports that pose and has been quiet for 1.5 s (it animates to a new pose
    and reports its camera on the way); ``deadline``: ``time.monotonic()`` to give up at."""
    import numpy as np
    import viser.transforms as vtf

    eye, look = np.asarray(eye, dtype=float), np.asarray(look, dtype=float)
    reports: list[float] = []
    client.camera.on_update(lambda cam: reports.append(time.monotonic()))
    client.camera.position = eye  # position first: it moves look_at along
    client.camera.look_at = look
    want = (look - eye) / np.linalg.norm(look - eye)
    while True:
        R = vtf.SO3(np.asarray(client.camera.wxyz)).as_matrix()
        near = np.linalg.norm(np.asarray(client.camera.position) - eye) < 1e-4
        quiet = bool(reports) and time.monotonic() - reports[-1] > 1.5
        if near and quiet and float(R[:, 2] @ want) > np.cos(1e-3):
            return
        assert time.monotonic() < deadline, "the browser did not take the camera"
        time.sleep(0.1)
