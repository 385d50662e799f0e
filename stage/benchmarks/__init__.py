"""Benchmarks run by ``stage bench NAME``; one module per benchmark."""

#: How far (mm, standard deviation per coordinate) a ``--copies`` copy moves every vertex of what it copies (a
#: tracking for ``stage bench armature``, the surfaces for ``stage bench track`` and ``patches``): far below a
#: voxel (a tracking re-run on another machine differs by about as much), so a figure that changes under it is
#: one draw among several (docs/notes/armature-decisions.md, "How reproducible the armature of a tracking is";
#: docs/notes/tracking-decisions.md, "How reproducible the tracking figures are").
COPY_SIGMA = 0.001


def check_copies(copies, *, name: str = "copies") -> int:
    """A count of moved copies (an integer >= 0), or a ValueError naming ``name`` (the option or the parameter)."""
    if isinstance(copies, bool) or not isinstance(copies, int) or copies < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {copies!r}")
    return copies


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
