"""The take is written once: masks, plates and attached calibrations go to TAKE.derived.h5 beside it."""

from __future__ import annotations

import hashlib
import logging
import threading
from pathlib import Path

import h5py
import numpy as np
import pytest

from stage.store import (
    CameraSpec,
    TakeError,
    TakeReader,
    TakeWriter,
    attach_calibration,
    derived_path,
    write_array,
    write_masks,
)
from stage.store import derived as derived_mod
from tests.stage.frames import H, W, calibration, make_frame


def sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def make_take(path: Path, n: int = 4, cams=("a", "b")) -> Path:
    with TakeWriter(path, [CameraSpec(c, W, H) for c in cams], fps=30, calibration=calibration(cams)) as w:
        for k in range(n):
            w.write_set({c: make_frame(c, i, k) for i, c in enumerate(cams)})
    return path


def masks_of(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).random((n, H, W)) > 0.5


def test_derived_data_never_touches_the_take(tmp_path):
    take = make_take(tmp_path / "t.h5")
    before = sha(take)
    m = masks_of(4, 1)
    write_masks(take, "a", m, {"mode": "chroma"})
    write_array(take, "cameras/b", "plate", np.full((H, W, 3), 7, np.uint8))
    cal = calibration(["a", "b"])
    attach_calibration(take, cal)
    assert sha(take) == before
    assert derived_path(take) == tmp_path / "t.derived.h5" and derived_path(take).is_file()
    assert not list(tmp_path.glob(".*tmp"))  # no temporary file left
    with TakeReader(take) as r:
        np.testing.assert_array_equal(r.masks("a"), m)
        np.testing.assert_array_equal(r.mask("a", 2), m[2])
        assert r.masks("b") is None and r.masks_present() == ["a"]
        assert r.mask_params("a") == {"mode": "chroma"}
        assert r.read_array("cameras/b", "plate")[0][0, 0, 0] == 7 and r.has_array("cameras/b", "plate")
        assert r.has_calibration and r.calibration == cal
    # re-keying replaces the masks; the other arrays are kept
    m2 = masks_of(4, 2)
    write_masks(take, "a", m2)
    with TakeReader(take) as r:
        np.testing.assert_array_equal(r.masks("a"), m2)
        assert r.has_array("cameras/b", "plate")
    assert sha(take) == before


def test_old_layout_masks_inside_the_take_still_read(tmp_path):
    take = make_take(tmp_path / "old.h5")
    legacy = masks_of(4, 3)
    with h5py.File(take, "r+") as f:  # what older versions of the store wrote
        ds = f["cameras/a"].create_dataset("masks", data=legacy.astype(np.uint8))
        ds.attrs["params"] = '{"mode": "luma"}'
    with TakeReader(take) as r:
        np.testing.assert_array_equal(r.masks("a"), legacy)
        assert r.mask_params("a") == {"mode": "luma"} and r.masks_present() == ["a"]
    # keying again puts the new masks in the derived file; they win over the old ones
    new = masks_of(4, 4)
    write_masks(take, "a", new)
    with TakeReader(take) as r:
        np.testing.assert_array_equal(r.masks("a"), new)


