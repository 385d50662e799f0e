"""`stage bench process` runs end to end on a tiny take and prints its table (figures not checked)."""

from stage.cli import main


def test_bench_process_prints_every_step(capsys):
    args = ["bench", "process", "--cameras", "4", "--frames", "3", "--size", "320x240", "--workers", "1", "--no-dask"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "disk-read floor" in out and "own benchmarks" in out
    assert "subject box:" in out and "ms a set" in out and "consistency" in out
    for label in ("in process", "1 worker"):
        for step in ("key", "surface + skeletons", "spine (reduce)", "END TO END"):
            assert any(line.startswith(label) and step in line for line in out.splitlines()), (label, step)


def test_invalid_input(capsys):
    # one clear line and exit code 2 (the CLI turns the ValueError into it)
    assert main(["bench", "process", "--size", "10x10"]) == 2
    assert "--size" in capsys.readouterr().err
    assert main(["bench", "process", "--frames", "1"]) == 2
    assert "--frames" in capsys.readouterr().err
