"""Fixtures of the app tests: a real viser server on a free port with the app built on it."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import viser

from app.server import App, ViewerConfig, run

APP_POINTS = 3000
"""Points per cloud in the app tests (small: the tests check wiring, the core checks accuracy)."""


@pytest.fixture
def make_app() -> Iterator:
    """``make_app(**config)`` builds the app on a fresh ``ViserServer`` (port 0) and cleans up."""
    made: list[tuple[viser.ViserServer, App]] = []

    def factory(**kw) -> App:
        kw.setdefault("n_points", APP_POINTS)
        # the planner process (on in `pregrasp view`) only where a test asks for it: its
        # start-up and warm-up would cost every app test a second of CPU on a 2-core machine
        kw.setdefault("planner_process", False)
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        try:
            app = run(ViewerConfig(**kw), server)
        except BaseException:
            server.stop()
            raise
        made.append((server, app))
        return app

    yield factory
    for server, app in made:
        app.close()
        server.stop()


@pytest.fixture
def app(make_app) -> App:
    """The app on the default object (the mug with a handle) at :data:`APP_POINTS` points."""
    return make_app()