def test_concurrent_writers_and_readers(tmp_path):
    cams = tuple(f"c{i}" for i in range(4))
    take = make_take(tmp_path / "t.h5", cams=cams)
    reader = TakeReader(take)  # open during every update: never blocks them, sees each new file
    assert reader.masks_present() == []
    errors = []

    def key(i: int, c: str) -> None:
        try:
            write_masks(take, c, masks_of(4, i))
        except Exception as exc:  # pragma: no cover - the assertion below reports it
            errors.append(exc)

    threads = [threading.Thread(target=key, args=(i, c)) for i, c in enumerate(cams)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert reader.masks_present() == list(cams)
    for i, c in enumerate(cams):
        np.testing.assert_array_equal(reader.masks(c), masks_of(4, i))
    reader.close()


def test_crash_mid_update_keeps_the_old_derived_file(tmp_path, monkeypatch):
    take = make_take(tmp_path / "t.h5")
    m = masks_of(4, 5)
    write_masks(take, "a", m)
    before = sha(derived_path(take))
    real = h5py.Group.create_dataset

    def boom(self, *a, **kw):
        raise RuntimeError("simulated crash while writing")

    monkeypatch.setattr(h5py.Group, "create_dataset", boom)
    with pytest.raises(RuntimeError, match="simulated"):
        write_masks(take, "b", masks_of(4, 6))
    monkeypatch.setattr(h5py.Group, "create_dataset", real)
    assert sha(derived_path(take)) == before and not list(tmp_path.glob(".*tmp"))
    with TakeReader(take) as r:
        np.testing.assert_array_equal(r.masks("a"), m)
        assert r.masks("b") is None


def test_stale_or_linked_derived_file_is_ignored(tmp_path, caplog):
    take = make_take(tmp_path / "t.h5")
    write_masks(take, "a", masks_of(4, 7))
    # a new take of the same name: the old derived file is removed with it
    make_take_overwrite = TakeWriter(take, [CameraSpec("a", W, H), CameraSpec("b", W, H)], overwrite=True)
    make_take_overwrite.close()
    assert not derived_path(take).exists()
    # a derived file of another take (copied in by hand) is not used
    other = make_take(tmp_path / "other.h5")
    write_masks(other, "a", masks_of(4, 8))
    derived_path(take).write_bytes(derived_path(other).read_bytes())
    with caplog.at_level(logging.WARNING, logger="stage.store"), TakeReader(take) as r:
        assert r.masks("a") is None
    assert "older take" in caplog.text
    # a derived file linked from another directory is never read
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    t2 = make_take(outside / "t2.h5")
    write_masks(t2, "a", masks_of(4, 9))
    inner = tmp_path / "inner"
    inner.mkdir()
    (inner / "t2.h5").write_bytes((outside / "t2.h5").read_bytes())  # the same take, so the same identity
    (inner / "t2.derived.h5").symlink_to(derived_path(t2))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="stage.store"), TakeReader(inner / "t2.h5") as r:
        assert r.masks("a") is None
    assert "links outside" in caplog.text


def test_invalid_input(tmp_path):
    take = make_take(tmp_path / "t.h5")
    with pytest.raises(ValueError, match="group_path 'meta'"):
        write_array(take, "meta", "rig", np.zeros(3))
    with pytest.raises(ValueError, match="reserved"):
        write_array(take, "cameras/a", "image", np.zeros(3))
    with pytest.raises(ValueError, match="shape"):
        write_masks(take, "a", masks_of(3, 0))
    write_array(take, "cameras/a", "x", np.zeros(3))
    with pytest.raises(ValueError, match="overwrite=False"):
        write_array(take, "cameras/a", "x", np.zeros(3), overwrite=False)
    # a take whose writer never closed it gets no derived data (recover it first)
    w = TakeWriter(tmp_path / "open.h5", [CameraSpec("a", W, H)])
    w.write_set({"a": make_frame("a", 0, 0)})
    w._f.flush()
    try:
        with pytest.raises(TakeError, match="not closed cleanly"):
            write_masks(tmp_path / "open.h5", "a", masks_of(1, 0))
    finally:
        w.close()
    assert derived_mod.DERIVED_SUFFIX == ".derived.h5" and derived_path("x/y.h5") == Path("x/y.derived.h5")
    with pytest.raises(ValueError, match="arrays"):
        TakeWriter(tmp_path / "a.h5", [CameraSpec("a", W, H)], arrays={"plate": np.zeros(3)})
    with pytest.raises(ValueError, match="arrays"):
        TakeWriter(tmp_path / "a.h5", [CameraSpec("a", W, H)], arrays={"cameras/zz/plate": np.zeros(3)})
    with pytest.raises(ValueError, match="expected_sets"):
        TakeWriter(tmp_path / "a.h5", [CameraSpec("a", W, H)], expected_sets=-1)
    assert not (tmp_path / "a.h5").exists()


def test_arrays_shot_with_the_capture_live_in_the_take(tmp_path):
    plate = np.full((H, W, 3), 9, np.uint8)
    with TakeWriter(tmp_path / "p.h5", [CameraSpec("a", W, H)], arrays={"cameras/a/plate": plate}) as w:
        w.write_set({"a": make_frame("a", 0, 0)})
    assert not derived_path(tmp_path / "p.h5").exists()
    with TakeReader(tmp_path / "p.h5") as r:
        np.testing.assert_array_equal(r.read_array("cameras/a", "plate")[0], plate)
