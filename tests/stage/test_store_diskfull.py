"""A full disk is an error, never a crash or a loss: capture, import, derived data and `stage process`.

The disk is a small tmpfs when the tests run as root (CI does); elsewhere HDF5's writes are
made to fail with ENOSPC by a mock at every flush, and the process sweep runs against a mocked
disk (a byte budget shared by every file written from Python) only.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest

from stage.store import CameraSpec, DiskFullError, TakeReader, TakeWriter, derived_path, space, write_masks
from tests.stage.frames import H, W, calibration, make_frame

ROOT = Path(__file__).resolve().parents[2]
#: free bytes left for `stage process` in the sweep (16 KiB .. 8 MiB): with the up-front estimate
#: (refused below about 1.2 MiB for this take, then enough), and without it, so that the disk fills up
#: mid-run (for this take: in the keying's derived-data write at 16-32 KiB, in the results at 64-384 KiB)
BUDGETS = (16 << 10, 256 << 10, 2 << 20, 8 << 20)
BUDGETS_MID_RUN = (16 << 10, 64 << 10, 320 << 10, 1 << 20)
#: the mocked disk counts only bytes written from Python (the derived file, the results)
BUDGETS_MOCKED = (16 << 10, 128 << 10, 8 << 20)


@contextlib.contextmanager
def small_fs(nbytes: int):
    """A fresh tmpfs of ``nbytes``; None when this machine cannot mount one (not root, no mount)."""
    d = Path(tempfile.mkdtemp(prefix="stage-fullfs-"))
    ok = os.geteuid() == 0 and shutil.which("mount") is not None and subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={nbytes}", "tmpfs", str(d)], capture_output=True
    ).returncode == 0
    try:
        yield d if ok else None
    finally:
        if ok:
            subprocess.run(["umount", "-l", str(d)], capture_output=True)
        shutil.rmtree(d, ignore_errors=True)


def fill(directory: Path, leave: int) -> None:
    """Write a ballast file so that only about ``leave`` bytes stay free."""
    free = space.free_bytes(directory)
    with open(directory / "ballast", "wb") as f:
        f.truncate(0)
        if free > leave:
            os.posix_fallocate(f.fileno(), 0, free - leave)


def sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@contextlib.contextmanager
def enospc_after(n_flushes: int):
    """Mock: every HDF5 flush after the first ``n_flushes`` fails as a full disk does."""
    real = h5py.File.flush
    calls = [0]

    def flush(self):
        calls[0] += 1
        if calls[0] > n_flushes:
            raise RuntimeError("Unable to synchronously flush file (file write failed: errno = 28, "
                               "error message = 'No space left on device')")
        return real(self)

    h5py.File.flush = flush
    try:
        yield
    finally:
        h5py.File.flush = real


def write_until_full(path: Path, max_sets: int = 200) -> tuple[int, DiskFullError | None]:
    cams = ("a", "b")
    w = TakeWriter(path, [CameraSpec(c, W, H) for c in cams], fps=30)
    k = 0
    try:
        for k in range(max_sets):
            w.write_set({c: make_frame(c, i, k) for i, c in enumerate(cams)})
    except DiskFullError as exc:
        return k, exc
    finally:
        w.close()
    return max_sets, None


def test_capture_on_a_full_disk_keeps_every_committed_set(tmp_path):
    with small_fs(3 << 20) as fs:
        if fs is not None:
            stored, err = write_until_full(fs / "t.h5")
            take = fs / "t.h5"
        else:  # mocked ENOSPC: creation takes 1 flush, each set 2
            with enospc_after(1 + 2 * 5):
                stored, err = write_until_full(tmp_path / "t.h5")
            take = tmp_path / "t.h5"
            assert stored == 5
        assert err is not None and "disk full" in str(err) and f"keeps the {stored} frame sets" in str(err)
        assert "closed cleanly" in str(err)
        with TakeReader(take) as r:
            assert r.complete and r.n_sets == stored >= 1
            np.testing.assert_array_equal(r.frame("b", stored - 1), make_frame("b", 1, stored - 1).image)
        assert sorted(p.name for p in take.parent.iterdir() if p.name != "ballast") == ["t.h5"]  # no reserve left


def test_stage_capture_on_a_full_disk_exits_cleanly(tmp_path):
    from fake_cameras.rigs import write_simulated_rig

    rig = tmp_path / "rig.toml"
    write_simulated_rig(rig, 4, frames=60, fps=30, size=(320, 240))
    with small_fs(20 << 20) as fs:
        if fs is None:
            pytest.skip("needs a small filesystem (tmpfs as root) to fill up")
        fill(fs, 13 << 20)  # passes the estimate (lz4 counted at 2:1), fills up mid-take (noise packs ~1.5:1)
        r = subprocess.run(
            [sys.executable, "-m", "stage", "capture", "--rig", str(rig), "--out", str(fs / "c.h5"), "--frames", "20",
             "--compression", "lz4", "--no-progress"],
            capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120,
        )
        assert r.returncode == 2, r.stderr[-2000:]
        assert "Traceback" not in r.stderr and "disk full" in r.stderr and "closed cleanly" in r.stderr, r.stderr
        kept = int(r.stderr.split("keeps the ")[1].split()[0])
        with TakeReader(fs / "c.h5") as rd:
            assert rd.complete and rd.n_sets == kept >= 1


def test_free_space_checked_up_front(tmp_path, monkeypatch):
    monkeypatch.setattr(space, "free_bytes", lambda p: 10 << 20)
    with pytest.raises(DiskFullError, match=r"a take of 1000 frame sets: about .* MiB needed, 10.0 MiB free"):
        TakeWriter(tmp_path / "t.h5", [CameraSpec("a", 640, 480)], expected_sets=1000)
    assert not (tmp_path / "t.h5").exists()
    TakeWriter(tmp_path / "t.h5", [CameraSpec("a", 64, 48)], expected_sets=10).close()


def test_import_on_a_full_disk_leaves_nothing(tmp_path):
    from tests.stage.footage import CAMS, img, write_anipose_toml

    src = tmp_path / "footage"
    for i, (name, *_rest) in enumerate(CAMS):
        (src / name).mkdir(parents=True)
        for k in range(30):
            noisy = img(i, k % 10) ^ np.random.default_rng(k).integers(0, 255, (H, W, 3), dtype=np.uint8)
            import cv2

            cv2.imwrite(str(src / name / f"f{k:03d}.png"), noisy)
    toml = tmp_path / "calib.toml"
    write_anipose_toml(toml)
    from stage.cli import main

    with small_fs(2 << 20) as fs:
        if fs is None:
            pytest.skip("needs a small filesystem (tmpfs as root) to fill up")
        out = fs / "imp.h5"
        assert main(["-q", "import", "--images", str(src), "--calibration", str(toml), "--out", str(out), "--storage", "raw"]) == 2
        assert list(fs.iterdir()) == []  # no .part, no reserve


def test_keying_on_a_full_disk_leaves_take_and_derived_data_unchanged(tmp_path, monkeypatch):
    with small_fs(4 << 20) as fs:
        root = fs if fs is not None else tmp_path
        take = root / "t.h5"
        with TakeWriter(take, [CameraSpec("a", W, H), CameraSpec("b", W, H)], calibration=calibration("ab")) as w:
            for k in range(20):
                w.write_set({c: make_frame(c, i, k) for i, c in enumerate("ab")})
        write_masks(take, "a", np.zeros((20, H, W), bool))
        before = (sha(take), sha(derived_path(take)))
        noisy = np.random.default_rng(0).random((20, H, W)) > 0.5  # does not compress
        if fs is not None:
            fill(fs, 32 << 10)
            with pytest.raises(DiskFullError, match="not enough free space for cameras/b/masks .* needed"):
                write_masks(take, "b", noisy)  # the estimate says no before anything is written
            ctx = contextlib.nullcontext()
        else:
            ctx = enospc_after(0)
        from stage.store import derived

        monkeypatch.setattr(derived, "check_free_space", lambda *a, **k: None)  # met mid-write instead
        with ctx, pytest.raises(DiskFullError, match="disk full while writing cameras/b/masks .*unchanged"):
            write_masks(take, "b", noisy)
        assert (sha(take), sha(derived_path(take))) == before
        assert not [p for p in root.iterdir() if p.name.endswith(".tmp")]
        with TakeReader(take) as r:
            assert r.masks_present() == ["a"]


# -- the sweep: `stage process` with 16 KiB .. 8 MiB free ---------------------------------------------

_RUN = """
import sys
mode, budget = sys.argv[1].split(":")
if mode in ("unchecked", "mocked"):  # no up-front estimate: the full disk is met mid-run
    import pipeline.process.driver, stage.store.derived
    pipeline.process.driver.check_free_space = stage.store.derived.check_free_space = lambda *a, **k: None
