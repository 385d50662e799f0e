"""Waiting in tests for something a background thread or another process does."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def wait_until(cond: Callable[[], T], *, timeout: float, what: str = "condition", poll: float = 0.05) -> T:
    """The first true value ``cond()`` returns, asked every ``poll`` seconds; an AssertionError
    naming ``what`` after ``timeout`` seconds."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = cond()
        if v:
            return v
        time.sleep(poll)
    raise AssertionError(f"timed out waiting for {what}")
