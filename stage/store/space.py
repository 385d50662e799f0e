"""Disk space: checks before writing and one clear error when the disk fills up.

Every writer of the project (the take writer, the derived-data file, import, processing) asks
:func:`check_free_space` before it starts when it knows what it will need, and turns the
errors a full disk raises deep inside HDF5 or numpy (``OSError`` with ``ENOSPC``, or h5py's
``RuntimeError``/``OSError`` quoting ``errno = 28``) into one :class:`DiskFullError` through
:func:`is_disk_full` / :func:`disk_full_error`.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
from pathlib import Path
from typing import Iterator

__all__ = ["DiskFullError", "free_bytes", "check_free_space", "is_disk_full", "disk_full_error", "raise_disk_full", "format_bytes"]


class DiskFullError(OSError):
    """The disk (or quota) is full; the message says where and how much space was needed."""

    def __init__(self, message: str) -> None:
        super().__init__(errno.ENOSPC, message)
        self.message = message

    def __str__(self) -> str:
        return self.message


def format_bytes(n: float) -> str:
    """``1536`` -> ``"1.5 KiB"``."""
    n = float(n)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"  # pragma: no cover


def _existing_dir(path: Path) -> Path:
    p = Path(path)
    while not p.exists() and p != p.parent:
        p = p.parent
    return p if p.is_dir() else p.parent


def free_bytes(path: str | os.PathLike) -> int:
    """Free bytes (for this user) on the filesystem holding ``path`` (or its nearest existing parent)."""
    return int(shutil.disk_usage(_existing_dir(Path(path))).free)


def check_free_space(path: str | os.PathLike, need: int, what: str) -> None:
    """Raise :class:`DiskFullError` when fewer than ``need`` bytes are free where ``path`` goes.

    Parameters
    ----------
    path : path
        The file to be written (or its directory).
    need : int
        Bytes the write is expected to take.
    what : str
        What is written, for the message (e.g. ``"the masks of take1.h5"``).
    """
    free = free_bytes(path)
    if free < need:
        raise DiskFullError(
            f"{Path(path).parent if not Path(path).is_dir() else Path(path)}: not enough free space for {what}: "
            f"about {format_bytes(need)} needed, {format_bytes(free)} free"
        )


def is_disk_full(exc: BaseException) -> bool:
    """True when ``exc`` (or what caused it) is a full disk or quota."""
    seen = 0
    while exc is not None and seen < 8:
        if isinstance(exc, DiskFullError):
            return True
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        msg = str(exc)
        if "errno = 28" in msg or "No space left on device" in msg or "errno = 122" in msg or "Disk quota exceeded" in msg:
            return True
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return False


def disk_full_error(path: str | os.PathLike, what: str, need: int | None = None, *, detail: str = "") -> DiskFullError:
    """The :class:`DiskFullError` for a write of ``what`` into ``path`` that hit a full disk."""
    try:
        free = format_bytes(free_bytes(path))
    except OSError:  # pragma: no cover
        free = "unknown"
    needed = f"about {format_bytes(need)} needed, " if need else ""
    tail = f"; {detail}" if detail else ""
    return DiskFullError(f"{path}: disk full while writing {what} ({needed}{free} free){tail}")


@contextlib.contextmanager
def raise_disk_full(path: str | os.PathLike, what: str, need: int | None = None, *, detail: str = "") -> Iterator[None]:
    """Turn a full-disk error raised inside the block into one :class:`DiskFullError`."""
    try:
        yield
    except DiskFullError:
        raise
    except (OSError, RuntimeError, ValueError) as exc:
        if not is_disk_full(exc):
            raise
        raise disk_full_error(path, what, need, detail=detail) from None
