"""Imports run one way (docs/architecture.md): no module imports a higher floor, not even
inside a function, and two packages on one floor do not import each other.

Every module of the five packages is parsed with :mod:`ast`; every ``import`` and
``from ... import`` counts, wherever it is (module level, function, ``if TYPE_CHECKING``),
and so does a string that is a whole import path (``"pipeline.process:process_take"``), since
``importlib`` turns it into an import the parser would not see.
"""

from __future__ import annotations

import ast
import functools
import graphlib
import re
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("stage", "calib", "pipeline", "api", "fake_cameras")

#: floor number -> (name, modules). ``"x"`` is the module (or package ``__init__``) ``x`` alone;
#: ``"x.*"`` is ``x`` and everything below it. Every module must be named: a new module fails
#: the test until it is placed here (and in docs/architecture.md when it opens a new room).
FLOORS: dict[int, tuple[str, tuple[str, ...]]] = {
    0: ("model", (
        "calib", "calib.camera", "calib.calibration", "calib.boards", "calib.formats", "calib._toml", "calib.fileio",
        "stage", "stage.frame", "stage.rig", "stage.workers", "stage.messages",
    )),
    1: ("ground", (
        "stage.drivers.*", "stage.sync", "stage.store.*", "stage.keying.*", "stage.discovery", "stage.capture", "stage.session",
        "stage.importer",
        "pipeline", "pipeline.volume", "pipeline.geodesic", "pipeline.meshio", "pipeline.mesh_primitives", "pipeline.cholesky",
    )),
    2: ("steps", (
        "pipeline.hull", "pipeline.subject_box", "pipeline.consistency",
        "pipeline.surface", "pipeline.photo_refine", "pipeline.tsdf", "pipeline.skeleton", "pipeline.merge",
        "pipeline.extremities", "pipeline.correspond", "pipeline.frame_skeleton", "pipeline.spine", "pipeline.spine_format",
        "pipeline.skinning",
        "pipeline.armature_spine", "pipeline.gltf_export", "pipeline.results",
        "pipeline.tracking", "pipeline.tracking_patches", "pipeline.rgbd_preprocess", "pipeline.colour_tracks",
        "pipeline.temporal_hull",
        "pipeline.motion_segmentation", "pipeline.trajectory_distances", "pipeline.rigid_parts",
        "pipeline.armature_skeleton", "pipeline.armature_fit", "pipeline.armature", "pipeline.armature_track",
        "pipeline.armature_limbs", "pipeline.template_labels", "pipeline.limb_segments",
        "pipeline.contraction_skeleton", "pipeline.armature_score", "pipeline.silhouette_refine",
        "calib.detect", "calib.intrinsics", "calib.extrinsics", "calib.bundle", "calib.rig", "calib.synthetic",
        "calib.evaluate", "calib.timestamps", "calib.mirror",
    )),
    3: ("orchestration", (
        # processing, tracking and the report run the pipeline over a take
        "pipeline.process.*", "pipeline.run.*", "pipeline.report.*", "pipeline.track", "pipeline.track_armature",
        "pipeline.track_armature_round", "pipeline.track_armature_models", "pipeline.track_armature_labels",
        "pipeline.track_frames",
        "pipeline.track_rgbd", "pipeline.track_colour", "pipeline.carve", "pipeline.armature_files", "pipeline.spine_meshes",
        "fake_cameras.*",
        # calibration run over a take
        "calib.take_detect",
    )),
    4: ("service", ("api.*",)),
    5: ("composition root", ("stage.cli.*", "stage.benchmarks.*", "stage.__main__")),
}

@dataclass(frozen=True)
class Edge:
    importer: str
    imported: str
    path: Path
    line: int
    how: str  # "import" or "string"

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.importer} -> {self.imported} ({self.how})"


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


@functools.cache
def _parse_cached(path: str, mtime_ns: int, size: int) -> ast.Module:
    return ast.parse(Path(path).read_text(encoding="utf-8"), filename=path)


def parse(path: Path) -> ast.Module:
    """The file's syntax tree, parsed once per version of the file (the import and the size checks share it)."""
    st = path.stat()
    return _parse_cached(str(path), st.st_mtime_ns, st.st_size)


