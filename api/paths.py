"""Ids and paths: every path a request touches is built here and checked to stay inside the data root."""

from __future__ import annotations

import re
from pathlib import Path

__all__ = [
    "TAKE_ID",
    "JOB_ID",
    "CAL_ID",
    "FILE_NAME",
    "InvalidIdError",
    "OutsideDataRootError",
    "check_id",
    "inside",
]

#: take ids: letters, digits, ``_ . -``; no leading dot; at most 128 characters.
TAKE_ID = r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,127}$"
#: job and calibration ids are uuid4 hex strings.
JOB_ID = r"^[0-9a-f]{32}$"
CAL_ID = TAKE_ID
#: a file name inside a result folder.
FILE_NAME = r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,127}$"

_TAKE_RE = re.compile(TAKE_ID)


class InvalidIdError(ValueError):
    """An id that does not match its pattern (maps to 400)."""


class OutsideDataRootError(ValueError):
    """A path that resolves outside the data root (maps to 400)."""


def check_id(value: str, *, pattern: str = TAKE_ID, name: str = "id") -> str:
    """Return ``value`` when it matches ``pattern`` and contains no ``..``; else raise :class:`InvalidIdError`."""
    if not isinstance(value, str) or not re.fullmatch(pattern, value) or ".." in value:
        raise InvalidIdError(f"{name} {value!r} is not valid (allowed: {pattern})")
    return value


def inside(root: Path, *parts: str | Path) -> Path:
    """``root / parts`` resolved, refusing anything that leaves ``root`` (symlinks included).

    Raises
    ------
    OutsideDataRootError
        When the resolved path is not ``root`` or below it.
    """
    base = Path(root).resolve()
    rel = Path(*[str(x) for x in parts]) if parts else Path()
    if "\0" in str(rel) or len(str(rel)) > 1024 or any(len(c) > 255 for c in rel.parts):
        raise OutsideDataRootError("path is too long or contains a NUL byte")
    try:
        p = base.joinpath(rel).resolve()
    except (OSError, RuntimeError) as exc:  # symlink loops, unreadable components
        raise OutsideDataRootError(f"path cannot be resolved ({type(exc).__name__})") from None
    if not p.is_relative_to(base):
        raise OutsideDataRootError("path is outside the data root")
    return p
