"""Headless Chromium for the page tests: Debian's ``/usr/bin/chromium`` (or ``$STAGE_CHROMIUM``)
driven by Playwright, never a browser Playwright downloads."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
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


def not_blank(png: bytes, what: str) -> np.ndarray:
    """Decode a screenshot and assert it shows a drawing: many colours, some contrast, ink on the background."""
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[0] > 200 and img.shape[1] > 300, (what, None if img is None else img.shape)
    px = img.reshape(-1, 3).astype(int)
    colours = len(np.unique(px // 8, axis=0))
    background = np.median(px, axis=0)
    ink = (np.abs(px - background).sum(1) > 60).mean()
    assert colours > 40, f"{what}: only {colours} distinct colours: blank?"
    assert float(img.std()) > 5.0, f"{what}: no contrast (std {img.std():.2f})"
    assert ink > 0.003, f"{what}: almost nothing drawn ({ink:.4%} of the pixels differ from the background)"
    return img


def artifacts_dir(tmp_path: Path, name: str) -> Path:
    """Where a test keeps its screenshots: ``$STAGE_TEST_ARTIFACTS/name`` (CI keeps them), else under ``tmp_path``."""
    env = os.environ.get("STAGE_TEST_ARTIFACTS")
    d = Path(env) / name if env else tmp_path / "artifacts"
    d.mkdir(parents=True, exist_ok=True)
    return d
