"""Headless Chromium for the browser tests and the documentation screenshots: Debian's
``chromium`` driven by Python playwright (never ``playwright install``, which downloads a
browser). Software WebGL is enough for viser's scene."""

from __future__ import annotations

import os
from typing import Any

CHROMIUM: str = os.environ.get("PREGRASP_CHROMIUM", "/usr/bin/chromium")
"""The browser binary (Debian's chromium package; ``PREGRASP_CHROMIUM`` overrides it)."""

CHROMIUM_ARGS: tuple[str, ...] = (
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--disable-sync",
)
"""Flags for a headless run as root, without a GPU and without network side traffic."""


def launch(playwright: Any, user_data_dir: str, executable: str = CHROMIUM, **options: Any) -> Any:
    """A persistent headless Chromium context with its own profile directory (``options``:
    playwright's ``launch_persistent_context`` keywords such as ``viewport``)."""
    return playwright.chromium.launch_persistent_context(
        user_data_dir=user_data_dir,
        executable_path=executable,
        headless=True,
        args=list(CHROMIUM_ARGS),
        **options,
    )
