"""HDF5 take store: one file per take, written once, plus its derived data (``docs/take-format.md``).

The store is the only capture-side package that imports :mod:`h5py`. One module per purpose:

* :mod:`stage.store.writer` -- :class:`TakeWriter`, frame set by frame set in SWMR mode
  (a killed writer loses at most the set in flight; a full disk closes the take cleanly);
* :mod:`stage.store.reader` -- :class:`TakeReader` (also of a take being written or whose
  writer was killed), which presents the derived data as part of the take;
* :mod:`stage.store.derived` -- masks and other arrays computed later, in ``TAKE.derived.h5``
  beside the take, replaced atomically (:func:`write_array`, :func:`write_masks`,
  :func:`attach_calibration`);
* :mod:`stage.store.jpeg` -- the JPEG codec of JPEG-stored cameras;
* :mod:`stage.store.h5repair` -- opening take files, clearing a killed writer's superblock flag;
* :mod:`stage.store.recover` -- :func:`recover_take`, a clean copy of a take's committed sets;
* :mod:`stage.store.space` -- free-space checks and :class:`DiskFullError`.

Meshes and spines do not belong in a take.
"""

from stage.store._format import COMPRESSIONS, DERIVED_FORMAT, FORMAT, CameraSpec, TakeError, have_lz4
from stage.store.derived import attach_calibration, derived_path, write_array, write_arrays, write_masks
from stage.store.reader import TakeReader
from stage.store.recover import recover_take
from stage.store.space import DiskFullError, check_free_space, free_bytes, is_disk_full
from stage.store.writer import TakeWriter, estimate_take_bytes

__all__ = [
    "FORMAT",
    "DERIVED_FORMAT",
    "COMPRESSIONS",
    "TakeError",
    "DiskFullError",
    "CameraSpec",
    "TakeWriter",
    "TakeReader",
    "write_array",
    "write_arrays",
    "write_masks",
    "attach_calibration",
    "derived_path",
    "recover_take",
    "have_lz4",
    "estimate_take_bytes",
    "check_free_space",
    "free_bytes",
    "is_disk_full",
]
