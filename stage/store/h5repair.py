"""Opening take files, and the one repair HDF5's own tools do not offer from Python.

A process killed while it had a take open for writing outside SWMR mode (older versions of
this project wrote masks into the take) leaves the superblock flag "open for write, not SWMR",
which no reader may open. :func:`open_h5` clears that flag when no process holds the file, as
``h5clear -s`` does. ``h5clear`` is a command-line tool of the HDF5 distribution that h5py does
not ship, so the superblock patch (and lookup3, HDF5's metadata checksum) is written out here.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import h5py

from stage.store._format import TakeError

__all__ = ["open_h5", "lookup3", "close_all"]

log = logging.getLogger("stage.store")

_M32 = 0xFFFFFFFF


def _rot32(x: int, k: int) -> int:
    return ((x << k) | (x >> (32 - k))) & _M32


_MIX = ((0, 2, 1, 4), (1, 0, 2, 6), (2, 1, 0, 8), (0, 2, 1, 16), (1, 0, 2, 19), (2, 1, 0, 4))


def _lookup3(data: bytes) -> int:
    """Bob Jenkins' lookup3 ``hashlittle`` with seed 0: HDF5's metadata checksum."""
    n = len(data)
    a = b = c = (0xDEADBEEF + n) & _M32
    i = 0
    while n - i > 12:
        v = [
            (a + int.from_bytes(data[i : i + 4], "little")) & _M32,
            (b + int.from_bytes(data[i + 4 : i + 8], "little")) & _M32,
            (c + int.from_bytes(data[i + 8 : i + 12], "little")) & _M32,
        ]
        for x, y, z, k in _MIX:  # x -= y; x ^= rot(y, k); y += z
            v[x] = ((v[x] - v[y]) & _M32) ^ _rot32(v[y], k)
            v[y] = (v[y] + v[z]) & _M32
        a, b, c = v
        i += 12
    rest = data[i:]
    if not rest:
        return c
    rest = rest + bytes(12 - len(rest))
    a = (a + int.from_bytes(rest[0:4], "little")) & _M32
    b = (b + int.from_bytes(rest[4:8], "little")) & _M32
    c = (c + int.from_bytes(rest[8:12], "little")) & _M32
    for x, y, k in ((2, 1, 14), (0, 2, 11), (1, 0, 25), (2, 1, 16), (0, 2, 4), (1, 0, 14), (2, 1, 24)):
        v = [a, b, c]
        v[x] ^= v[y]
        v[x] = (v[x] - _rot32(v[y], k)) & _M32
        a, b, c = v
    return c


_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _clear_killed_writer_flags(path: Path) -> bool:
    """Clear the "open for writing" flag a killed non-SWMR writer left in the superblock.

    What ``h5clear -s`` does, for the one case where no reader can open the file: the flag
    says "open for write" but not "SWMR" (e.g. a process writing masks was killed), so
    neither a plain nor a SWMR reader is allowed in. Only done when no process has the file
    open (an exclusive lock is free: HDF5 locks the files it opens, and the kernel drops the
    lock of a killed process). Superblocks of version 2 and 3 only (what h5py writes).

    Returns
    -------
    bool
        True when the flag was cleared.
    """
    import fcntl

    with open(path, "r+b") as fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return False  # a live process has it open
        try:
            for base in (0, 512, 1024, 2048, 4096, 8192):
                fh.seek(base)
                head = fh.read(12)
                if head[:8] == _SIGNATURE:
                    break
            else:
                return False
            version, size_offsets, flags = head[8], head[9], head[11]
            if version not in (2, 3) or not flags & 0x01 or flags & 0x04:
                return False
            n = 12 + 4 * size_offsets
            fh.seek(base)
            block = bytearray(fh.read(n + 4))
            if _lookup3(bytes(block[:n])) != int.from_bytes(block[n:], "little"):
                return False  # not a superblock we understand: leave it alone
            block[11] = 0
            block[n:] = _lookup3(bytes(block[:n])).to_bytes(4, "little")
            fh.seek(base)
            fh.write(block)
            fh.flush()
            os.fsync(fh.fileno())
            return True
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def open_h5(path: Path, mode: str = "r") -> h5py.File:
    if not path.exists():
        raise FileNotFoundError(f"{path}: take not found")
    if not path.is_file():
        raise TakeError(f"{path}: not a file")
    try:
        try:
            return _open_once(path, mode)
        except OSError as exc:
            msg = str(exc).lower()
            stuck = "not already open for swmr writing" in msg or (mode != "r" and "already open for write" in msg)
            if not (stuck and _clear_killed_writer_flags(path)):
                raise
            log.warning("%s: its last writer was killed while the take was open for writing; cleared the "
                        "file's open-for-write flag (like `h5clear -s`) and opened it again", path)
            return _open_once(path, mode)
    except OSError as exc:
        msg = str(exc)
        if "truncated" in msg.lower():
            raise TakeError(f"{path}: truncated take file (it ends before its own end-of-data address): {msg}") from None
        if "signature" in msg.lower() or "not an hdf5" in msg.lower():
            raise TakeError(f"{path}: not an HDF5 file (corrupt, or not a take)") from None
        if "already open for write" in msg.lower():
            raise TakeError(
                f"{path}: the take was not closed cleanly (its writer was killed, or is still writing); "
                f"it can be read but not modified: make a clean copy with `stage info --recover NEW.h5 {path}`"
            ) from None
        if "already open for read-only" in msg.lower():
            raise TakeError(f"{path}: cannot modify the take while this process has it open for reading "
                            "(close the TakeReader first)") from None
        raise TakeError(f"{path}: cannot open take: {msg}") from None


def _open_once(path: Path, mode: str) -> h5py.File:
    if mode == "r":
        try:
            return h5py.File(path, "r")  # a closed take: HDF5 checks its end-of-file address
        except OSError as exc:
            if "already open for write" not in str(exc).lower():
                raise
        # being written, or its writer was killed: only a SWMR reader may open it
        return h5py.File(path, "r", libver="latest", swmr=True)
    return h5py.File(path, mode)


lookup3 = _lookup3


def close_all(f: h5py.File) -> None:
    """Close an HDF5 file and every object of it still open, whatever state a failed write left.

    After a failed write (a full disk) HDF5 still holds dirty data for the file's datasets;
    h5py would try to write it again whenever a forgotten dataset object is garbage collected,
    which crashes the interpreter. Closing every identifier of the file at once avoids that.
    """
    try:
        ids = f.id.get_obj_ids(h5py.h5f.OBJ_DATASET | h5py.h5f.OBJ_GROUP | h5py.h5f.OBJ_ATTR | h5py.h5f.OBJ_DATATYPE)
    except Exception:
        ids = []
    for oid in ids:
        try:
            while oid.valid:
                oid._close()
        except Exception:
            pass
    try:
        f.close()
    except Exception as exc:
        log.debug("closing %s: %s", getattr(f, "filename", "?"), exc)
