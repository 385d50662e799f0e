"""Contact sheets: frame, matte and overlay side by side, for a person to check masks at a glance."""

from __future__ import annotations

import cv2
import numpy as np

from stage.keying.params import KeyResult

__all__ = ["contact_sheet"]


def _label(img: np.ndarray, text: str, color: tuple[int, int, int] = (255, 255, 255)) -> None:
    cv2.putText(img, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, color, 1, cv2.LINE_AA)


def contact_sheet(
    frames: np.ndarray, result: KeyResult, *, rows: int = 6, width: int = 320, indices: np.ndarray | None = None
) -> np.ndarray:
    """One image per camera: for a few frames, the frame, its matte and the mask overlay.

    Parameters
    ----------
    frames : (N, H, W, 3) uint8 ndarray
        The keyed frames (BGR).
    result : KeyResult
        Their keying result.
    rows : int
        Frames shown (evenly spaced; invalid frames are always included first).
    width : int
        Width of each tile in pixels.
    indices : (N,) int ndarray or None
        Frame numbers to print on the tiles (default 0..N-1).

    Returns
    -------
    (R * h, 3 * width, 3) uint8 ndarray
        The overlay tints the foreground, outlines it in yellow and marks invalid
        frames in red with the reason.
    """
    n = frames.shape[0]
    if result.masks.shape[0] != n:
        raise ValueError(f"result has {result.masks.shape[0]} masks for {n} frames")
    if rows < 1 or width < 16:
        raise ValueError("rows must be >= 1 and width >= 16")
    idx_names = np.arange(n) if indices is None else np.asarray(indices)
    bad = [i for i in range(n) if not result.valid[i]]
    even = np.unique(np.linspace(0, n - 1, min(n, rows)).round().astype(int)).tolist()
    pick = sorted(set(bad[:rows]) | set(even[: max(0, rows - len(bad[:rows]))]))[:rows]
    h0, w0 = frames.shape[1:3]
    th = max(8, int(round(h0 * width / w0)))
    out_rows = []
    for i in pick:
        img = cv2.resize(frames[i], (width, th), interpolation=cv2.INTER_AREA)
        matte = cv2.cvtColor(cv2.resize(result.matte[i], (width, th), interpolation=cv2.INTER_AREA), cv2.COLOR_GRAY2BGR)
        m = cv2.resize(result.masks[i].view(np.uint8), (width, th), interpolation=cv2.INTER_NEAREST)
        over = img.copy()
        over[m == 0] = (over[m == 0] * 0.35).astype(np.uint8)
        contours, _ = cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(over, contours, -1, (0, 255, 255), 1)
        _label(img, f"frame {int(idx_names[i])}")
        _label(matte, "matte")
        if result.valid[i]:
            _label(over, f"mask {100 * result.masks[i].mean():.1f} %")
        else:
            cv2.line(over, (0, 0), (width - 1, th - 1), (0, 0, 255), 2)
            cv2.line(over, (width - 1, 0), (0, th - 1), (0, 0, 255), 2)
            _label(over, "INVALID: " + result.reasons[i][:60], (80, 80, 255))
        out_rows.append(np.hstack([img, matte, over]))
    return np.vstack(out_rows)
