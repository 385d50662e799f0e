"""A minimal TOML writer for the small files calibration writes.

Python 3.11 reads TOML with :mod:`tomllib` but cannot write it, and we take no
dependency for that. This writes the subset we need: a flat table of scalars
and (nested) lists, followed by sub-tables ``[name]`` of the same. Floats are
written with ``repr`` so they read back bit-exactly.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["dumps"]


def _key(k: str) -> str:
    if k and all(c.isalnum() or c in "_-" for c in k):
        return k
    return _string(k)


def _string(s: str) -> str:
    out = s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t")
    return f'"{out}"'


def _value(v: Any) -> str:
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if math.isnan(f):
            return "nan"
        if math.isinf(f):
            return "inf" if f > 0 else "-inf"
        return repr(f)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(str(k))} = {_value(x)}" for k, x in v.items()) + "}"
    if v is None:
        raise ValueError("TOML has no null value")
    raise ValueError(f"cannot write {type(v).__name__} to TOML")


def dumps(data: dict) -> str:
    """Serialize a dict of scalars, lists and one level of sub-tables (nested tables inline)."""
    lines: list[str] = []
    tables: list[tuple[str, dict]] = []
    for k, v in data.items():
        if isinstance(v, dict):
            tables.append((k, v))
        else:
            lines.append(f"{_key(str(k))} = {_value(v)}")
    for name, table in tables:
        if lines:
            lines.append("")
        lines.append(f"[{_key(str(name))}]")
        for k, v in table.items():
            lines.append(f"{_key(str(k))} = {_value(v)}")
    return "\n".join(lines) + "\n"
