"""Check a take from end to end: its structure, and every chunk of every dataset.

Takes written since checksums were added store every chunk with HDF5's Fletcher-32 checksum
(``/`` attribute ``checksums = "fletcher32"``), so a damaged chunk fails to read; older takes
have none, and damage inside their frame data cannot be told from a picture (the report says
so). :func:`verify_take` reads every committed row of every per-frame dataset a block at a time
and, where a block fails, row by row, so the report names each damaged camera frame and the
frame sets that hold it. HDF5 offers no "check this file" call from Python (its ``h5check``
tool is not shipped with h5py), hence the walk here.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from stage.store._format import RESERVED, TakeError
from stage.store.reader import TakeReader

__all__ = ["TakeDamage", "verify_take", "frames_text"]

_BLOCK = 32  # rows read at once before looking row by row


@dataclass
class TakeDamage:
    """What :func:`verify_take` found.

    Attributes
    ----------
    path : Path
    checksums : bool
        Every frame dataset carries checksums (False: a take written before they were added).
    frames : dict of camera id -> list of int
        Damaged rows (frames) of each camera, sorted.
    sets : list of int
        Frame sets holding a damaged frame, or whose own row is damaged, sorted.
    problems : list of str
        One line per damaged dataset (structure, metadata, per-frame data).
    n_sets : int
        Frame sets in the take.
    other : list of str
        The problems not confined to frames (metadata, the set table, a camera's plate): a run
        cannot skip them.
    """

    path: Path
    checksums: bool
    frames: dict[str, list[int]] = field(default_factory=dict)
    sets: list[int] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    n_sets: int = 0
    other: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    @property
    def skippable(self) -> bool:
        """All the damage lies in frames: skipping the frame sets in :attr:`sets` (and keying no
        damaged frame) leaves a take that reads whole."""
        return not self.other

    def _other(self, line: str) -> None:
        self.problems.append(line)
        self.other.append(line)

    def summary(self) -> str:
        """One line: the damaged cameras and frames, or that none were found."""
        if self.ok:
            return f"{self.path}: {self.n_sets} frame sets, no damage found"
        cams = "; ".join(f"camera {c} frames {frames_text(v)}" for c, v in self.frames.items() if v)
        what = cams or self.problems[0]
        sets = f" (frame sets {frames_text(self.sets)})" if self.sets else ""
        return f"{self.path}: damaged take: {what}{sets}"


def frames_text(rows, limit: int = 12) -> str:
    """``0-3, 7, 9`` for rows 0, 1, 2, 3, 7, 9 (at most ``limit`` ranges, then ``...``)."""
    rows = sorted(int(r) for r in rows)
    runs: list[list[int]] = []
    for r in rows:
        if runs and r == runs[-1][1] + 1:
            runs[-1][1] = r
        else:
            runs.append([r, r])
    parts = [f"{a}" if a == b else f"{a}-{b}" for a, b in runs]
    return ", ".join(parts[:limit]) + (f", ... ({len(rows)} in all)" if len(parts) > limit else "")


def _bad_rows(ds: h5py.Dataset, n: int) -> list[int]:
    """Rows ``0..n-1`` of ``ds`` that cannot be read (a block at a time, row by row where it fails)."""
    bad: list[int] = []
    for a in range(0, n, _BLOCK):
        b = min(n, a + _BLOCK)
        try:
            ds[a:b]
            continue
        except (OSError, ValueError, KeyError, RuntimeError):
            pass
        for i in range(a, b):
            try:
                ds[i]
            except (OSError, ValueError, KeyError, RuntimeError):
                bad.append(i)
    return bad


def _jpeg_bad_rows(g: h5py.Group, n: int, off: np.ndarray, length: np.ndarray) -> list[int]:
    """Frames whose JPEG bytes touch an unreadable chunk of the byte stream."""
    ds = g["jpeg"]
    step = int(ds.chunks[0])
    end = int((off[:n] + length[:n]).max()) if n else 0
    bad_chunks = [c for c in range(0, end, step) if not _readable(ds, slice(c, min(end, c + step)))]
    rows = []
    for c in bad_chunks:
        hit = (length[:n] > 0) & (off[:n] < c + step) & (off[:n] + length[:n] > c)
        rows += np.flatnonzero(hit).tolist()
    return sorted(set(rows))


def _readable(ds: h5py.Dataset, sel=()) -> bool:
    try:
        ds[sel]
        return True
    except (OSError, ValueError, KeyError, RuntimeError):
        return False


def _check_camera(r: TakeReader, cam: str, out: TakeDamage) -> None:
    g = r._f["cameras"][cam]
    n = r.n_frames(cam)
    rows: set[int] = set()
    for name in g:
        ds = g[name]
        if not isinstance(ds, h5py.Dataset) or name == "jpeg":
            continue
        if name not in RESERVED:  # arrays shot with the capture (the plate): whole or damaged
            if not _readable(ds):
                out._other(f"camera {cam}: {name} cannot be read")
            continue
        bad = _bad_rows(ds, n)
        if bad:
            out.problems.append(f"camera {cam}: {name} of frames {frames_text(bad)} cannot be read")
            rows.update(bad)
    if "jpeg" in g:
        try:
            off, length = g["jpeg_offset"][:n], g["jpeg_length"][:n]
        except (OSError, ValueError, KeyError, RuntimeError):
            off = length = None  # already named above
        if off is not None:
            bad = _jpeg_bad_rows(g, n, off, length)
            if bad:
                out.problems.append(f"camera {cam}: JPEG bytes of frames {frames_text(bad)} cannot be read")
                rows.update(bad)
    if rows:
        out.frames[cam] = sorted(rows)


def verify_take(path: str | os.PathLike) -> TakeDamage:
    """Read every chunk of a take and say what is damaged.

    Parameters
    ----------
    path : path
        The take.

    Returns
    -------
    TakeDamage
        ``ok`` when nothing is damaged; else the damaged frames of each camera and the sets
        holding them.

    Raises
    ------
    FileNotFoundError
        No such file.
    TakeError
        The take cannot be opened at all (damaged header, truncated, not a take): one line.
    """
    p = Path(path)
    with TakeReader(p) as r:
        out = TakeDamage(path=p, checksums=r.checksums, n_sets=r.n_sets)
        for name in ("meta/rig", "meta/calibration", "meta/extra"):
            try:
                r._read_json(name)
            except TakeError:
                out._other(f"{name} cannot be read")
        try:
            r._f["meta/sync_stats"][:]
        except (OSError, ValueError, KeyError, RuntimeError):
            out._other("meta/sync_stats cannot be read")
        bad_sets: set[int] = set()
        for name in ("frames", "time_ns"):
            bad = _bad_rows(r._f["sets"][name], r.n_sets)
            if bad:
                out._other(f"sets/{name} of frame sets {frames_text(bad)} cannot be read")
                bad_sets.update(bad)
        for cam in r.cameras:
            _check_camera(r, cam, out)
        if out.frames:
            try:
                table = r.set_table()
            except TakeError:
                table = None
            if table is not None:
                for cam, rows in out.frames.items():
                    col = table[:, r.cameras.index(cam)]
                    bad_sets.update(np.flatnonzero(np.isin(col, rows)).tolist())
        out.sets = sorted(bad_sets)
    return out
