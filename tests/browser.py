"""Headless Chromium for the page tests: Debian's ``/usr/bin/chromium`` (or ``$STAGE_CHROMIUM``)
driven by Playwright, never a browser Playwright downloads."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

CHROMIUM = os.environ.get("STAGE_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]


def sync_playwright_or_skip():
    """Playwright's ``sync_playwright``, or a skip naming what is missing (the Chromium executable or
    the ``playwright`` package: things outside the project)."""
    if not (Path(CHROMIUM).is_file() and os.access(CHROMIUM, os.X_OK)):
        pytest.skip(f"no Chromium at {CHROMIUM} (apt-get install -y chromium, or set STAGE_CHROMIUM)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("the Python package playwright is not installed (pip install playwright; never `playwright install`)")
    return sync_playwright
