"""The docs a newcomer reads resolve inside a clone of the repository.

Every relative Markdown link of README.md and docs/ (a file, and its ``#anchor`` when it names a
heading of a Markdown file) resolves, every path of the repository they name (``docs/...md``,
``tests/...py``, ``pipeline/...py``, ...) exists, and no doc cites a path outside the repository
(``/tmp/...``, ``/work/notes/...``): a figure cites a command the repository can run. CHANGELOG.md is
checked for the outside paths only (its entries name files as they were).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
REPO_PATH = re.compile(r"(?<![\w/.~-])((?:docs|tests|pipeline|stage|fake_cameras|calib|api)/[\w./-]+\.(?:py|md|toml|json|sh))")
OUTSIDE = re.compile(r"/tmp/|/work/|/home/|/root/")


def anchors(path: Path) -> set[str]:
    """GitHub's anchors of a Markdown file's headings: lower case, punctuation but '-' and '_' dropped,
    spaces as '-'."""
    out = set()
    for line in path.read_text(encoding="utf-8").splitlines():
        m = re.match(r"#{1,6}\s+(.*)", line)
        if m:
            text = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower())
            out.add(text.replace(" ", "-"))
    return out


def broken_links(path: Path) -> list[str]:
    text = path.read_text(encoding="utf-8")
    bad = []
    for target in LINK.findall(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        if not dest.exists():
            bad.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(target)
    bad += [p for p in REPO_PATH.findall(text) if not (ROOT / p).exists()]
    return bad


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_links_and_paths_resolve(path):
    assert broken_links(path) == []


@pytest.mark.parametrize("path", [*DOCS, ROOT / "CHANGELOG.md"], ids=lambda p: str(p.relative_to(ROOT)))
def test_no_doc_cites_a_path_outside_the_repository(path):
    lines = [f"{k}: {line.strip()[:80]}" for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
             if OUTSIDE.search(line)]
    assert lines == []


def test_the_checks_fail_on_what_they_look_for(tmp_path):
    doc = tmp_path / "x.md"
    doc.write_text("# Title\n[a](missing.md) [b](#title) [c](#nowhere) [d](https://example.org) `tests/none_such.py`\n")
    assert broken_links(doc) == ["missing.md", "#nowhere", "tests/none_such.py"]
    assert OUTSIDE.search("driver `/tmp/x/run.py`") and OUTSIDE.search("/work/notes/a.md")


def day_at_the_stage(text: str) -> list[list[str]]:
    """The commands of README.md's "A day at the stage" block, each as its words (comments dropped)."""
    import shlex

    block = text.split("## A day at the stage", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    return [shlex.split(line.split("  #", 1)[0]) for line in block.splitlines() if line.startswith("stage ")]


def test_a_day_at_the_stage_runs_in_its_order():
    """README's day at the stage is the take's path a newcomer follows: every command parses with the CLI as written,
    and the results directory's armature (``stage armature results/``) is built before its BVH is exported from it
    (``stage export results/ --format bvh`` needs ``results/rig/rig.json``)."""
    from stage.cli import build_parser

    commands = day_at_the_stage((ROOT / "README.md").read_text(encoding="utf-8"))
    parser = build_parser()
    for words in commands:
        parser.parse_args(words[1:])  # exits (SystemExit) on an option the command does not have
    at = {" ".join(w[1:3]): i for i, w in enumerate(commands)}
    assert at["armature results/"] < next(i for i, w in enumerate(commands) if w[1] == "export" and "bvh" in w)


def test_the_days_exports_name_the_files_they_write():
    """Every ``stage export`` of README's day at the stage names the file it writes (``stage export``'s default name
    for its format, in ``results/``), and the day's trackings after the first say they are its alternatives (each
    tracks the take again: a tracking with other options starts over)."""
    import shlex

    from stage.cli import build_parser
    from stage.cli.export import DEFAULT_NAMES

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    block = text.split("## A day at the stage", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    lines = [line for line in block.splitlines() if line.startswith("stage export results/")]
    assert lines
    for line in lines:
        command, comment = line.split("  #", 1)
        fmt = build_parser().parse_args(shlex.split(command)[1:]).format
        assert f"results/{DEFAULT_NAMES[fmt]}" in comment, line
    tracks = [line.split("  #", 1)[1].strip() for line in block.splitlines() if line.startswith("stage track results/")]
    assert len(tracks) >= 2 and all(c.startswith("or, ") for c in tracks[1:]), tracks

