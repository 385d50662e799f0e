"""Benchmarks run by ``stage bench NAME``; one module per benchmark."""


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
