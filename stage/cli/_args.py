"""Argument parsers shared by the ``stage`` subcommands and benchmarks."""

from __future__ import annotations

__all__ = ["parse_size", "units_warning", "assumed_units", "MESH_UNITS_DEFAULT"]

#: the units of a mesh sequence (``--meshes``) whose command was given none
MESH_UNITS_DEFAULT = "mm"


def parse_size(text: str) -> tuple[int, int]:
    """Image size ``WxH`` (e.g. ``640x480``) as ``(width, height)``; at least 64x48.

    Raises
    ------
    ValueError
        Naming ``--size`` when the text is not ``WxH`` or the size is too small.
    """
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--size must look like 640x480, got {text!r}") from None
    if w < 64 or h < 48:
        raise ValueError(f"--size must be at least 64x48, got {text!r}")
    return w, h


def units_warning(span: float) -> str | None:
    """The warning for a mesh sequence taken in millimetres because no ``--units`` was given, when its
    span (the longest side of the first frame's bounding box) makes a subject the stage cannot have
    filmed: under 10 mm (a sequence in metres, or scaled to a unit box, as many datasets are) or over
    100 m. None otherwise. Every file written from it (spine.json, rig.json, the GLB in metres, the BVH)
    carries those units.

    Raises
    ------
    ValueError
        Naming ``span`` when it is not a finite number >= 0.
    """
    import math

    if isinstance(span, bool) or not isinstance(span, (int, float)) or not math.isfinite(span) or span < 0:
        raise ValueError(f"span must be a finite number >= 0, got {span!r}")
    if 10 <= span <= 1e5:
        return None
    other = ("m", "a {:.3g} m subject".format(span)) if span < 10 else ("um", "a {:.3g} mm subject".format(span / 1000))
    return (f"warning: the meshes span {span:.4g} units, taken as millimetres (no --units): a {span:.4g} mm subject; "
            f"if they are in another unit, give it (--units {other[0]}: {other[1]}); the files written carry it "
            "(the GLB is in metres)")


def assumed_units(vertices) -> str:
    """The units of a mesh sequence given none (:data:`MESH_UNITS_DEFAULT`), said when its first frame's span
    (``vertices``, (V, 3)) makes them unlikely (:func:`units_warning`)."""
    import numpy as np

    V = np.asarray(vertices, dtype=np.float64)
    hint = units_warning(float((V.max(axis=0) - V.min(axis=0)).max())) if len(V) else None
    if hint:
        print(hint)
    return MESH_UNITS_DEFAULT
