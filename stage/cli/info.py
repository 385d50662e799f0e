"""``stage info``: summary of a take (also one being written or whose writer was killed)."""

from __future__ import annotations

import argparse
from pathlib import Path

ORDER = 22


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "info",
        help="print a take's summary: cameras, frames, fps, sync, compression, calibration, masks",
        description="Summarize an HDF5 take. Works on a take that is still being written and on one "
        "whose writer was killed (only frame sets flushed before the kill are counted).",
    )
    p.add_argument("take", type=Path, metavar="TAKE.h5")
    p.add_argument("--recover", type=Path, metavar="NEW.h5", help="also copy the committed frame sets into a clean, closed take")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def _size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def summarize(path: Path) -> dict:
    """The summary of a take; :class:`~stage.store.TakeError` (one line) when it is damaged."""
    from stage.store import TakeError

    try:
        return _summarize(path)
    except (KeyError, IndexError, TypeError, AttributeError, OSError, RuntimeError) as exc:
        if isinstance(exc, FileNotFoundError):
            raise
        raise TakeError(f"{path}: damaged take, cannot summarize it ({type(exc).__name__}: {exc})") from None


def _summarize(path: Path) -> dict:
    from stage.store import TakeReader

    with TakeReader(path) as r:
        md = r.metadata
        cams = {}
        for c in r.cameras:
            info = r.camera_info(c)
            ts = r.timestamps(c)
            cams[c] = {
                "frames": r.n_frames(c),
                "size": [int(info["width"]), int(info["height"])],
                "storage": info["storage"],
                "depth": bool(info["has_depth"]),
                "invalid": int((ts["valid"] == 0).sum()),
                "masks": r.has_array(f"cameras/{c}", "masks"),
            }
        return {
            "path": str(path),
            "state": "complete" if r.complete else "open (being written, or the writer was killed)",
            "software_version": md.get("software_version"),
            "created_utc": md.get("created_utc"),
            "sets": len(r),
            "fps_nominal": r.fps,
            "fps_measured": r.measured_fps(),
            "duration_s": r.duration_s,
            "compression": r.compression,
            "checksums": r.checksums,
            "calibration": r.has_calibration,
            "rig": (r.rig or {}).get("name"),
            "cameras": cams,
            "sync": r.sync_stats,
            "size_on_disk": r.size_on_disk,
            "derived": {"path": str(r.derived_path), "size": r.derived_path.stat().st_size} if r.derived_path.is_file() else None,
        }


def run(args: argparse.Namespace) -> int:
    from stage.sync import relock_warnings

    s = summarize(args.take)
    if args.json:
        import json

        print(json.dumps(s, indent=1))
    else:
        fps = f"{s['fps_measured']:.2f}" if s["fps_measured"] else "-"
        nominal = f" (nominal {s['fps_nominal']:g})" if s["fps_nominal"] else ""
        print(f"{s['path']}: {s['state']}")
        print(f"  rig {s['rig']!r}, written by capture-stage {s['software_version']} at {s['created_utc']}")
        print(f"  {s['sets']} frame sets, {fps} sets/s{nominal}, {s['duration_s']:.2f} s")
        print(f"  compression {s['compression']}, calibration {'present' if s['calibration'] else 'absent'}, "
              f"size on disk {_size(s['size_on_disk'])}")
        print("  checksums: every chunk (`stage verify` reads them all)" if s["checksums"] else
              "  checksums: none (written before checksums were added: damage inside frames cannot be detected)")
        masks = [c for c, v in s["cameras"].items() if v["masks"]]
        print(f"  masks: {', '.join(masks) if masks else 'none'}")
        if s["derived"]:
            print(f"  derived data (masks...): {s['derived']['path']}, {_size(s['derived']['size'])}")
        sync = s["sync"] or {}
        if sync:
            print(f"  sync: {sync.get('sets_complete', 0)} complete / {sync.get('sets_incomplete', 0)} incomplete sets, "
                  f"spread median {sync.get('spread_median_ms', 0):.2f} ms, max {sync.get('spread_max_ms', 0):.2f} ms")
        else:
            print("  sync: no statistics recorded yet")
        for c, v in s["cameras"].items():
            cs = (sync.get("cameras") or {}).get(c, {})
            drops = f", missing in {cs.get('missing', 0)} sets, device gaps {cs.get('sequence_gaps', 0)}" if cs else ""
            inv = f", {v['invalid']} invalid" if v["invalid"] else ""
            print(f"  {c}: {v['size'][0]}x{v['size'][1]} {v['storage']}{' +depth' if v['depth'] else ''}, "
                  f"{v['frames']} frames{inv}{drops}")
        for line in relock_warnings(sync):
            print(f"  warning: {line}")
    if args.recover is not None:
        from stage.store import recover_take

        n = recover_take(args.take, args.recover)
        print(f"recovered {n} frame sets into {args.recover}")
    return 0
