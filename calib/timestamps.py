"""Synchronise videos of several cameras by a timestamps file.

Two layouts are read (CSV with a header row):

- caliscope's ``timestamps.csv``: ``sync_index, cam_id, frame_time``. Frames of one
  ``sync_index`` were taken together; the n-th row of a camera is the n-th frame of
  its video. The frame set is the sync index.
- a plain ``camera, frame, time_s``: the camera's name (or number), the frame index
  in its video, the time in seconds. Frames of different cameras are matched to the
  camera with the most frames by the nearest time, when within half its frame
  period; the frame set is that camera's frame index.

Camera ids match a video named ``<id>``, ``cam_<id>`` or ``cam<id>``. The result
maps every camera to ``{frame index in its video: frame set}``; gaps and unknown
cameras are reported by name.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["read_timestamps", "TimestampsError"]


class TimestampsError(ValueError):
    """The timestamps file cannot be used (names the file, the camera and the row)."""


def _match(cam_id: str, cameras: Sequence[str]) -> str | None:
    for name in cameras:
        if name == cam_id or name in (f"cam_{cam_id}", f"cam{cam_id}"):
            return name
    return None


def _rows(path: Path) -> tuple[list[str], list[dict]]:
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            header = [h.strip() for h in (reader.fieldnames or [])]
            rows = [{k.strip(): (v or "").strip() for k, v in r.items() if k is not None} for r in reader]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise TimestampsError(f"--timestamps {path}: cannot be read: {exc}") from None
    return header, rows


def read_timestamps(path: str | Path, cameras: Sequence[str]) -> tuple[dict[str, dict[int, int]], list[str]]:
    """Frame sets of every camera's video frames from a timestamps file.

    Parameters
    ----------
    path : str or Path
    cameras : sequence of str
        Camera names (the videos).

    Returns
    -------
    sets : dict
        Camera -> ``{video frame index: frame set}``.
    warnings : list of str
        Gaps (frame sets without a frame of a camera), frames without a partner in time.

    Raises
    ------
    TimestampsError
        Unknown layout, unknown camera, unreadable values, a camera of ``cameras`` absent.
    """
    p = Path(path)
    if not p.is_file():
        raise TimestampsError(f"--timestamps {p}: no such file")
    header, rows = _rows(p)
    if {"sync_index", "cam_id", "frame_time"} <= set(header):
        sets, warnings = _caliscope(p, rows, cameras)
    elif {"camera", "frame", "time_s"} <= set(header):
        sets, warnings = _plain(p, rows, cameras)
    else:
        raise TimestampsError(f"--timestamps {p}: expected the columns sync_index, cam_id, frame_time (caliscope) "
                              f"or camera, frame, time_s; found {', '.join(header) or 'no header'}")
    absent = [c for c in cameras if not sets.get(c)]
    if absent:
        raise TimestampsError(f"--timestamps {p}: no rows for camera(s) {', '.join(absent)}")
    return sets, warnings


def _camera_of(p: Path, raw: str, cameras: Sequence[str], line: int) -> str:
    name = _match(raw, cameras)
    if name is None:
        raise TimestampsError(f"--timestamps {p}, line {line}: unknown camera {raw!r} (cameras: {', '.join(cameras)})")
    return name


def _number(p: Path, row: dict, key: str, line: int, kind=float):
    try:
        return kind(row[key])
    except (TypeError, ValueError):
        raise TimestampsError(f"--timestamps {p}, line {line}: {key} {row.get(key)!r} is not a number") from None


def _caliscope(p: Path, rows: list[dict], cameras: Sequence[str]):
    sets: dict[str, dict[int, int]] = {c: {} for c in cameras}
    for line, r in enumerate(rows, start=2):
        name = _camera_of(p, r["cam_id"], cameras, line)
        s = _number(p, r, "sync_index", line, int)
        _number(p, r, "frame_time", line)
        sets[name][len(sets[name])] = s
    warnings = []
    for name, m in sets.items():
        if not m:
            continue
        have = set(m.values())
        lo, hi = min(have), max(have)
        miss = sorted(set(range(lo, hi + 1)) - have)
        if miss:
            warnings.append(f"{name}: the timestamps have no frame for {len(miss)} sync index(es) between {lo} and "
                            f"{hi} (first {miss[0]}); those frame sets lack {name}")
    return sets, warnings


def _plain(p: Path, rows: list[dict], cameras: Sequence[str]):
    times: dict[str, dict[int, float]] = {c: {} for c in cameras}
    for line, r in enumerate(rows, start=2):
        name = _camera_of(p, r["camera"], cameras, line)
        f = _number(p, r, "frame", line, int)
        t = _number(p, r, "time_s", line)
        if f < 0 or not np.isfinite(t):
            raise TimestampsError(f"--timestamps {p}, line {line}: frame must be >= 0 and time_s finite")
        times[name][f] = t
    present = [c for c in cameras if times[c]]
    if not present:
        return {c: {} for c in cameras}, []
    ref = max(present, key=lambda c: len(times[c]))
    rf = np.array(sorted(times[ref]))
    rt = np.array([times[ref][f] for f in rf])
    if len(rt) < 2:
        raise TimestampsError(f"--timestamps {p}: camera {ref} needs at least 2 timed frames")
    order = np.argsort(rt)
    rf, rt = rf[order], rt[order]
    period = float(np.median(np.diff(rt)))
    if not period > 0:
        raise TimestampsError(f"--timestamps {p}: camera {ref}'s frame times do not increase")
    warnings = []
    sets: dict[str, dict[int, int]] = {}
    for name in cameras:
        fr = np.array(sorted(times[name]), dtype=np.int64)
        if fr.size == 0:
            sets[name] = {}
            continue
        t = np.array([times[name][f] for f in fr])
        gaps = np.flatnonzero(np.diff(t) > 1.5 * period)
        if gaps.size:
            warnings.append(f"{name}: the timestamps jump by {np.diff(t)[gaps].max():.2f} s at {gaps.size} place(s) "
                            f"(first after frame {fr[gaps[0]]}); no frames were taken there")
        j = np.clip(np.searchsorted(rt, t), 1, len(rt) - 1)
        j = np.where(np.abs(rt[j - 1] - t) <= np.abs(rt[j] - t), j - 1, j)
        dt = np.abs(rt[j] - t)
        ok = dt <= 0.5 * period
        best: dict[int, tuple[float, int]] = {}
        for f, jj, d in zip(fr[ok], j[ok], dt[ok]):
            s = int(rf[jj])
            if s not in best or d < best[s][0]:
                best[s] = (float(d), int(f))
        sets[name] = {f: s for s, (_, f) in best.items()}
        lost = int(fr.size - len(sets[name]))
        if lost and name != ref:
            warnings.append(f"{name}: {lost} frame(s) have no frame of {ref} within half a frame period "
                            f"({0.5 * period:.3f} s) and are not used")
    return sets, warnings
