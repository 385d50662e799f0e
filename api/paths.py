"""Ids and paths: every path a request touches is built here and checked to stay inside the data root."""

from __future__ import annotations

import logging
import re
from pathlib import Path

__all__ = [
    "TAKE_ID",
    "RESERVED_SUFFIXES",
    "MAX_NAME_BYTES",
    "check_take_id",
    "take_id_rule",
    "upload_path",
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

#: what the files stored beside a take end in (``TAKE.derived.h5`` holds its masks, ``TAKE.gt.npz``
#: a simulated take's ground truth, ``TAKE.template.ply`` an RGB-D take's scan, ``.part``/``.tmp``
#: files being written): no take id ends in one (any case), so no id reaches them
RESERVED_SUFFIXES = (".derived", ".gt", ".template", ".part", ".tmp")
#: a path component (a file name) in bytes, as the file system counts it (ext4, XFS, APFS: 255)
MAX_NAME_BYTES = 255
_MAX_PATH_BYTES = 1024


class InvalidIdError(ValueError):
    """An id that does not match its pattern (maps to 400)."""


class OutsideDataRootError(ValueError):
    """A path that resolves outside the data root (maps to 400)."""


def check_id(value: str, *, pattern: str = TAKE_ID, name: str = "id") -> str:
    """Return ``value`` when it matches ``pattern`` and contains no ``..``; else raise :class:`InvalidIdError`."""
    if not isinstance(value, str) or not re.fullmatch(pattern, value) or ".." in value:
        raise InvalidIdError(f"{name} {value!r} is not valid (allowed: {pattern})")
    return value


def check_take_id(value: str, *, name: str = "take id") -> str:
    """The one rule for take ids (URL paths, bodies, queries): :data:`TAKE_ID` (ASCII, so
    characters are bytes; at most 128), no ``..``, and none of :data:`RESERVED_SUFFIXES`.

    Raises
    ------
    InvalidIdError
    """
    check_id(value, pattern=TAKE_ID, name=name)
    if value.lower().endswith(RESERVED_SUFFIXES):
        raise InvalidIdError(f"{name} {value!r} is not valid (ids ending in {', '.join(RESERVED_SUFFIXES)} "
                             f"name the files kept beside a take)")
    return value


def take_id_rule(value: str) -> str:
    """:func:`check_take_id` as a pydantic validator (``Annotated[str, AfterValidator(take_id_rule)]``)."""
    return check_take_id(value)


def upload_path(path: str) -> bool:
    """True for ``/takes/{id}``, the one URL a take file is PUT to."""
    parts = path.strip("/").split("/")
    return len(parts) == 2 and parts[0] == "takes" and parts[1] != "import"


def _too_long(rel: Path) -> bool:
    def nbytes(s: str) -> int:
        return len(s.encode("utf-8", "surrogateescape"))

    return nbytes(str(rel)) > _MAX_PATH_BYTES or any(nbytes(c) > MAX_NAME_BYTES for c in rel.parts)


def inside(root: Path, *parts: str | Path) -> Path:
    """``root / parts`` resolved, refusing anything that leaves ``root`` (symlinks included).

    Raises
    ------
    OutsideDataRootError
        When the resolved path is not ``root`` or below it.
    """
    base = Path(root).resolve()
    rel = Path(*[str(x) for x in parts]) if parts else Path()
    if "\0" in str(rel) or _too_long(rel):
        raise OutsideDataRootError(f"path is too long (a name holds at most {MAX_NAME_BYTES} bytes, a path "
                                   f"{_MAX_PATH_BYTES}) or contains a NUL byte")
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
