"""Board detection in images, and the choice of which views to keep.

Chessboards: ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix`` (the classic
detector: its corners reproduce OpenCV's published calibrations), falling back
to ``cv2.findChessboardCornersSB`` (Duda & Frese 2018) when it fails. The corner
order is made canonical (the board frame of :mod:`calib.boards`) from the
colours of the squares, so every camera numbers the corners the same way; this
needs ``cols + rows`` odd (e.g. 9 x 6 inner corners), otherwise a chessboard is
180-degree symmetric and only usable for intrinsics.

ChArUco: ``cv2.aruco.CharucoDetector`` (corner ids are unique).

Boards printed inverted (white on black) are detected on the inverted image.
Cameras that deliver mirrored images (the "mirror" mode of many webcams) are
detected on the image flipped left-right (``mirror=True``): the corners are then
pixels of the flipped, true image, which is what such a camera's calibration
describes. :func:`board_variants` finds out which of these a camera needs when
the board is never found.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from dataclasses import dataclass, field
from typing import Iterable, Iterator, Sequence

import numpy as np

from calib.boards import Board, Charuco, Chessboard

__all__ = ["Detection", "detect_board", "select_views", "default_min_corners", "to_gray", "board_variants",
           "find_variant"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Detection:
    """Board corners found in one image.

    Parameters
    ----------
    ids : (N,) int ndarray
        Row indices into ``board.object_points()``.
    corners : (N, 2) float ndarray
        Pixel coordinates (integer = pixel centre).
    frame : int
        Frame / image index in its sequence (``-1`` when unknown).
    """

    ids: np.ndarray
    corners: np.ndarray
    frame: int = -1
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        c = np.asarray(self.corners, dtype=np.float64).reshape(-1, 2)
        if ids.shape[0] != c.shape[0]:
            raise ValueError(f"ids ({ids.shape[0]}) and corners ({c.shape[0]}) must have the same length")
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "corners", c)
        object.__setattr__(self, "frame", int(self.frame))

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def with_frame(self, frame: int) -> "Detection":
        return Detection(self.ids, self.corners, frame, dict(self.meta))

    def to_dict(self) -> dict:
        return {"frame": self.frame, "ids": self.ids.tolist(), "corners": self.corners.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Detection":
        return cls(ids=np.asarray(d["ids"]), corners=np.asarray(d["corners"]), frame=int(d.get("frame", -1)))


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey image from (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA uint8/uint16."""
    import cv2

    img = np.asarray(image)
    if img.ndim not in (2, 3) or img.size == 0 or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
        raise ValueError(f"image must be an (H, W) or (H, W, 3) array, got shape {img.shape}")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        if np.issubdtype(img.dtype, np.floating) and img.size and np.nanmax(img) <= 1.0:
            img = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
        else:
            raise ValueError(f"image must be uint8 (or uint16 / float in [0, 1]), got {img.dtype}")
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    return np.ascontiguousarray(img)


def default_min_corners(board: Board) -> int:
    """Corners a view needs to be useful: all of a chessboard; a quarter (>= 6) of a ChArUco board."""
    if isinstance(board, Chessboard):
        return board.n_corners
    return max(6, int(np.ceil(board.n_corners / 4)))


# -- chessboards ---------------------------------------------------------------------------


def _sample(gray: np.ndarray, pts: np.ndarray) -> np.ndarray:
    import cv2

    h, w = gray.shape
    x = np.clip(np.round(pts[:, 0]).astype(int), 0, w - 1)
    y = np.clip(np.round(pts[:, 1]).astype(int), 0, h - 1)
    blur = cv2.blur(gray, (3, 3))
    return blur[y, x].astype(np.float64)


