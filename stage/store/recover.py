"""Copy the committed part of a take (e.g. one whose writer was killed) into a clean, closed take."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import h5py
import numpy as np

from calib.fileio import replace_durably
from stage.store._format import RESERVED
from stage.store.derived import derived_path
from stage.store.reader import TakeReader
from stage.store.space import check_free_space, raise_disk_full

__all__ = ["recover_take"]


def recover_take(src: str | os.PathLike, dst: str | os.PathLike, *, overwrite: bool = False) -> int:
    """Copy the committed part of a take (e.g. one whose writer was killed) into a clean, closed take.

    Returns the number of frame sets copied. The derived file of ``src`` (masks...) is copied
    beside ``dst``. Nothing is left at ``dst`` when the copy fails (e.g. a full disk).
    """
    src, dst = Path(src), Path(dst)
    if dst.exists() and not overwrite:
        raise FileExistsError(f"{dst}: exists (use overwrite)")
    if dst.resolve() == src.resolve():
        raise ValueError("dst must differ from src")
    if not dst.parent.is_dir():
        raise FileNotFoundError(f"{dst.parent}: output directory does not exist")
    tmp = dst.with_name(dst.name + ".part")
    try:
        with raise_disk_full(dst, "the recovered take", src.stat().st_size):
            check_free_space(dst, src.stat().st_size, "the recovered take")
            n_sets = _copy_committed(src, tmp)
            replace_durably(tmp, dst)
            if derived_path(src).exists():
                shutil.copyfile(derived_path(src), derived_path(dst))
    finally:
        if tmp.exists():
            tmp.unlink()
    return n_sets


def _copy_committed(src: Path, dst: Path) -> int:
    with TakeReader(src) as r:
        counts = r.frame_counts()
        n_sets = r.n_sets
        fin = r._f
        jpeg_end = {}
        for c in r.cameras:
            g = fin["cameras"][c]
            n = counts[c]
            jpeg_end[c] = int(g["jpeg_offset"][n - 1] + g["jpeg_length"][n - 1]) if ("jpeg" in g and n) else 0
        with h5py.File(dst, "w", libver="latest") as out:
            for k, v in fin.attrs.items():
                out.attrs[k] = v
            for name in ("meta", "sets", "cameras"):
                fin.copy(fin[name], out, name)
            out["sets/frames"].resize(n_sets, axis=0)
            out["sets/time_ns"].resize(n_sets, axis=0)
            out["sets/commit"][...] = np.array([n_sets, 1] + [counts[c] for c in r.cameras], dtype=np.int64)
            for c in r.cameras:
                g = out["cameras"][c]
                for name in g:
                    if name == "jpeg":
                        g[name].resize(jpeg_end[c], axis=0)
                    elif name in RESERVED:
                        g[name].resize(counts[c], axis=0)
    return n_sets
