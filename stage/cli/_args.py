"""Argument parsers shared by the ``stage`` subcommands and benchmarks."""

from __future__ import annotations

__all__ = ["parse_size"]


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