def _canonical_chessboard(gray: np.ndarray, corners: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """Reorder detected corners into the board frame of :class:`~calib.boards.Chessboard`.

    Handedness first (the print is seen from the front, so board ``x`` then ``y`` turn
    clockwise in the image), then the 180-degree ambiguity from the square colours:
    the square whose top-left corner is corner ``(j, i)`` is black when ``i + j`` is even.
    """
    c, r = grid
    g = corners.reshape(r, c, 2)
    dx = g[0, -1] - g[0, 0]
    dy = g[-1, 0] - g[0, 0]
    if dx[0] * dy[1] - dx[1] * dy[0] < 0:
        g = g[:, ::-1]
    if (c + r) % 2 == 1:
        centres = 0.25 * (g[:-1, :-1] + g[1:, :-1] + g[:-1, 1:] + g[1:, 1:])
        jj, ii = np.meshgrid(np.arange(c - 1), np.arange(r - 1))
        black = ((ii + jj) % 2 == 0).ravel()
        val = _sample(gray, centres.reshape(-1, 2))
        if black.any() and (~black).any() and val[black].mean() > val[~black].mean():
            g = g[::-1, ::-1]
    return g.reshape(-1, 2)


def _subpix_window(corners: np.ndarray, grid: tuple[int, int]) -> int:
    c, r = grid
    g = corners.reshape(r, c, 2)
    d = []
    if c > 1:
        d.append(np.linalg.norm(np.diff(g, axis=1), axis=2).min())
    if r > 1:
        d.append(np.linalg.norm(np.diff(g, axis=0), axis=2).min())
    spacing = float(min(d)) if d else 20.0
    return int(np.clip(np.floor(spacing * 0.45), 2, 11))


def _detect_chessboard(gray: np.ndarray, board: Chessboard, method: str, window: int | None) -> np.ndarray | None:
    import cv2

    pattern = board.corners
    corners = None
    if method in ("auto", "classic"):
        scale = 1.0
        small = gray
        if max(gray.shape) > 1600:
            scale = 1600.0 / max(gray.shape)
            small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
        ok, c = cv2.findChessboardCorners(small, pattern, flags=flags)
        if ok:
            c = (c.reshape(-1, 2) + 0.5) / scale - 0.5
            win = _subpix_window(c, pattern) if window is None else window
            c = cv2.cornerSubPix(
                gray, c.astype(np.float32).reshape(-1, 1, 2), (win, win), (-1, -1),
                (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01),
            )
            corners = c.reshape(-1, 2).astype(np.float64)
    if corners is None and method in ("auto", "sb"):
        ok, c = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        if ok:
            corners = c.reshape(-1, 2).astype(np.float64)
    if corners is None:
        return None
    return _canonical_chessboard(gray, corners, pattern)


# -- ChArUco ---------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _charuco_detector(board: Charuco):
    import cv2

    cv_board = board.to_cv()
    cparams = cv2.aruco.CharucoParameters()
    dparams = cv2.aruco.DetectorParameters()
    dparams.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.CharucoDetector(cv_board, cparams, dparams), cv_board


def _detect_charuco(gray: np.ndarray, board: Charuco) -> tuple[np.ndarray, np.ndarray] | None:
    det, cv_board = _charuco_detector(board)
    cc, ids, _, _ = det.detectBoard(gray)
    if ids is None or len(ids) < 4:
        return None
    ids = ids.ravel().astype(np.int64)
    if cv_board.checkCharucoCornersCollinear(ids.reshape(-1, 1).astype(np.int32)):
        return None
    return ids, cc.reshape(-1, 2).astype(np.float64)


# -- public ------------------------------------------------------------------------------------


def detect_board(
    image: np.ndarray,
    board: Board,
    *,
    frame: int = -1,
    method: str = "auto",
    min_corners: int | None = None,
    subpix_window: int | None = None,
    mirror: bool = False,
) -> Detection | None:
    """Find the board in one image.

    Parameters
    ----------
    image : (H, W, 3) BGR or (H, W) grey uint8 ndarray
    board : Chessboard or Charuco
    frame : int, optional
        Stored in the detection.
    method : {"auto", "classic", "sb"}
        Chessboards only: classic detector + ``cornerSubPix``, the sector-based
        detector, or classic with SB as fallback.
    subpix_window : int, optional
        Half size of the ``cornerSubPix`` window (OpenCV's samples use 11); by
        default 45% of the smallest corner spacing, at most 11, so the window
        never reaches past the neighbouring corners on small or tilted boards.
    min_corners : int, optional
        Fewer corners than this count as "not found" (default
        :func:`default_min_corners`).
    mirror : bool, optional
        The camera delivers mirrored images: detect on the image flipped
        left-right; corners are pixels of the flipped image.

    Returns
    -------
    Detection or None
        ``None`` when the board is not found (or too little of it).
    """
    if not isinstance(board, (Chessboard, Charuco)):
        raise ValueError(f"board must be a Chessboard or Charuco, got {type(board).__name__}")
    if method not in ("auto", "classic", "sb"):
        raise ValueError(f"method must be 'auto', 'classic' or 'sb', got {method!r}")
    gray = to_gray(image)
    if mirror:
        gray = np.ascontiguousarray(gray[:, ::-1])
    if board.inverted:
        gray = 255 - gray
    need = default_min_corners(board) if min_corners is None else int(min_corners)
    if need < 1:
        raise ValueError(f"min_corners must be >= 1, got {min_corners!r}")
    if isinstance(board, Chessboard):
        if subpix_window is not None and int(subpix_window) < 1:
            raise ValueError(f"subpix_window must be >= 1, got {subpix_window!r}")
        c = _detect_chessboard(gray, board, method, subpix_window)
        if c is None:
            return None
        ids = np.arange(board.n_corners)
    else:
        found = _detect_charuco(gray, board)
        if found is None:
            return None
        ids, c = found
    if len(ids) < need:
        return None
    return Detection(ids=ids, corners=c, frame=frame)


def view_change(a: Detection, b: Detection, size: tuple[int, int]) -> float:
    """How different two views of the board are, as a fraction of the image diagonal.

    The median displacement of the corners both views share; ``inf`` when they
    share fewer than half of the corners of the smaller view.
    """
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if len(common) < 0.5 * min(len(a), len(b)) or len(common) == 0:
        return float("inf")
    d = np.linalg.norm(a.corners[ia] - b.corners[ib], axis=1)
    return float(np.median(d) / np.hypot(*size))


def select_views(
    detections: Sequence[Detection | None],
    *,
    size: tuple[int, int],
    min_corners: int = 4,
    min_change: float = 0.02,
) -> list[int]:
    """Indices of the views worth keeping from a sequence (e.g. video frames).

    A view is kept when it has at least ``min_corners`` corners and moved by more
    than ``min_change`` of the image diagonal (median corner displacement) since
    the last kept view.

    Parameters
    ----------
    detections : sequence of Detection or None
    size : (int, int)
        Image ``(width, height)``.
    min_corners : int
    min_change : float
        Fraction of the image diagonal, ``>= 0`` (0 keeps every detection).

    Returns
    -------
    list of int
        Positions in ``detections``.
    """
    if len(size) != 2 or min(size) <= 0:
        raise ValueError(f"size must be (width, height) > 0, got {size!r}")
    if min_change < 0 or not np.isfinite(min_change):
        raise ValueError(f"min_change must be >= 0, got {min_change!r}")
    if min_corners < 1:
        raise ValueError(f"min_corners must be >= 1, got {min_corners!r}")
    keep: list[int] = []
    last: Detection | None = None
    for i, d in enumerate(detections):
        if d is None or len(d) < min_corners:
            continue
        if last is None or view_change(d, last, size) > min_change:
            keep.append(i)
            last = d
    return keep


def detect_sequence(
    images: Iterable[np.ndarray], board: Board, *, method: str = "auto", min_corners: int | None = None
) -> Iterator[Detection | None]:
    """Detect the board in every image of a sequence (frame = position)."""
    for i, img in enumerate(images):
        yield detect_board(img, board, frame=i, method=method, min_corners=min_corners)


def board_variants(board: Board) -> list[tuple[str, Board, bool]]:
    """The ways a board file or a camera may differ from the print: ``(description, board, mirror)``.

    Mirrored images first (a camera setting), then the board's ``inverted`` and
    ChArUco ``legacy`` flags flipped, alone and with the mirror; for a chessboard also
    the squares given instead of the inner corners (one fewer each way).
    """
    mirrors = (False,) if isinstance(board, Chessboard) else (False, True)  # a chessboard looks the same mirrored
    out: list[tuple[str, Board, bool]] = [("mirrored images", board, True)] if True in mirrors else []
    flips = [dataclasses.replace(board, inverted=not board.inverted)]
    if isinstance(board, Charuco):
        flips.append(dataclasses.replace(board, legacy=not board.legacy))
        flips.append(dataclasses.replace(board, inverted=not board.inverted, legacy=not board.legacy))
    elif min(board.corners) > 2:
        flips.append(dataclasses.replace(board, corners=(board.corners[0] - 1, board.corners[1] - 1)))
    for b in flips:
        desc = ", ".join(_board_value(k, getattr(b, k)) for k in ("corners", "inverted", "legacy") if hasattr(b, k)
                         and getattr(b, k) != getattr(board, k))
        out += [(f"board file with {desc}" + (" and mirrored images" if m else ""), b, m) for m in mirrors]
    return out


def _board_value(key: str, value) -> str:
    """``key = value`` as written in a board file."""
    if isinstance(value, tuple):
        return f"{key} = [{', '.join(str(v) for v in value)}]"
    return f"{key} = {str(value).lower()}"


def find_variant(images: Sequence[np.ndarray], board: Board, *, min_found: int = 2):
    """Which variant of :func:`board_variants` finds the board in ``images`` (a few evenly spaced
    frames of one camera).

    The variants are tried in order and the first that finds the board in ``min_found`` images
    (or in all of them, when fewer) is returned: a wrong board file costs one failed detection per
    image and variant, so keep ``images`` few.

    Returns
    -------
    (description, board, mirror, found) or None
        ``found``: in how many of ``images`` that variant found the board.
    """
    need = min(int(min_found), len(images))
    if need < 1:
        return None
    for desc, b, mirror in board_variants(board):
        found = 0
        for i, img in enumerate(images):
            found += detect_board(img, b, mirror=mirror) is not None
            if found + len(images) - 1 - i < need:
                break  # this variant can no longer reach need
        if found >= need:
            return desc, b, mirror, found
    return None
