"""What a person reads: progress bars on a terminal only (or --progress), -q/-v after the command,
a closed pipe ends quietly, `stage key` names the file its masks went to."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from stage.cli import _progress_bars, build_parser, main


def _help_text(capsys, command: str) -> str:
    """``stage COMMAND --help`` as one line (argparse wraps its help to the terminal's width)."""
    import re

    with pytest.raises(SystemExit):
        main([command, "--help"])
    return re.sub(r"\s+", " ", capsys.readouterr().out)


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    import os

    d = tmp_path_factory.mktemp("out")
    os.environ.setdefault("CAPTURE_STAGE_CACHE", str(d / "cache"))
    from fake_cameras.record import record_take
    from fake_cameras.take import simulate_take

    return record_take(simulate_take("starfish", n_cameras=4, frames=2, size=(64, 48), seed=1), d / "t.h5")


def test_quiet_and_verbose_after_the_command():
    p = build_parser()
    assert p.parse_args(["rig", "-q"]).quiet is True
    assert p.parse_args(["-q", "info", "x"]).quiet is True  # kept when the command does not repeat it
    assert p.parse_args(["info", "x"]).quiet is False
    assert p.parse_args(["info", "-vv", "x"]).verbose == 2
    assert p.parse_args(["process", "t.h5", "--out", "r", "--progress"]).progress is True


def test_progress_bars_only_on_a_terminal(monkeypatch):
    def args(**kw):
        return argparse.Namespace(**{"no_progress": False, "quiet": False, "progress": False, **kw})

    monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
    a = args()
    assert not _progress_bars(a) and a.no_progress  # a file or a pipe: no bars
    a = args(progress=True)
    assert _progress_bars(a) and not a.no_progress
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    assert _progress_bars(args())
    for kw in ({"quiet": True}, {"no_progress": True}, {"quiet": True, "progress": True}):
        a = args(**kw)
        assert not _progress_bars(a) and a.no_progress
    a = argparse.Namespace(quiet=True, progress=True)  # a command without the option: it reads no_progress
    assert not _progress_bars(a) and a.no_progress


def test_a_closed_pipe_ends_quietly(take):
    p = subprocess.Popen([sys.executable, "-m", "stage", "info", str(take)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    p.stdout.close()  # `stage info | head -0`: the reader is gone before the first line
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 0 and err == "", err


def test_key_names_the_derived_file(take, capsys):
    assert main(["key", str(take), "--no-progress", "--workers", "1"]) == 0
    out = capsys.readouterr().out
    assert f"masks stored in {take.with_name('t.derived.h5')}" in out


def test_info_warns_of_a_sync_relock(tmp_path, capsys):
    """`stage info` names a camera whose frames left their sync chain, and from which set on."""
    from stage.store import CameraSpec, TakeWriter
    from tests.stage.frames import H, W, make_frame

    path = tmp_path / "t.h5"
    with TakeWriter(path, [CameraSpec(c, W, H) for c in "ab"], fps=30) as w:
        for k in range(3):
            w.write_set({c: make_frame(c, i, k) for i, c in enumerate("ab")})
        cams = {c: {"frames": 3, "missing": 0, "sequence_gaps": 0, "unused": 0, "offset_ns": 0} for c in "ab"}
        cams["b"].update(relocks=1, first_relock_set=2)
        cams["a"] = {"missing": 0}  # statistics with fewer fields (older or imported takes) still print
        w.update_sync_stats({"sets": 3, "sets_complete": 3, "cameras": cams})
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "warning: b: its frames left their sync chain 1 time(s), in set 2" in out
    assert "warning: a" not in out and "a: 160x120 raw, 3 frames, missing in 0 sets, device gaps 0" in out


def test_the_demo_ends_with_the_command_that_builds_the_armature(tmp_path, capsys, monkeypatch):
    """The demo's last line names the next step of a take's path, its armature, as a command that runs on the demo's
    results (``stage armature RESULTS_DIR``, which tracks first)."""
    import shlex

    import pipeline.gltf_export
    import pipeline.report
    from stage.cli.demo import _take_away

    monkeypatch.setattr(pipeline.gltf_export, "export_rig", lambda d: d / "spine_rig.glb")  # the files: not this test's
    monkeypatch.setattr(pipeline.report, "write_report", lambda d, take: d / "report.html")
    results = tmp_path / "demo-out" / "starfish-results"
    _take_away(results, tmp_path / "demo-out" / "starfish.h5", {"seconds": 12.0}, tmp_path / "demo-out")
    last = capsys.readouterr().out.splitlines()[-1]
    command = shlex.split(last.split(": ", 1)[1].split(" (", 1)[0])
    assert command == ["stage", "armature", str(results)], last
    assert build_parser().parse_args(command[1:]).results == results


def test_track_help_names_the_template_frame_it_tracks_from(tmp_path, capsys):
    """``stage track --help`` names the template a results directory gets, the surface of the spine's reference frame
    (tracked/track.json's ``reference_frame``, ``template``), not the first frame's, which it is only without a
    spine."""
    text = _help_text(capsys, "track")
    assert "the template is the surface of the spine's reference frame, tracked forwards and backwards from it " \
           "(without spine.json: the first frame's), unless given" in text
    assert "(default for RESULTS_DIR: the surface of the spine's reference frame)" in text


def test_track_help_says_how_the_data_weight_is_chosen(capsys):
    """``stage track --help``'s default ``--gamma`` is the rule :func:`pipeline.tracking.choose_gamma` applies: its two
    values either side of the stated mean triangle area (a square of two triangles, area side^2 / 2 each)."""
    import re

    import numpy as np

    from pipeline.tracking import choose_gamma

    text = _help_text(capsys, "track")
    found = re.search(r"--gamma GAMMA data weight \(default: ([\d.]+) when the template's mean triangle area is above "
                      r"([\d.]+) mm\^2, else ([\d.]+);", text)
    assert found, text
    above, area, below = map(float, found.groups())
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    for scale, want in ((1.01, above), (0.99, below)):
        side = np.sqrt(2 * area * scale)
        square = np.array([[0, 0, 0], [side, 0, 0], [side, side, 0], [0, side, 0]], dtype=float)
        assert choose_gamma(square, faces) == want


def test_the_fast_motion_chain_is_the_same_in_the_help_the_readme_and_the_docs(capsys):
    """The opt-in chain for fast limbs, as ``stage track --help`` and README's day at the stage give it, is the job
    parameters docs/tracking.md gives for it, option by option."""
    import json
    import re
    import shlex
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    with pytest.raises(SystemExit):
        main(["track", "--help"])
    helped = re.search(r"^ +(stage track RESULTS_DIR --labels .*)$", capsys.readouterr().out, re.M)
    readme = [line.split("  #", 1)[0] for line in (root / "README.md").read_text(encoding="utf-8").splitlines()
              if line.startswith("stage track results/ --labels")]
    docs = re.search(r"the chain for fast motion below is\s+`(\{.*?\})`", (root / "docs" / "tracking.md").read_text(
        encoding="utf-8"), re.S)
    assert helped and len(readme) == 1 and docs
    job = json.loads(docs.group(1))
    for line in (helped.group(1), readme[0]):
        args = build_parser().parse_args(shlex.split(line)[1:])
        assert {"labels": args.labels, "colour": args.colour, "armature_rounds": args.rig_rounds,
                "armature_parts": args.armature_parts} == job, line


def test_armature_help_says_meshes_need_an_out_directory(tmp_path, capsys):
    """``stage armature --out``'s help says it is required with ``--meshes``, as the command then says."""
    assert "(default RESULTS_DIR/rig; required with --meshes)" in _help_text(capsys, "armature")
    assert main(["armature", "--meshes", str(tmp_path / "*.obj")]) == 2
    assert "--meshes needs --out DIR" in capsys.readouterr().err


def test_armature_help_says_which_rest_frame_it_chooses(capsys):
    """``stage armature --reference``'s default is :func:`pipeline.armature.choose_reference`'s: of as many evenly
    spaced frames as its ``candidates``, the one whose curve skeleton shows the most tips."""
    import inspect
    import re

    from pipeline.armature import choose_reference

    text = _help_text(capsys, "armature")
    found = re.search(r"--reference POS position \(0-based\) of the rest frame \(default: of (\d+) evenly spaced "
                      r"frames, the one whose curve skeleton shows the most tips\)", text)
    assert found, text
    assert int(found.group(1)) == inspect.signature(choose_reference).parameters["candidates"].default

