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


#: the WCAG 2 contrast ratio of every visible text element of the page against its first opaque background
#: below 4.5 (AA for text under 18 pt): {"colour on background": [ratio, element]}
LOW_CONTRAST = """() => {
  const parse = (c) => c.match(/[\\d.]+/g).map(Number);
  const lum = (c) => { const f = (v) => { v /= 255; return v <= 0.03928 ? v / 12.92 : Math.pow((v + 0.055) / 1.055, 2.4); };
                       const m = parse(c); return 0.2126 * f(m[0]) + 0.7152 * f(m[1]) + 0.0722 * f(m[2]); };
  const bg = (e) => { for (; e; e = e.parentElement){ const c = getComputedStyle(e).backgroundColor; const m = parse(c);
                        if (m.length < 4 || m[3] === 1) return c; } return 'rgb(255, 255, 255)'; };
  const out = {};
  for (const e of document.querySelectorAll('body *')){
    if (![...e.childNodes].some((n) => n.nodeType === 3 && n.textContent.trim()) || !e.checkVisibility()) continue;
    if (e.closest('.frame')) continue;  // the badges over the pictures: white on a dark veil over an image
    if (e.closest('button:disabled, input:disabled')) continue;  // inactive controls: exempt (WCAG 1.4.3)
    const s = getComputedStyle(e); const a = lum(s.color), b = lum(bg(e));
    const r = (Math.max(a, b) + 0.05) / (Math.min(a, b) + 0.05);
    if (r < 4.5) out[s.color + ' on ' + bg(e)] = [Math.round(r * 100) / 100,
                                                  e.tagName + '.' + e.className + ': ' + e.textContent.trim().slice(0, 40)];
  }
  return out;
}"""

#: the controls and pictures of the page without an accessible name (label, aria-label, alt or text)
UNNAMED = """() => [...document.querySelectorAll('input, button, select, progress, canvas, img')]
  .filter((e) => !(e.labels && e.labels.length) && !e.getAttribute('aria-label') && !e.getAttribute('alt')
                 && !(e.textContent || '').trim())
  .map((e) => e.tagName + '#' + e.id + '.' + e.className)"""
