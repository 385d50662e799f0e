"""`stage spines --meshes` and `stage process --meshes`: one implementation, same spine."""

import json

from stage.cli import main
from tests.conftest import shared_dataset


def test_spines_and_process_meshes_agree(tmp_path, capsys):
    cat = shared_dataset("cat_poses")
    pattern = str(cat / "000[1-4].obj")
    assert main(["spines", "--meshes", pattern, "--out", str(tmp_path / "a"), "--workers", "0", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "K = 6 limbs" in out
    # the cat is scaled to a unit box: taken as millimetres, and said (one line; both commands)
    assert "warning: the meshes span 1.798 units, taken as millimetres (no --units)" in out
    assert main(["process", "--meshes", pattern, "--out", str(tmp_path / "b"), "--workers", "0", "--no-progress"]) == 0
    assert "warning: the meshes span 1.798 units" in capsys.readouterr().out
    a = json.loads((tmp_path / "a" / "spine.json").read_text())
    b = json.loads((tmp_path / "b" / "spine.json").read_text())
    assert a["graph"] == b["graph"] and a["frames"] == b["frames"]
    # options only `stage spines` exposes reach the skeletons
    assert main(["spines", "--meshes", pattern, "--out", str(tmp_path / "c"), "--workers", "0", "--no-progress",
                 "--bins", "40"]) == 0
    assert json.loads((tmp_path / "c" / "spine.json").read_text())["frames"] != a["frames"]


def test_invalid_input(tmp_path, capsys):
    assert main(["spines", "--meshes", str(tmp_path / "none*.obj"), "--out", str(tmp_path / "o")]) == 2
    assert "mesh" in capsys.readouterr().err.lower()


def test_quiet_silences_progress_bars(tmp_path, capsys):
    """`stage -q` draws no progress bar (tqdm writes them to stderr), not even with --progress;
    stderr here is no terminal, so bars are drawn only with --progress."""
    cat = shared_dataset("cat_poses")
    pattern = str(cat / "000[1-3].obj")
    assert main(["spines", "--meshes", pattern, "--out", str(tmp_path / "a"), "--workers", "0", "--progress"]) == 0
    assert "%|" in capsys.readouterr().err
    assert main(["spines", "--meshes", pattern, "--out", str(tmp_path / "c"), "--workers", "0"]) == 0
    assert "%|" not in capsys.readouterr().err  # a file or a pipe: no bars
    assert main(["-q", "spines", "--meshes", pattern, "--out", str(tmp_path / "b"), "--workers", "0",
                 "--progress"]) == 0
    assert "%|" not in capsys.readouterr().err


def test_quiet_silences_libraries_that_set_their_own_log_levels():
    """`stage -q` in a fresh process: a library logger set to INFO (as Dask's distributed sets its
    own) prints nothing below WARNING; without -q its INFO lines are printed."""
    import subprocess
    import sys

    code = ("import logging; from stage.cli import _setup_logging; _setup_logging(0, {quiet}); "
            "lib = logging.getLogger('distributed.scheduler'); lib.setLevel(logging.INFO); "
            "lib.info('state start'); lib.warning('worker lost')")
    quiet = subprocess.run([sys.executable, "-c", code.format(quiet=True)], capture_output=True, text=True, check=True)
    assert quiet.stderr == "WARNING distributed.scheduler: worker lost\n"
    loud = subprocess.run([sys.executable, "-c", code.format(quiet=False)], capture_output=True, text=True, check=True)
    assert "INFO distributed.scheduler: state start" in loud.stderr
