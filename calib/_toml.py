"""TOML writing for the small files calibration writes, through ``tomli-w``.

Python reads TOML with :mod:`tomllib`; ``tomli_w`` writes it. This adapter only turns
numpy scalars and arrays into the plain Python values ``tomli_w`` accepts and names
what TOML cannot hold (``None``). Floats are written so they read back bit-exactly.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import tomli_w

__all__ = ["dumps"]


def _plain(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v)
    if isinstance(v, str):
        return v
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if v is None:
        raise ValueError("TOML has no null value")
    raise ValueError(f"cannot write {type(v).__name__} to TOML")


def dumps(data: dict) -> str:
    """Serialize a dict (tables, scalars, nested lists) to TOML text."""
    return tomli_w.dumps(_plain(data))