if mode == "mocked":  # no small filesystem: every file written from Python shares a byte budget
    import builtins, errno, io
    real_open, used = io.open, [0]

    class Budgeted:
        def __init__(self, f):
            self._f = f
        def write(self, b):
            if used[0] + len(b) > int(budget):
                raise OSError(errno.ENOSPC, "No space left on device")
            used[0] += len(b)
            return self._f.write(b)
        def __getattr__(self, name):
            return getattr(self._f, name)
        def __enter__(self):
            return self
        def __exit__(self, *exc):
            return self._f.__exit__(*exc)

    def budgeted_open(file, mode="r", *a, **k):
        f = real_open(file, mode, *a, **k)
        return Budgeted(f) if any(c in mode for c in "wax+") else f

    builtins.open = io.open = budgeted_open
from stage.cli import main
raise SystemExit(main(sys.argv[2:]))
"""


def process_sweep(take_dir: Path, fs: Path, budgets=BUDGETS, *, mode: str) -> list[dict]:
    """Run `stage process` on a fresh copy of the take for every budget of free bytes; what happened.

    ``mode``: "checked" (as users run it), "unchecked" (no up-front estimate, so the disk fills up
    mid-run) on a small filesystem ``fs``; "mocked" (a byte budget for every file written from
    Python, ENOSPC past it) in any directory.
    """
    results = []
    for budget in budgets:
        for p in fs.iterdir():
            shutil.rmtree(p) if p.is_dir() else p.unlink()
        for p in take_dir.iterdir():
            shutil.copy(p, fs / p.name)
        before = sha(fs / "t.h5")
        if mode != "mocked":
            fill(fs, budget)
        r = subprocess.run(
            [sys.executable, "-c", _RUN, f"{mode}:{budget}", "-q", "process", str(fs / "t.h5"),
             "--out", str(fs / "out"), "--resolution", "32", "--no-progress"],
            capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120,
        )
        (fs / "ballast").unlink(missing_ok=True)
        with TakeReader(fs / "t.h5") as rd:
            masks = rd.masks_present()
        results.append({
            "budget": budget, "rc": r.returncode, "stderr": r.stderr.strip(), "take_same": sha(fs / "t.h5") == before,
            "out_left": (fs / "out").exists(), "masks": masks,
            "spine": (fs / "out" / "spine.json").is_file(),
            "stray": sorted(p.name for p in fs.iterdir() if p.name.endswith((".tmp", ".part"))),
        })
    return results


@pytest.fixture(scope="module")
def small_take(tmp_path_factory):
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take

    d = tmp_path_factory.mktemp("sweep-take")
    record_take(simulate_take("starfish", n_cameras=4, frames=3, size=(160, 120), seed=3), d / "t.h5")
    (d / "t.gt.npz").unlink()
    return d


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["checked", "unchecked", "mocked"])
def test_process_sweep_fails_cleanly_or_succeeds(small_take, mode, tmp_path):
    with small_fs(16 << 20) as fs:
        if mode == "mocked":
            res = process_sweep(small_take, tmp_path, BUDGETS_MOCKED, mode=mode)
        elif fs is None:
            pytest.skip("needs a small filesystem that fills up (tmpfs, as root); the mocked sweep runs instead")
        else:
            res = process_sweep(small_take, fs, BUDGETS if mode == "checked" else BUDGETS_MID_RUN, mode=mode)
    for r in res:
        assert r["take_same"], r
        assert r["rc"] in (0, 2), r
        assert r["stray"] == [], r
        if r["rc"] == 0:
            assert r["spine"] and r["masks"] == ["cam00", "cam01", "cam02", "cam03"], r
        else:
            lines = r["stderr"].splitlines()
            assert len(lines) == 1 and "Traceback" not in r["stderr"], r
            assert "disk full" in lines[0] or "not enough free space" in lines[0], r
            assert not r["out_left"], r
    assert res[-1]["rc"] == 0, res[-1]  # 8 MiB (1 MiB without the estimate's margin) is enough
    assert res[0]["rc"] == 2, res[0]
