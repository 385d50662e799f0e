"""Names, errors and small functions every part of the take store shares."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from calib.fileio import json_default

try:  # registers the Blosc/LZ4 filters with HDF5 (optional extra ``capture-stage[fast]``)
    import hdf5plugin
except ImportError:  # pragma: no cover - depends on the environment
    hdf5plugin = None

__all__ = ["FORMAT", "DERIVED_FORMAT", "COMPRESSIONS", "RESERVED", "TakeError", "CameraSpec", "have_lz4", "filter_kwargs", "to_json"]

FORMAT = "capture-stage/take@1"
DERIVED_FORMAT = "capture-stage/derived@1"
COMPRESSIONS = ("none", "lz4", "gzip")
# per-frame datasets of a capture; no derived array may take these names
RESERVED = frozenset(
    {"image", "jpeg", "jpeg_offset", "jpeg_length", "depth", "timestamp_ns", "host_timestamp_ns", "sequence", "valid", "set_index"}
)


class TakeError(ValueError):
    """A take file that cannot be read or written; the message names the file and the problem."""


def have_lz4() -> bool:
    """True when the Blosc/LZ4 filter (``hdf5plugin``) is available."""
    return hdf5plugin is not None


def filter_kwargs(compression: str) -> dict:
    """``create_dataset`` keywords of a compression name."""
    if compression == "none":
        return {}
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 1}
    if compression == "lz4":
        if hdf5plugin is None:
            raise ValueError(
                "compression='lz4' needs the optional package hdf5plugin (pip install 'capture-stage[fast]' "
                "or pip install hdf5plugin); use compression='none' instead"
            )
        # Blosc/LZ4 with bit shuffle: the only filter here that keeps up with
        # several 640x480 cameras at 30 fps and still compresses noisy frames.
        return dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.BITSHUFFLE))
    raise ValueError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")


def derived_filter_kwargs() -> dict:
    """Compression of derived arrays: LZ4 when available, else gzip level 1."""
    return filter_kwargs("lz4") if hdf5plugin is not None else filter_kwargs("gzip")


@dataclass(frozen=True)
class CameraSpec:
    """What the writer needs to know about one camera before the take starts.

    Parameters
    ----------
    id : str
        Camera id (the HDF5 group name; no ``/``).
    width, height : int
        Frame size in pixels.
    storage : {"raw", "jpeg"}
        Raw BGR frames, or the camera's JPEG bytes as delivered.
    depth : bool
        The camera delivers depth images (uint16 mm, same size).
    """

    id: str
    width: int
    height: int
    storage: Literal["raw", "jpeg"] = "raw"
    depth: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not self.id or "/" in self.id or self.id in (".", ".."):
            raise ValueError(f"camera id must be a non-empty string without '/', got {self.id!r}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera {self.id}: width and height must be positive, got {self.width}x{self.height}")
        if self.storage not in ("raw", "jpeg"):
            raise ValueError(f"camera {self.id}: storage must be 'raw' or 'jpeg', got {self.storage!r}")

    def frame_bytes(self) -> int:
        """Bytes of one uncompressed frame (image and depth)."""
        n = int(self.width) * int(self.height)
        return 3 * n + (2 * n if self.depth else 0)


def to_json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=json_default)


def attr_value(v: Any) -> Any:
    """An HDF5 attribute as a plain Python value."""
    return v.item() if isinstance(v, np.generic) else v
