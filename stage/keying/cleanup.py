"""From a backdrop-distance image to a clean silhouette.

1. *Soft matte*: linear between the thresholds ``t_lo`` (backdrop) and ``t_hi``
   (solid foreground).
2. *Coverage rule*: for a pixel mixing subject and backdrop the residual distance
   is proportional to its coverage, so a candidate pixel must reach half of the
   local maximum distance (a ``coverage_window`` square): the mask edge sits at 50 %
   coverage whatever the subject's colour, and thin limb tips survive.
3. *Hysteresis* (Canny 1986): candidate components (distance >= ``t_lo``) are kept
   only if they contain a solid pixel (distance >= ``t_hi``) and are not smaller
   than ``min_area`` of the image; backdrop holes below that size are filled
   unless they have the backdrop's own colour (a gap between legs stays open).
4. Optional closing (never opening, which would cut limb tips): by a radius in pixels, and by
   one relative to the subject's extent in the image (the plate mode's default: gaps narrower
   than about a limb's width close, see :attr:`stage.keying.params.KeyParams.close_relative`),
   then the holes the silhouette encloses may be filled (``fill_holes="enclosed"``); growing.
"""

from __future__ import annotations

import cv2
import numpy as np

from stage.keying.params import FILL_HOLES

__all__ = ["soft_matte", "mask_from_distance"]