def imports_of(path: Path, root: Path, packages: tuple[str, ...]) -> list[Edge]:
    """Every import of one of ``packages`` in the file, at any depth, and whole import-path strings."""
    name = module_name(path, root)
    is_pkg = path.name == "__init__.py"
    tree = parse(path)
    pattern = re.compile(r"^(?:%s)(?:\.[A-Za-z_]\w*)*(?::[A-Za-z_]\w*)?$" % "|".join(map(re.escape, packages)))
    out = []
    for node in ast.walk(tree):
        targets: list[tuple[str, str]] = []
        if isinstance(node, ast.Import):
            targets = [(a.name, "import") for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = name.split(".") if is_pkg else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # ``from pkg import mod`` imports pkg.mod when that is a module
            targets = [(mod, "import")] + [(f"{mod}.{a.name}", "import?") for a in node.names]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and pattern.match(node.value):
            targets = [(node.value.split(":")[0], "string")]
        for target, how in targets:
            if target.split(".")[0] in packages:
                out.append(Edge(name, target, path.relative_to(root), node.lineno, how))
    return out


def import_graph(root: Path, packages: tuple[str, ...]) -> tuple[set[str], list[Edge]]:
    """All modules of ``packages`` under ``root`` and the edges between them."""
    modules, edges = set(), []
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            modules.add(module_name(path, root))
            edges += imports_of(path, root, packages)
    resolved = []
    for e in edges:
        if e.how == "import?":  # ``from a import b``: an edge to a.b only when a.b is a module
            if e.imported in modules:
                resolved.append(Edge(e.importer, e.imported, e.path, e.line, "import"))
        else:
            resolved.append(e)
    return modules, resolved


def _matches(module: str, pattern: str) -> bool:
    if pattern.endswith(".*"):
        base = pattern[:-2]
        return module == base or module.startswith(base + ".")
    return module == pattern


def floor_of(module: str, floors: dict[int, tuple[str, tuple[str, ...]]]) -> int | None:
    """The floor naming ``module`` (exactly, or through the longest ``x.*``)."""
    best, best_len = None, -1
    for number, (_, patterns) in floors.items():
        for p in patterns:
            if _matches(module, p) and len(p) > best_len:
                best, best_len = number, len(p)
    return best


def violations(root: Path, packages: tuple[str, ...], floors) -> list[str]:
    """Upward imports, imports between packages of one floor, modules without a floor, room cycles."""
    modules, edges = import_graph(root, packages)
    problems = [f"{m}: on no floor (add it to FLOORS and docs/architecture.md)"
                for m in sorted(modules) if floor_of(m, floors) is None]
    rooms: dict[tuple[int, str], set[tuple[int, str]]] = {}
    for e in edges:
        a, b = floor_of(e.importer, floors), floor_of(e.imported, floors)
        if a is None or b is None:
            continue
        pa, pb = e.importer.split(".")[0], e.imported.split(".")[0]
        rooms.setdefault((a, pa), set())
        if (b, pb) != (a, pa):
            rooms[(a, pa)].add((b, pb))
        if b > a:
            problems.append(f"upward import, floor {a} ({floors[a][0]}) -> floor {b} ({floors[b][0]}): {e}")
        elif b == a and pa != pb:
            problems.append(f"import between two packages of floor {a} ({floors[a][0]}): {e}")
    try:
        graphlib.TopologicalSorter(rooms).prepare()
    except graphlib.CycleError as exc:
        problems.append(f"circular imports between packages/floors: {exc.args[1]}")
    return problems


# --------------------------------------------------------------------------- the project


@functools.cache
def _project_graph():
    return import_graph(ROOT, PACKAGES)


def test_imports_run_one_way():
    problems = violations(ROOT, PACKAGES, FLOORS)
    assert not problems, "\n".join(problems)


def test_no_installed_module_imports_the_tests():
    """``tests`` is not packaged (pyproject's packages are the five): an import of it from a
    packaged module works in the checkout and dies in an installed ``stage``."""
    found = [str(e) for pkg in PACKAGES for path in sorted((ROOT / pkg).rglob("*.py"))
             for e in imports_of(path, ROOT, ("tests",))]
    assert not found, "\n".join(found)


def test_the_tests_check_catches_an_import_of_the_tests(tmp_path):
    root = _tree(tmp_path, {"low/__init__.py": "", "low/a.py": "def f():\n    from tests.conftest import X\n"})
    assert [e.imported for e in imports_of(root / "low" / "a.py", root, ("tests",))] == ["tests.conftest",
                                                                                       "tests.conftest.X"]


_TEST_FILE_IMPORT = re.compile(r"\b(?:from|import)\s+tests(?:\.\w+)*\.test_\w+|\bfrom\s+tests(?:\.\w+)*\s+import\s+[^\n]*\btest_\w+")


def imports_of_test_files(text: str) -> list[str]:
    """The imports of a test file (``test_*.py``) in ``text``: statements, and the code of child
    processes a test writes as a string."""
    return _TEST_FILE_IMPORT.findall(text)


def test_no_test_imports_another_test_file():
    """What several test files share lives in a fixture module (``conftest.py``, or a module not named
    ``test_*``): a test file imported by another is collected twice, its module caches are built
    in two workers, and its tests cannot move without breaking the other."""
    found = [f"{path.relative_to(ROOT)}: {hit}" for path in sorted((ROOT / "tests").rglob("*.py"))
             if path != Path(__file__) for hit in imports_of_test_files(path.read_text(encoding="utf-8"))]
    assert not found, "\n".join(found)


def test_the_test_import_check_catches_each_form():
    assert imports_of_test_files("from tests.pipeline.test_hull import sim_grid\n")
    assert imports_of_test_files("    from tests.api import test_serve\n")
    assert imports_of_test_files("code = 'import sys; from tests.stage.test_store import make_frame'")
    assert not imports_of_test_files("from tests.pipeline.shapes import capsule\nfrom tests.conftest import SHARED_DATA\n")


def test_every_floor_entry_is_a_module():
    modules, _ = _project_graph()
    stale = [p for _, patterns in FLOORS.values() for p in patterns if not any(_matches(m, p) for m in modules)]
    assert not stale, f"FLOORS names modules that do not exist: {stale}"


def test_the_architecture_doc_names_every_module():
    """docs/architecture.md draws the layout in words: every module the floor map names is in it."""
    doc = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    words = set(re.findall(r"[A-Za-z_]\w*", doc)) | set(re.findall(r"[A-Za-z_][\w.]*\w", doc))
    missing = [p for _, patterns in FLOORS.values() for p in patterns
               if p.removesuffix(".*") not in words and p.removesuffix(".*").rsplit(".", 1)[-1] not in words]
    assert not missing, f"docs/architecture.md does not name: {missing}"


# --------------------------------------------------------------------------- sizes


#: One idea a module: no module of ``pipeline/`` is longer than this many lines.
MAX_MODULE_LINES = 700
#: One screen an idea: no function (or method) of the five packages is longer than this many lines,
#: its docstring not counted (tests are not held to it).
MAX_FUNCTION_LINES = 80
#: Modules kept over the limit, and why (each must still be over it: the list only shrinks).
LONG_MODULES: dict[str, str] = {}
#: Functions kept over the limit ("path:qualified name"), and why.
LONG_FUNCTIONS: dict[str, str] = {}


def body_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines of a function from its ``def`` to its end, its docstring (and decorators) not counted."""
    n = node.end_lineno - node.lineno + 1
    first = node.body[0]
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        n -= first.end_lineno - first.lineno + 1
    return n


def long_functions(path: Path, root: Path, limit: int) -> dict[str, int]:
    """``{"path:qualified name": lines}`` of the functions in ``path`` longer than ``limit``."""
    found: dict[str, int] = {}
    rel = path.relative_to(root).as_posix()

    def walk(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef) and body_lines(child) > limit:
                    found[f"{rel}:{name}"] = body_lines(child)
                walk(child, name + ".")

    walk(parse(path), "")
    return found


def _package_files() -> list[Path]:
    return [p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))]


def test_no_pipeline_module_is_over_the_limit():
    sizes = {p.relative_to(ROOT).as_posix(): len(p.read_text(encoding="utf-8").splitlines())
             for p in sorted((ROOT / "pipeline").rglob("*.py"))}
    over = {m: n for m, n in sizes.items() if n > MAX_MODULE_LINES and m not in LONG_MODULES}
    assert not over, f"modules over {MAX_MODULE_LINES} lines (split them by idea): {over}"
    stale = [m for m in LONG_MODULES if sizes.get(m, 0) <= MAX_MODULE_LINES]
    assert not stale, f"LONG_MODULES lists modules that are no longer over the limit: {stale}"


def test_no_function_is_over_the_limit():
    found: dict[str, int] = {}
    for path in _package_files():
        found.update(long_functions(path, ROOT, MAX_FUNCTION_LINES))
    over = {f: n for f, n in found.items() if f not in LONG_FUNCTIONS}
    assert not over, f"functions over {MAX_FUNCTION_LINES} lines, docstring aside (one screen an idea): {over}"
    stale = [f for f in LONG_FUNCTIONS if f not in found]
    assert not stale, f"LONG_FUNCTIONS lists functions that are no longer over the limit: {stale}"


def test_the_size_checks_count_what_they_say(tmp_path):
    five = "".join(f"    x{i} = {i}\n" for i in range(5))
    text = ('def short():\n    """Doc\n\n    more doc\n    """\n' + five + "\n\n"
            "class A:\n    def long(self):\n" + textwrap.indent(five + five, "    "))
    (tmp_path / "m.py").write_text(text)
    assert long_functions(tmp_path / "m.py", tmp_path, 6) == {"m.py:A.long": 11}
    assert long_functions(tmp_path / "m.py", tmp_path, 5) == {"m.py:short": 6, "m.py:A.long": 11}


# --------------------------------------------------------------------------- the checker itself


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(textwrap.dedent(text))
    return tmp_path


TOY_FLOORS = {0: ("low", ("low.*",)), 1: ("high", ("high.*",))}
TOY = {"low/__init__.py": "", "low/a.py": "import math\n", "high/__init__.py": "", "high/b.py": "from low import a\n"}


def test_checker_passes_a_clean_tree(tmp_path):
    assert violations(_tree(tmp_path, TOY), ("low", "high"), TOY_FLOORS) == []


@pytest.mark.parametrize("planted", [
    "from high import b\n",                                   # module level
    "def f():\n    from high.b import x\n    return x\n",     # inside a function
    "def f():\n    import high.b\n",                          # plain import in a function
    "WORK = 'high.b:run'\n",                                  # an import path as a string
    "from ..high import b\n",                                 # relative import out of the package
])
def test_checker_fails_on_a_planted_upward_import(tmp_path, planted):
    root = _tree(tmp_path, {**TOY, "low/a.py": planted})
    problems = violations(root, ("low", "high"), TOY_FLOORS)
    assert len(problems) >= 1 and "upward import" in problems[0], problems


def test_checker_fails_between_packages_of_one_floor(tmp_path):
    floors = {0: ("ground", ("low.*", "high.*"))}
    problems = violations(_tree(tmp_path, TOY), ("low", "high"), floors)
    assert any("between two packages of floor 0" in p for p in problems), problems


def test_checker_fails_on_a_module_without_floor(tmp_path):
    root = _tree(tmp_path, {**TOY, "other/__init__.py": ""})
    problems = violations(root, ("low", "high", "other"), TOY_FLOORS)
    assert problems == ["other: on no floor (add it to FLOORS and docs/architecture.md)"]


def test_checker_fails_on_a_cycle_the_floors_do_not_order(tmp_path):
    floors = {0: ("one", ("low.*", "high.*"))}
    root = _tree(tmp_path, {**TOY, "low/a.py": "import high.b\n"})
    assert any("circular" in p for p in violations(root, ("low", "high"), floors))


def test_the_project_goes_red_on_a_planted_upward_import(tmp_path):
    """The real floor map on a copy of one ground module with an upward import planted in a function."""
    files = {f"{p}/__init__.py": "" for p in PACKAGES}
    files["stage/rig.py"] = "def f():\n    from pipeline.volume import check_plane\n    return check_plane\n"
    files["pipeline/volume.py"] = "from stage.rig import f\n"
    problems = [p for p in violations(_tree(tmp_path, files), PACKAGES, FLOORS) if "no floor" not in p]
    assert problems and "upward import, floor 0 (model) -> floor 1 (ground)" in problems[0], problems
