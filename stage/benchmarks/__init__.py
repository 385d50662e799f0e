"""Benchmarks run by ``stage bench NAME``; one module per benchmark, and here the pieces several of them share."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np

#: How far (mm, standard deviation per coordinate) a ``--copies`` copy moves every vertex of what it copies (a
#: tracking for ``stage bench armature``, the surfaces for ``stage bench track`` and ``patches``): far below a
#: voxel (a tracking re-run on another machine differs by about as much), so a figure that changes under it is
#: one draw among several (docs/notes/armature-decisions.md, "How reproducible the armature of a tracking is";
#: docs/notes/tracking-decisions.md, "How reproducible the tracking figures are").
COPY_SIGMA = 0.001


def check_copies(copies, *, name: str = "copies") -> int:
    """A count of moved copies, checked.

    Parameters
    ----------
    copies : int
        How many moved copies: an integer >= 0 (numpy's integers too, as the seeds; not a bool).
    name : str
        What the error calls it: the parameter or the command-line option.

    Returns
    -------
    int
        ``copies`` as a Python int.

    Raises
    ------
    ValueError
        Naming ``name`` when ``copies`` is not an integer >= 0.
    """
    return _whole(copies, name)


def _whole(x, name: str) -> int:
    """``x`` as a Python int when it is an integer >= 0 (numpy's too, not a bool), else a ValueError naming
    ``name``: the one check of the copies' count, the draws' seed and the printed digits."""
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {x!r}")
    return int(x)


def check_sigma(sigma, *, name: str = "sigma") -> float:
    """How far a copy moves every coordinate (mm, a number > 0, not a bool), or a ValueError naming ``name``."""
    if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not (math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"{name} must be a number > 0 (mm), got {sigma!r}")
    return sigma


def move_meshes(paths, *, seed: int, sigma: float = COPY_SIGMA) -> None:
    """Move every vertex of the PLY meshes ``paths`` by N(0, ``sigma``) mm per coordinate, in place.

    The draws come from ``numpy.random.default_rng(seed)``, mesh after mesh in the order of ``paths``: the same
    seed and paths move every vertex the same way. Every mesh is rewritten whole (its faces as they were), each
    write atomic.

    Parameters
    ----------
    paths : iterable of path
        The meshes, in the order they draw.
    seed : int
        The draws' seed (>= 0).
    sigma : float
        Standard deviation of every coordinate's move, mm (> 0).

    Raises
    ------
    ValueError
        Naming ``seed`` or ``sigma`` when out of range, before any mesh is read.
    """
    from pipeline.meshio import load_mesh
    from pipeline.results import atomic_write_bytes, ply_bytes

    rng = np.random.default_rng(_whole(seed, "seed"))
    check_sigma(sigma)
    for path in paths:
        v, f = load_mesh(path, largest=False)
        atomic_write_bytes(path, ply_bytes(v + rng.normal(scale=sigma, size=v.shape), f))


def moved_surfaces(results, dst, *, seed: int, sigma: float = COPY_SIGMA) -> Path:
    """A copy of a processed results directory whose surfaces are moved by round-off-sized amounts.

    ``results`` is copied to ``dst`` without ``tracked/`` and ``rig/``, and every vertex of every surface
    (``meshes/frame_NNNNNN.ply``: the data the tracking tracks, and its template) is moved by N(0, ``sigma``) mm
    per coordinate, drawn by ``numpy.random.default_rng(seed)`` surface after surface in frame order
    (:func:`move_meshes`). The spine, the grid and the take the colour tracks read stay the take's own.

    Parameters
    ----------
    results : path
        A ``stage process`` results directory.
    dst : path
        Where the copy goes (replaced when it is there); neither ``results`` itself nor inside it, nor a directory
        that holds ``results``.
    seed : int
        The draws' seed (>= 0): the same seed moves every vertex the same way.
    sigma : float
        Standard deviation of every coordinate's move, mm (> 0).

    Returns
    -------
    Path
        ``dst``.

    Raises
    ------
    ValueError
        Naming ``seed`` or ``sigma`` when out of range, ``results`` when it is not a processed results directory,
        and ``dst`` when it is ``results``, lies inside it or holds it (replacing it would delete the results);
        nothing is touched then.
    """
    _whole(seed, "seed")
    check_sigma(sigma)
    results, dst = Path(results), Path(dst)
    if not (results / "meshes").is_dir():
        raise ValueError(f"results must be a processed results directory (with meshes/), got {str(results)!r}")
    src, out = results.resolve(), dst.resolve()
    if out == src or src in out.parents or out in src.parents:
        raise ValueError(f"dst must lie outside results and not hold it, got {str(dst)!r} for {str(results)!r}")
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(results, dst, ignore=shutil.ignore_patterns("tracked", "rig"))
    move_meshes(sorted((dst / "meshes").glob("frame_*.ply")), seed=seed, sigma=sigma)
    return dst


def spread_cell(values, digits: int) -> str:
    """A figure over a run and its moved copies as "mean (least..most)", each with ``digits`` decimals.

    Parameters
    ----------
    values : sequence of float
        The figure of every run (at least one).
    digits : int
        Decimals printed (>= 0).

    Returns
    -------
    str
        E.g. ``"1.25 (1.00..1.50)"`` for 1.0, 1.5 and 1.25 with 2 decimals.

    Raises
    ------
    ValueError
        Naming ``values`` when it is empty, ``digits`` when it is not an integer >= 0.
    """
    _whole(digits, "digits")
    x = np.asarray(values, dtype=np.float64).ravel()
    if not len(x):
        raise ValueError("values must hold at least one figure")
    d = int(digits)
    return f"{x.mean():.{d}f} ({x.min():.{d}f}..{x.max():.{d}f})"


def spread_figures(rows: list[dict]) -> str:
    """A tracking's four figures over itself and its moved copies, each as mean (least..most).

    Parameters
    ----------
    rows : list of dict
        The figures of the tracking and of each copy (the tracking's first), as
        :func:`stage.benchmarks.patches.track_row` gives them: ``mean``, ``p95`` and ``worst`` (the worst frame's
        mean and 95th percentile).

    Returns
    -------
    str
        "mean / 95th percentile; worst frame's mean / 95th percentile", each cell :func:`spread_cell`'s (three
        decimals, then two).

    Raises
    ------
    ValueError
        Naming ``rows`` when it is empty.
    """
    if not rows:
        raise ValueError("rows must hold at least one tracking's figures")
    figures = np.array([[r["mean"], r["p95"], *r["worst"]] for r in rows], dtype=np.float64)
    cells = [spread_cell(f, d) for f, d in zip(figures.T, (3, 3, 2, 2))]
    return f"{cells[0]} / {cells[1]}; {cells[2]} / {cells[3]}"


def seeds_option(text: str, option: str = "--take-seeds") -> list[int]:
    """The simulator's seeds of a comma-separated option (``"3,5"`` -> ``[3, 5]``); ``ValueError`` names ``option``."""
    try:
        seeds = [int(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"{option} must be integers (e.g. 3,5), got {text!r}") from None
    if not seeds:
        raise ValueError(f"{option}: give at least one seed")
    if min(seeds) < 0:
        raise ValueError(f"{option} must be seeds >= 0, got {text!r}")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"{option}: a seed given twice in {text!r}")
    return seeds


def check_starts(starts, *, name: str = "starts") -> list[float]:
    """Simulated takes' start times, checked.

    Parameters
    ----------
    starts : sequence of float
        Seconds into the creature's motion each take starts at (``fake_cameras.take.simulate_take(start=)``): at
        least one, each a finite number >= 0 (numpy's numbers too; not a bool), none given twice.
    name : str
        What the error calls it: the parameter or the command-line option.

    Returns
    -------
    list of float
        ``starts`` as Python floats, in their order.

    Raises
    ------
    ValueError
        Naming ``name`` when ``starts`` is a string or not a sequence, is empty, or holds a value that is not a
        finite number >= 0 or is given twice.
    """
    try:
        if isinstance(starts, (str, bytes)):
            raise TypeError
        values = list(starts)
    except TypeError:
        raise ValueError(f"{name} must be a sequence of seconds >= 0, got {starts!r}") from None
    if not values:
        raise ValueError(f"{name}: give at least one start")
    for s in values:
        if isinstance(s, bool) or not isinstance(s, (int, float, np.integer, np.floating)) or not (
                math.isfinite(s) and s >= 0):
            raise ValueError(f"{name} must be finite numbers of seconds >= 0, got {starts!r}")
    out = [float(s) for s in values]
    if len(set(out)) != len(out):
        raise ValueError(f"{name}: a start given twice in {starts!r}")
    return out


def starts_option(text: str, option: str = "--take-starts") -> list[float]:
    """The take starts of a comma-separated option (``"0,0.3125"`` -> ``[0.0, 0.3125]``), checked by
    :func:`check_starts`; ``ValueError`` names ``option``."""
    try:
        starts = [float(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"{option} must be numbers of seconds (e.g. 0,0.3125), got {text!r}") from None
    return check_starts(starts, name=option)