def soft_matte(distance: np.ndarray, *, t_lo: float, t_hi: float) -> np.ndarray:
    """(H, W) uint8 matte: 0 at ``distance <= t_lo``, 255 at ``distance >= t_hi``, linear between."""
    scale = 255.0 / (t_hi - t_lo)
    return cv2.addWeighted(distance, scale, distance, 0.0, -t_lo * scale, dtype=cv2.CV_8U)


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _select_labels(labels: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Boolean mask of the pixels whose label is in ``keep`` (label ids)."""
    if keep.size == 0:
        return np.zeros(labels.shape, bool)
    if keep.size <= 4:  # OpenCV compares release the GIL (worker threads scale)
        out = cv2.compare(labels, float(keep[0]), cv2.CMP_EQ)
        for k in keep[1:]:
            out = cv2.bitwise_or(out, cv2.compare(labels, float(k), cv2.CMP_EQ))
        # OpenCV's 0/255 must become 0/1 before viewing it as bool: a NumPy bool holding the
        # byte 255 tests True but counts as 255 wherever its bytes are read as uint8 (summed-area
        # tables, cv2 sums), e.g. the hull carver's coarse-to-fine block counts
        return cv2.bitwise_and(out, 1).view(bool)
    lut = np.zeros(int(labels.max()) + 1, bool)
    lut[keep] = True
    return lut[labels]


def _close_relative(mask: np.ndarray, labels: np.ndarray, largest: int, fraction: float, distance: np.ndarray,
                    t_doubt: float) -> np.ndarray:
    """``mask`` closed by a disc of ``fraction`` times the larger side of component ``largest``'s
    bounding box (at least one pixel), on a padded region around the mask (the image border
    neither opens nor closes anything); a pixel the closing adds is kept where its distance is
    at least ``t_doubt``."""
    x, y, bw, bh = cv2.boundingRect(cv2.compare(labels, float(largest), cv2.CMP_EQ))
    r = max(1, int(round(fraction * max(bw, bh))))
    x, y, bw, bh = cv2.boundingRect(mask.view(np.uint8))
    h, w = mask.shape
    x0, y0, x1, y1 = max(0, x - r), max(0, y - r), min(w, x + bw + r), min(h, y + bh + r)
    roi = cv2.copyMakeBorder(np.ascontiguousarray(mask[y0:y1, x0:x1]).view(np.uint8), r, r, r, r,
                             cv2.BORDER_CONSTANT, value=0)
    closed = cv2.morphologyEx(roi, cv2.MORPH_CLOSE, _disk(r))[r:-r, r:-r].view(bool)
    out = mask.copy()
    out[y0:y1, x0:x1] |= closed & (distance[y0:y1, x0:x1] >= t_doubt)
    return out


def _fill_enclosed(mask: np.ndarray, distance: np.ndarray, t_doubt: float) -> tuple[np.ndarray, int]:
    """Every hole of ``mask`` that it encloses (background not connected to the image's border,
    4-connected) filled, unless the hole's median distance is below ``t_doubt`` (backdrop seen
    through a gap)."""
    x, y, bw, bh = cv2.boundingRect(mask.view(np.uint8))
    roi = np.ascontiguousarray(mask[y : y + bh, x : x + bw])
    n, lab = cv2.connectedComponents((~roi).view(np.uint8), connectivity=4, ltype=cv2.CV_32S)
    if n <= 1:
        return mask, 0
    inner = np.ones(n, bool)
    inner[np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))] = False
    inner[0] = False  # label 0: the silhouette itself
    if inner.any() and t_doubt > 0:
        sel = inner[lab]
        labs, vals = lab[sel], distance[y : y + bh, x : x + bw][sel]
        order = np.lexsort((vals, labs))  # by hole, then by distance: medians by index
        labs, vals = labs[order], vals[order]
        cand = np.flatnonzero(inner)
        starts, ends = np.searchsorted(labs, cand), np.searchsorted(labs, cand, side="right")
        med = 0.5 * (vals[(starts + ends - 1) // 2] + vals[(starts + ends) // 2])
        inner[cand[med < t_doubt]] = False
    if not inner.any():
        return mask, 0
    out = mask.copy()
    out[y : y + bh, x : x + bw] |= _select_labels(lab, np.flatnonzero(inner).astype(np.int32))
    return out, int(inner.sum())


def mask_from_distance(
    distance: np.ndarray,
    *,
    t_lo: float,
    t_hi: float,
    min_area: float,
    close_radius: int = 0,
    grow: int = 0,
    coverage_window: int = 3,
    coverage_fraction: float = 0.5,
    fill_holes: str = "uncertain",
    min_relative_area: float = 0.0,
    close_relative: float = 0.0,
    t_doubt: float = 0.0,
) -> tuple[np.ndarray, dict[str, float]]:
    """Silhouette from a backdrop-distance image.

    Parameters
    ----------
    distance : (H, W) float32 ndarray
        Backdrop distance in units of the backdrop spread (0 = backdrop).
    t_lo, t_hi : float
        Candidate and solid thresholds.
    min_area : float
        Minimum component (and hole) size as a fraction of the image.
    close_radius, grow : int
        Closing radius and final dilation in pixels.
    coverage_window : int
        Odd window side for the 50 %-coverage rule (1 disables it).
    coverage_fraction : float
        Fraction of the local maximum a boundary pixel must reach.
    fill_holes : {"uncertain", "small", "enclosed", "none"}
        Which backdrop holes inside the subject are filled: of those smaller than
        ``min_area``, ``uncertain`` those whose median distance is at least ``t_lo``
        (mixed or doubtful pixels; a hole of clean backdrop colour is a gap the camera
        sees through), ``small`` all of them; ``enclosed`` every hole the silhouette
        encloses, whatever its size, whose median distance is at least ``t_doubt``; ``none`` none.
    min_relative_area : float
        Components smaller than this fraction of the largest kept one are dropped too.
    close_relative : float
        Radius of a closing of the chosen components, as a fraction of the larger side of
        the largest one's bounding box (0 = none; at least one pixel otherwise); it adds only
        pixels whose distance is at least ``t_doubt``.
    t_doubt : float
        The distance below which a pixel is backdrop within its noise, seen through a gap
        (the relative closing and the ``enclosed`` holes leave it open).

    Returns
    -------
    mask : (H, W) bool ndarray
    stats : dict
        ``components_dropped``, ``holes_filled``.
    """
    if fill_holes not in FILL_HOLES:
        raise ValueError(f"fill_holes must be one of {FILL_HOLES}, got {fill_holes!r}")
    h, w = distance.shape
    min_px = max(1, int(round(min_area * h * w)))
    cand8, seeds8 = _candidates(distance, t_lo=t_lo, t_hi=t_hi, close_radius=close_radius,
                                coverage_window=coverage_window, coverage_fraction=coverage_fraction)
    n, labels, area, keep = _kept_components(cand8, seeds8, min_px=min_px, min_relative_area=min_relative_area)
    dropped = int(n - 1 - keep.size)
    mask = _select_labels(labels, keep)
    if close_relative > 0 and keep.size:
        mask = _close_relative(mask, labels, int(keep[np.argmax(area[keep])]), close_relative, distance, t_doubt)
    holes = 0
    if fill_holes == "enclosed" and keep.size:
        mask, holes = _fill_enclosed(mask, distance, t_doubt)
    elif fill_holes != "none" and keep.size and min_px > 1:
        holes = _fill_small_holes(mask, distance, min_px=min_px, uncertain_only=fill_holes == "uncertain", t_lo=t_lo)
    if grow > 0:
        mask = cv2.dilate(mask.view(np.uint8), _disk(grow)).view(bool)
    return mask, {"components_dropped": float(dropped), "holes_filled": float(holes)}


def _candidates(distance: np.ndarray, *, t_lo: float, t_hi: float, close_radius: int, coverage_window: int,
                coverage_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """The candidate pixels (distance >= ``t_lo``, the coverage rule, the closing) and, among
    them, the solid seeds (distance >= ``t_hi``), both (H, W) uint8 0/255.

    OpenCV comparisons (uint8 0/255, no GIL) rather than NumPy boolean arrays.
    """
    cand8 = cv2.compare(distance, float(t_lo), cv2.CMP_GE)
    if coverage_window > 1:
        local = cv2.dilate(distance, np.ones((coverage_window, coverage_window), np.uint8))
        cand8 = cv2.bitwise_and(cand8, cv2.compare(distance, cv2.multiply(local, float(coverage_fraction)), cv2.CMP_GE))
    if close_radius > 0:
        cand8 = cv2.morphologyEx(cand8, cv2.MORPH_CLOSE, _disk(close_radius))
    seeds8 = cv2.bitwise_and(cand8, cv2.compare(distance, float(t_hi), cv2.CMP_GE))
    return cand8, seeds8


def _kept_components(cand8: np.ndarray, seeds8: np.ndarray, *, min_px: int,
                     min_relative_area: float) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """Hysteresis: the candidate components that hold a seed and are large enough.

    Returns the number of labels (background included), the (H, W) int32 labels, the area of
    each label (a single 0 when there is no component) and the kept label ids (int32).
    Labels are found without stats (the stats pass costs more than the labelling itself);
    areas and seed counts come from the candidates' bounding box only.
    """
    n, labels = cv2.connectedComponents(cand8, connectivity=8, ltype=cv2.CV_32S)
    area = np.zeros(1, np.int64)
    if n > 1:
        x, y, bw, bh = cv2.boundingRect(cand8)
        lab_roi = labels[y : y + bh, x : x + bw]
        area = np.bincount(lab_roi.ravel(), minlength=n)
        seeds = np.bincount(lab_roi[seeds8[y : y + bh, x : x + bw] != 0], minlength=n)
        ok = (area >= min_px) & (seeds > 0)
        ok[0] = False
        if min_relative_area > 0 and ok.any():
            ok &= area >= min_relative_area * area[ok].max()
    else:
        ok = np.zeros(1, bool)
    return n, labels, area, np.flatnonzero(ok).astype(np.int32)


def _fill_small_holes(mask: np.ndarray, distance: np.ndarray, *, min_px: int, uncertain_only: bool,
                      t_lo: float) -> int:
    """Fill, in place, the backdrop holes of ``mask`` smaller than ``min_px`` pixels that do not
    touch its bounding box's border; with ``uncertain_only`` only those whose median distance
    is at least ``t_lo``. Returns how many holes were filled."""
    x, y, bw, bh = cv2.boundingRect(mask.view(np.uint8))
    roi = mask[y : y + bh, x : x + bw]
    n2, lab2 = cv2.connectedComponents((~roi).view(np.uint8), connectivity=4, ltype=cv2.CV_32S)
    if n2 <= 1:
        return 0
    area2 = np.bincount(lab2[~roi], minlength=n2)
    border = np.unique(np.concatenate([lab2[0], lab2[-1], lab2[:, 0], lab2[:, -1]]))
    small = area2 < min_px
    small[0] = False
    small[border] = False
    if uncertain_only and small.any():
        # a hole of backdrop colour (median distance below t_lo) is backdrop seen
        # through a gap (between legs, arm and torso); only holes the model is unsure
        # of (mixed pixels, specks the coverage rule rejected) are subject
        cand = np.flatnonzero(small)
        small[cand[_median_distances(lab2, distance[y : y + bh, x : x + bw], cand) < t_lo]] = False
    fill = np.flatnonzero(small).astype(np.int32)
    if fill.size:
        roi |= _select_labels(lab2, fill)
    return int(fill.size)


def _median_distances(labels: np.ndarray, distance: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Median of ``distance`` over the pixels of each label in ``wanted`` (sorted label ids),
    in one pass (the holes are few and small)."""
    is_wanted = np.zeros(int(labels.max()) + 1, bool)
    is_wanted[wanted] = True
    sel = is_wanted[labels]
    labs, vals = labels[sel], distance[sel]
    order = np.lexsort((vals, labs))  # by label, then by distance: medians by index
    labs, vals = labs[order], vals[order]
    starts = np.searchsorted(labs, wanted)
    ends = np.searchsorted(labs, wanted, side="right")
    return 0.5 * (vals[(starts + ends - 1) // 2] + vals[(starts + ends) // 2])


def estimate_coverage_fraction(
    distances: list[np.ndarray], *, t_lo: float, t_hi: float, coverage_window: int, default: float = 0.5
) -> float:
    """The coverage rule's fraction, from the edge statistics of a few frames.

    Near a solid pixel (distance >= ``t_hi``) the ratio ``rho = distance / local
    max`` of the other pixels is bimodal: backdrop pixels that only pick up blur
    and bleeding from the subject (low ``rho``, set by the optics) and the
    subject's own pixels (high ``rho``, lowered by spill and shading). The
    fraction is the minimum of the smoothed ``rho`` histogram between the
    backdrop-side mode and 0.5 (Prewitt & Mendelsohn 1966); with ideal box-filter
    mixing there is no backdrop mode below 0.5 and the result is 0.5.

    Returns
    -------
    float
        In [0.1, 0.5]; ``default`` when the frames have too few edge pixels.
    """
    if coverage_window <= 1:
        return default
    bins = 40
    top = 0.6
    hist = np.zeros(bins)
    kernel = np.ones((coverage_window, coverage_window), np.uint8)
    for d in distances:
        local = cv2.dilate(d, kernel)
        sel = (d >= t_lo) & (local >= t_hi) & (d < local)
        rho = d[sel] / local[sel]
        rho = rho[rho < top]
        hist += np.bincount((rho / top * bins).astype(int), minlength=bins)[:bins]
    if hist.sum() < 100:
        return default
    from scipy.ndimage import gaussian_filter1d

    smooth = gaussian_filter1d(hist, 1.5, mode="nearest")
    centers = (np.arange(bins) + 0.5) / bins * top
    upto = int(np.searchsorted(centers, 0.5))
    # the backdrop-side mode: the first local maximum holding a fair share of the counts
    floor = 0.25 * smooth[:upto].max()
    mode = next(
        (i for i in range(1, upto) if smooth[i] >= floor and smooth[i] >= smooth[i - 1] and smooth[i] >= smooth[i + 1]),
        0,
    )
    valley = mode + int(np.argmin(smooth[mode : upto + 1]))
    return float(np.clip(centers[min(valley, bins - 1)], 0.1, 0.5))
