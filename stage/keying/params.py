"""Keying parameters and results (value objects, no algorithms)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, Literal

import numpy as np

from calib.fileio import plain

__all__ = ["KEY_MODES", "KEY_LAYERS", "FILL_HOLES", "PLATE_CLOSE_RELATIVE", "KeyMode", "KeyParams", "KeyResult", "KeyingError"]

KeyMode = Literal["chroma", "luma", "plate"]
KEY_MODES: tuple[str, ...] = ("chroma", "luma", "plate")
FILL_HOLES: tuple[str, ...] = ("uncertain", "small", "enclosed", "none")
#: The plate mode's closing radius, as a fraction of the subject's extent in the image (see
#: :attr:`KeyParams.close_relative`): gaps up to about 6 % of the subject (a limb's width) close.
PLATE_CLOSE_RELATIVE = 0.03
#: Layers combinable with any mode: ``volume`` (pixels whose rays miss the capture volume are
#: background, :mod:`stage.keying.volume_prior`), ``graphcut`` (a per-camera graph cut seeded by
#: the keyer's sure background and a first hull's projection, :mod:`pipeline.silhouette_refine`).
KEY_LAYERS: tuple[str, ...] = ("volume", "graphcut")


class KeyingError(ValueError):
    """Valid input from which no backdrop model can be estimated (e.g. no backdrop in any frame)."""


@dataclass(frozen=True)
class KeyParams:
    """Options of the keyer; ``None`` means "derive from the data".

    After keying, :attr:`KeyResult.params` holds a copy with every derived value
    filled in (thresholds, backdrop model), so the masks can be reproduced.

    Parameters
    ----------
    mode : {"chroma", "luma", "plate"}
        ``chroma``: distance to the backdrop's chroma, shading-invariant (green/blue
        screens). ``luma``: brightness against a dark (or bright) backdrop.
        ``plate``: difference from a clean background plate (Horprasert et al. 1999).
    t_lo, t_hi : float or None
        Soft-matte thresholds on the backdrop distance, in units of the backdrop's
        own robust spread (standard deviations). Below ``t_lo`` a pixel is backdrop
        (matte 0), above ``t_hi`` it is solid foreground (matte 1). Default: the
        radii holding all but 1e-3 and 1e-6 of a Gaussian backdrop
        (chi-square quantiles; 2 degrees of freedom for chroma, 1 for luma and plate).
    backdrop_color : str or None
        Hint for the chroma mode ("green", "blue", ...): only hues within 60 degrees of
        it are considered as the backdrop. ``None`` = the dominant saturated hue.
    polarity : {"dark", "bright"} or None
        Luma mode: backdrop darker or brighter than the subject. ``None`` = the
        class that covers the image border.
    shadow_floor : float
        Plate mode: darkest shadow still accepted as backdrop, as a fraction of the
        plate's brightness (chroma mode needs none: it compares chroma at the
        pixel's own brightness).
    min_area : float
        Foreground components smaller than this fraction of the image are dropped
        (and backdrop holes smaller than it are filled, see ``fill_holes``).
    min_relative_area : float or None
        Foreground components smaller than this fraction of the frame's largest one are
        dropped. ``None``: 0.02 in plate mode (without a backdrop, the small changes of a
        room are noise beside the subject), 0 otherwise.
    fill_holes : {"uncertain", "small", "enclosed", "none"} or None
        Holes below ``min_area``: ``uncertain`` fills those whose pixels do not match
        the backdrop (median distance >= ``t_lo``) and leaves gaps of clean backdrop
        colour open (a slit between legs, between arm and torso); ``small`` fills
        every small hole (safest for the hull when the subject has backdrop-coloured
        patches); ``enclosed`` fills every hole the silhouette encloses, whatever its
        size; ``none`` fills nothing. ``None``: ``uncertain`` in the chroma mode (a
        subject rarely has the backdrop's hue), ``small`` in the luma mode (a shadow on
        the subject is as dark as a black backdrop), ``enclosed`` in the plate mode
        (see ``close_relative``).
    close_radius : int
        Radius in pixels of the morphological closing applied to the final mask
        (0 = none). Closing never removes thin limbs; opening is not used.
    close_relative : float or None
        Radius of a closing after the components are chosen, as a fraction of the
        subject's extent in the image (the larger side of the largest component's
        bounding box). ``None``: :data:`PLATE_CLOSE_RELATIVE` in the plate mode, 0
        otherwise. Without a backdrop the subject's own colours match what lies behind
        it somewhere (skin before a pale wall, dark clothes before a dark machine), so
        the plate keyer leaves holes and notches inside the subject; in a visual hull a
        hole in one camera's silhouette removes the subject for every camera, while a
        gap closed wrongly is carved away by the cameras that see through it. The plate
        mode closes gaps narrower than about a limb's width (twice the radius) and fills
        the holes the silhouette encloses.
    grow : int
        Dilate the final mask by this many pixels (conservative silhouettes).
    coverage_window : int
        Side of the window in which a pixel is compared with its local solid
        foreground: a boundary pixel is foreground when its backdrop distance is at
        least ``coverage_fraction`` of the local maximum (mixed pixels are linear in
        their coverage, so 0.5 is the pixel-centre rule for box-filtered edges).
    coverage_fraction : float or None
        ``None``: estimated per camera from the edge statistics (optical blur and
        spill move it below 0.5), see :func:`stage.keying.cleanup.estimate_coverage_fraction`.
    min_backdrop_fraction, max_foreground_fraction : float
        A frame is invalid when fewer than ``min_backdrop_fraction`` of its pixels
        match the backdrop, or when more than ``max_foreground_fraction`` are keyed
        as foreground (subject fills the image).
    black_level : float
        A frame whose 99.5th-percentile luma is below this is invalid (black frame).
    sample_stride : int
        Pixel stride used when sampling frames to estimate the backdrop model.
    model : dict or None
        The estimated backdrop model (filled in by the keyer; passing one skips estimation).
    """

    mode: KeyMode = "chroma"
    t_lo: float | None = None
    t_hi: float | None = None
    backdrop_color: str | None = None
    polarity: Literal["dark", "bright"] | None = None
    shadow_floor: float = 0.35
    min_area: float = 2e-4
    min_relative_area: float | None = None
    fill_holes: Literal["uncertain", "small", "none"] | None = None
    close_radius: int = 0
    close_relative: float | None = None
    grow: int = 0
    coverage_window: int = 3
    coverage_fraction: float | None = None
    min_backdrop_fraction: float = 0.02
    max_foreground_fraction: float = 0.85
    black_level: float = 12.0
    sample_stride: int = 4
    model: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        self._check_choices()
        self._check_thresholds()
        self._check_counts()
        self._check_fractions()

    def _check_choices(self) -> None:
        if self.mode not in KEY_MODES:
            raise ValueError(f"mode must be one of {KEY_MODES}, got {self.mode!r}")
        if self.polarity not in (None, "dark", "bright"):
            raise ValueError(f"polarity must be 'dark', 'bright' or None, got {self.polarity!r}")

    def _check_thresholds(self) -> None:
        for name in ("t_lo", "t_hi"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number or None, got {v!r}")
        if self.t_lo is not None and self.t_hi is not None and not self.t_hi > self.t_lo:
            raise ValueError(f"t_hi ({self.t_hi}) must be greater than t_lo ({self.t_lo})")
        if not 0 < self.shadow_floor < 1:
            raise ValueError(f"shadow_floor must be in (0, 1), got {self.shadow_floor!r}")
        if self.fill_holes is not None and self.fill_holes not in FILL_HOLES:
            raise ValueError(f"fill_holes must be one of {FILL_HOLES} or None, got {self.fill_holes!r}")
        if not 0 <= self.min_area < 0.5:
            raise ValueError(f"min_area must be in [0, 0.5), got {self.min_area!r}")
        if self.close_relative is not None and not (np.isfinite(self.close_relative) and 0 <= self.close_relative < 0.5):
            raise ValueError(f"close_relative must be in [0, 0.5) or None, got {self.close_relative!r}")
        if self.min_relative_area is not None and not 0 <= self.min_relative_area < 1:
            raise ValueError(f"min_relative_area must be in [0, 1) or None, got {self.min_relative_area!r}")

    def _check_counts(self) -> None:
        for name in ("close_radius", "grow", "sample_stride", "coverage_window"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 0:
                raise ValueError(f"{name} must be a non-negative integer, got {v!r}")
        if self.sample_stride < 1:
            raise ValueError("sample_stride must be >= 1")
        if self.coverage_window < 1 or self.coverage_window % 2 == 0:
            raise ValueError(f"coverage_window must be a positive odd integer, got {self.coverage_window!r}")

    def _check_fractions(self) -> None:
        if self.coverage_fraction is not None and not 0 < self.coverage_fraction <= 1:
            raise ValueError(f"coverage_fraction must be in (0, 1] or None, got {self.coverage_fraction!r}")
        if not 0 <= self.min_backdrop_fraction < 1:
            raise ValueError(f"min_backdrop_fraction must be in [0, 1), got {self.min_backdrop_fraction!r}")
        if not 0 < self.max_foreground_fraction <= 1:
            raise ValueError(f"max_foreground_fraction must be in (0, 1], got {self.max_foreground_fraction!r}")
        if not self.black_level >= 0:
            raise ValueError(f"black_level must be >= 0, got {self.black_level!r}")

    def replace(self, **kw: Any) -> "KeyParams":
        """A copy with some fields changed (validated again)."""
        return replace(self, **kw)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serializable dict (numpy values converted to lists/floats)."""
        return plain(asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "KeyParams":
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError`` naming them."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"KeyParams: unknown keys {unknown}")
        return cls(**data)


@dataclass(frozen=True, eq=False)
class KeyResult:
    """Masks of one camera's frames.

    Attributes
    ----------
    masks : (N, H, W) bool ndarray
        Foreground silhouettes (all ``False`` in invalid frames).
    matte : (N, H, W) uint8 ndarray
        Soft matte, 0 = backdrop .. 255 = solid foreground (linear between ``t_lo`` and ``t_hi``).
    valid : (N,) bool ndarray
        Whether each frame's mask can be trusted.
    reasons : list of str
        Why a frame is invalid ("" for valid frames).
    params : KeyParams
        The parameters used, with every derived value filled in.
    stats : list of dict
        Per-frame figures (foreground and backdrop fractions, components dropped).
    """

    masks: np.ndarray
    matte: np.ndarray
    valid: np.ndarray
    reasons: list[str]
    params: KeyParams
    stats: list[dict[str, float]] = field(default_factory=list)
