"""Debian's headless ``chromium`` for the browser tests: where it is, the skip that names the fix, and its launch
(software WebGL, no sandbox), so that every browser test starts the same browser."""

from __future__ import annotations

import os
import shutil

import pytest

CHROMIUM = shutil.which("chromium")

requires_chromium = pytest.mark.skipif(
    CHROMIUM is None and not os.environ.get("CI"),
    reason="chromium is not installed (apt-get install -y chromium); set CI=1 to require it",
)
"""Skips a test where chromium is absent, unless the environment variable CI is set: then it must run."""


def launch(playwright):
    """The headless browser, through Playwright's ``sync_playwright()`` handle ``playwright``."""
    assert CHROMIUM is not None, "CI is set but chromium is missing: apt-get install -y chromium"
    return playwright.chromium.launch(
        executable_path=CHROMIUM,
        headless=True,
        args=["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"],
    )
