"""Ids and paths: every path a request touches is built here and checked to stay inside the data root."""

from __future__ import annotations

import logging
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
    "confined",
    "confined_entries",
    "data_relative",
]

log = logging.getLogger("api")

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


def confined(path: Path, root: Path) -> bool:
    """True when ``path`` resolved (symlinks included) lies inside ``root``; logs a warning when it does not."""
    try:
        ok = Path(path).resolve().is_relative_to(Path(root).resolve())
    except (OSError, RuntimeError):
        ok = False
    if not ok:
        log.warning("%s points outside the data root; skipped", path)
    return ok


def confined_entries(directory: Path, pattern: str, *, root: Path) -> list[Path]:
    """Entries of ``directory`` matching ``pattern`` that resolve inside ``root`` (links out skipped, with a warning)."""
    d = Path(directory)
    if not d.is_dir() or not confined(d, root):
        return []
    return [p for p in sorted(d.glob(pattern)) if confined(p, root)]


def data_relative(obj, root: Path):
    """``obj`` (JSON-like) with every string path under ``root`` written as ``DATA/...``."""
    roots = sorted({str(Path(root)), str(Path(root).resolve())}, key=len, reverse=True)
    if isinstance(obj, str):
        for r in roots:
            obj = obj.replace(r, "DATA")
        return obj
    if isinstance(obj, dict):
        return {k: data_relative(v, root) for k, v in obj.items()}
    if isinstance(obj, list):
        return [data_relative(v, root) for v in obj]
    return obj
