"""Calibration boards: chessboards and ChArUco boards, as small value objects.

A board is described by the small TOML file users write by hand::

    type = "chessboard"
    corners = [9, 6]        # inner corners [cols, rows]
    square_mm = 25

    type = "charuco"
    squares = [4, 5]        # squares [cols, rows]
    square_mm = 54
    marker_mm = 40.5
    dictionary = "DICT_4X4_1000"
    legacy = false          # OpenCV's pre-4.6 ChArUco layout (setLegacyPattern)
    inverted = true         # printed white-on-black

caliscope's ``charuco.toml`` (``columns``, ``rows``, ``aruco_scale``,
``square_size_override_cm``, ``inverted``, ``legacy_pattern``...) reads as well.

Board frame
-----------
Corners lie in the plane ``z = 0``, in millimetres, ``x`` along the columns
(to the right in :meth:`image`), ``y`` along the rows (down in :meth:`image`),
so ``z`` points *into* the printed face. For a chessboard the origin is the
first inner corner (OpenCV's usual object points); for a ChArUco board it is the
outer top-left corner of the pattern and corner ``k`` is OpenCV's ChArUco
corner id ``k`` (``CharucoBoard.getChessboardCorners()``).

References: Zhang, "A flexible new technique for camera calibration", 1998/2000;
Garrido-Jurado et al., "Automatic generation and detection of highly reliable
fiducial markers under occlusion", 2014 (ArUco).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Union

import numpy as np

from calib import _toml

__all__ = [
    "BoardError",
    "Chessboard",
    "Charuco",
    "Board",
    "parse_board",
    "load_board",
    "save_board",
    "DICTIONARIES",
]


class BoardError(ValueError):
    """A board definition is invalid; the message names the offending key."""


def _dictionaries() -> dict[str, int]:
    import cv2

    return {k: int(getattr(cv2.aruco, k)) for k in dir(cv2.aruco) if k.startswith("DICT_")}


DICTIONARIES: tuple[str, ...] = tuple(sorted(_dictionaries()))


def _dictionary_size(name: str) -> int:
    import cv2

    d = cv2.aruco.getPredefinedDictionary(_dictionaries()[name])
    return int(d.bytesList.shape[0])


def _pair(data: dict, key: str, minimum: int, what: str) -> tuple[int, int]:
    v = data.get(key)
    ok = (
        isinstance(v, (list, tuple))
        and len(v) == 2
        and all(isinstance(x, (int, np.integer)) and not isinstance(x, bool) for x in v)
        and all(int(x) >= minimum for x in v)
    )
    if not ok:
        raise BoardError(f"board: {key!r} must be two integers >= {minimum} [cols, rows] ({what}), got {v!r}")
    return int(v[0]), int(v[1])


def _positive(data: dict, key: str) -> float:
    v = data.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not np.isfinite(v) or v <= 0:
        raise BoardError(f"board: {key!r} must be a positive number of millimetres, got {v!r}")
    return float(v)


def _flag(data: dict, key: str) -> bool:
    v = data.get(key, False)
    if not isinstance(v, (bool, np.bool_)):
        raise BoardError(f"board: {key!r} must be true or false, got {v!r}")
    return bool(v)


def _check_keys(data: dict, allowed: set[str], kind: str) -> None:
    extra = sorted(set(data) - allowed - {"type"})
    if extra:
        raise BoardError(
            f"board: unknown key(s) {', '.join(map(repr, extra))} for type {kind!r} "
            f"(allowed: {', '.join(sorted(allowed))})"
        )


class _BoardBase:
    """Shared behaviour of both board types (rendering, serialization)."""

    type: ClassVar[str]
    square_mm: float
    inverted: bool

    # -- geometry (subclasses) -------------------------------------------------
    @property
    def grid(self) -> tuple[int, int]:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def n_corners(self) -> int:
        c, r = self.grid
        return c * r

    def object_points(self) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def outline_mm(self) -> tuple[float, float, float, float]:  # pragma: no cover - abstract
        raise NotImplementedError

    def neighbor_pairs(self) -> np.ndarray:
        """Index pairs of horizontally and vertically adjacent corners.

        Returns
        -------
        (P, 2) int ndarray
            Corner indices ``(i, j)``; their true distance is ``square_mm``.
        """
        c, r = self.grid
        idx = np.arange(c * r).reshape(r, c)
        h = np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], axis=1)
        v = np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], axis=1)
        return np.concatenate([h, v], axis=0)

    # -- rendering ---------------------------------------------------------------
    def _margin(self, margin_mm: float | None) -> float:
        if margin_mm is None:
            return float(self.square_mm)
        if not np.isfinite(margin_mm) or margin_mm < 0:
            raise ValueError(f"margin_mm must be >= 0, got {margin_mm!r}")
        return float(margin_mm)

    def image_transform(self, *, px_per_mm: float = 4.0, margin_mm: float | None = None) -> np.ndarray:
        """Affine map from board millimetres to pixels of :meth:`image`.

        Parameters
        ----------
        px_per_mm : float
            Resolution of the image.
        margin_mm : float, optional
            White border around the pattern (default: one square).

        Returns
        -------
        (3, 3) float ndarray
            ``A @ [x, y, 1]`` gives ``[u, v, 1]`` with pixel centres at integers.
        """
        if not np.isfinite(px_per_mm) or px_per_mm <= 0:
            raise ValueError(f"px_per_mm must be > 0, got {px_per_mm!r}")
        m = self._margin(margin_mm)
        x0, y0, _, _ = self.outline_mm
        s = float(px_per_mm)
        return np.array([[s, 0.0, (m - x0) * s - 0.5], [0.0, s, (m - y0) * s - 0.5], [0.0, 0.0, 1.0]])

    def image(self, *, px_per_mm: float = 4.0, margin_mm: float | None = None) -> np.ndarray:
        """Render the printable board (as it is printed: inverted when ``inverted``).

        Parameters
        ----------
        px_per_mm : float
            Pixels per millimetre (``dpi / 25.4``).
        margin_mm : float, optional
            White quiet zone around the pattern (default: one square).

        Returns
        -------
        (H, W) uint8 ndarray
            Grey image; board point ``(x, y)`` mm sits at
            ``image_transform(...) @ (x, y, 1)``.
        """
        A = self.image_transform(px_per_mm=px_per_mm, margin_mm=margin_mm)
        m = self._margin(margin_mm)
        x0, y0, x1, y1 = self.outline_mm
        s = float(px_per_mm)
        w = int(round((x1 - x0 + 2 * m) * s))
        h = int(round((y1 - y0 + 2 * m) * s))
        img = np.full((h, w), 255, np.uint8)
        pw, ph = int(round((x1 - x0) * s)), int(round((y1 - y0) * s))
        u0, v0 = int(round(A[0, 2] + x0 * s + 0.5)), int(round(A[1, 2] + y0 * s + 0.5))
        img[v0 : v0 + ph, u0 : u0 + pw] = self._pattern(pw, ph)
        if self.inverted:
            img = 255 - img
        return img

    def _pattern(self, width: int, height: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    # -- serialization --------------------------------------------------------------
    def to_toml(self) -> str:
        return _toml.dumps(self.to_dict())

    def to_dict(self) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError


@dataclass(frozen=True)
class Chessboard(_BoardBase):
    """A plain chessboard.

    Parameters
    ----------
    corners : (int, int)
        Inner corners ``(cols, rows)`` as given to ``cv2.findChessboardCorners``.
    square_mm : float
        Side of one square in millimetres.
    inverted : bool
        Printed white-on-black.
    """

    corners: tuple[int, int]
    square_mm: float
    inverted: bool = False
    type: ClassVar[str] = "chessboard"

    def __post_init__(self) -> None:
        c = _pair({"corners": list(self.corners) if isinstance(self.corners, (list, tuple)) else self.corners},
                  "corners", 2, "inner corners")
        object.__setattr__(self, "corners", c)
        object.__setattr__(self, "square_mm", _positive({"square_mm": self.square_mm}, "square_mm"))
        object.__setattr__(self, "inverted", _flag({"inverted": self.inverted}, "inverted"))

    @property
    def grid(self) -> tuple[int, int]:
        """Corner grid ``(cols, rows)``."""
        return self.corners

    def object_points(self) -> np.ndarray:
        """(N, 3) corners in the board frame (mm, z = 0), OpenCV's row-major detection order."""
        c, r = self.corners
        xx, yy = np.meshgrid(np.arange(c, dtype=np.float64), np.arange(r, dtype=np.float64))
        return np.stack([xx.ravel(), yy.ravel(), np.zeros(c * r)], axis=1) * self.square_mm

    @property
    def outline_mm(self) -> tuple[float, float, float, float]:
        """Pattern extent ``(x0, y0, x1, y1)`` in the board frame (mm)."""
        c, r = self.corners
        s = self.square_mm
        return (-s, -s, c * s, r * s)

    def to_cv(self) -> tuple[int, int]:
        """OpenCV has no chessboard object: the pattern size for ``findChessboardCorners``."""
        return self.corners

    def _pattern(self, width: int, height: int) -> np.ndarray:
        c, r = self.corners
        nx, ny = c + 1, r + 1
        ix = np.minimum((np.arange(width) + 0.5) * nx // width, nx - 1).astype(int)
        iy = np.minimum((np.arange(height) + 0.5) * ny // height, ny - 1).astype(int)
        black = ((iy[:, None] + ix[None, :]) % 2) == 0
        return np.where(black, 0, 255).astype(np.uint8)

    def to_dict(self) -> dict:
        d: dict[str, Any] = {"type": self.type, "corners": list(self.corners), "square_mm": self.square_mm}
        if self.inverted:
            d["inverted"] = True
        return d


@dataclass(frozen=True)
class Charuco(_BoardBase):
    """A ChArUco board (chessboard with ArUco markers in the white squares).

    Parameters
    ----------
    squares : (int, int)
        Squares ``(cols, rows)``; the corner grid is ``(cols - 1, rows - 1)``.
    square_mm, marker_mm : float
        Square side and marker side in millimetres (``marker_mm < square_mm``).
    dictionary : str
        OpenCV predefined dictionary name, e.g. ``"DICT_4X4_1000"``.
    legacy : bool
        OpenCV's legacy layout (boards made with OpenCV < 4.6 and most
        calibration tools built on it, e.g. aniposelib/calib.io with even rows).
    inverted : bool
        Printed white-on-black.
    """

    squares: tuple[int, int]
    square_mm: float
    marker_mm: float
    dictionary: str = "DICT_4X4_1000"
    legacy: bool = False
    inverted: bool = False
    type: ClassVar[str] = "charuco"

    def __post_init__(self) -> None:
        sq = _pair({"squares": list(self.squares) if isinstance(self.squares, (list, tuple)) else self.squares},
                   "squares", 2, "squares")
        object.__setattr__(self, "squares", sq)
        s = _positive({"square_mm": self.square_mm}, "square_mm")
        m = _positive({"marker_mm": self.marker_mm}, "marker_mm")
        if m >= s:
            raise BoardError(f"board: 'marker_mm' ({m}) must be smaller than 'square_mm' ({s})")
        object.__setattr__(self, "square_mm", s)
        object.__setattr__(self, "marker_mm", m)
        if not isinstance(self.dictionary, str) or self.dictionary.upper() not in _dictionaries():
            raise BoardError(
                f"board: 'dictionary' must be an OpenCV ArUco dictionary name such as 'DICT_4X4_1000', "
                f"got {self.dictionary!r}"
            )
        object.__setattr__(self, "dictionary", self.dictionary.upper())
        need = (sq[0] * sq[1]) // 2
        have = _dictionary_size(self.dictionary)
        if need > have:
            raise BoardError(
                f"board: 'dictionary' {self.dictionary} has {have} markers but {sq[0]}x{sq[1]} squares need {need}"
            )
        object.__setattr__(self, "legacy", _flag({"legacy": self.legacy}, "legacy"))
        object.__setattr__(self, "inverted", _flag({"inverted": self.inverted}, "inverted"))

    @property
    def grid(self) -> tuple[int, int]:
        """Corner grid ``(cols - 1, rows - 1)``."""
        return (self.squares[0] - 1, self.squares[1] - 1)

    @property
    def n_markers(self) -> int:
        return (self.squares[0] * self.squares[1]) // 2

    def to_cv(self):
        """The OpenCV board (``cv2.aruco.CharucoBoard``, lengths in mm, legacy flag applied)."""
        import cv2

        d = cv2.aruco.getPredefinedDictionary(_dictionaries()[self.dictionary])
        b = cv2.aruco.CharucoBoard(self.squares, self.square_mm, self.marker_mm, d)
        b.setLegacyPattern(self.legacy)
        return b

    def object_points(self) -> np.ndarray:
        """(N, 3) ChArUco corners in the board frame (mm, z = 0); row ``k`` is corner id ``k``."""
        c, r = self.grid
        s = self.square_mm
        xx, yy = np.meshgrid(np.arange(1, c + 1, dtype=np.float64), np.arange(1, r + 1, dtype=np.float64))
        return np.stack([xx.ravel() * s, yy.ravel() * s, np.zeros(c * r)], axis=1)

    @property
    def outline_mm(self) -> tuple[float, float, float, float]:
        """Pattern extent ``(x0, y0, x1, y1)`` in the board frame (mm)."""
        return (0.0, 0.0, self.squares[0] * self.square_mm, self.squares[1] * self.square_mm)

    def _pattern(self, width: int, height: int) -> np.ndarray:
        # OpenCV's generateImage places a marker one pixel past the pattern at some sizes and fails (a 7 x 5 board
        # of 70 mm squares at 60 pixels a square); there the pattern is drawn at an integer multiple of the size
        # and averaged down by whole blocks (INTER_AREA), which keeps every edge where the board has it
        import cv2

        board = self.to_cv()
        for k in range(1, 5):
            try:
                img = board.generateImage((width * k, height * k), marginSize=0, borderBits=1)
            except cv2.error:
                continue
            return img if k == 1 else cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
        raise BoardError(f"board: OpenCV cannot draw this ChArUco board at {width} x {height} pixels; "
                         f"try another resolution")

    def to_dict(self) -> dict:
        return {
            "type": self.type,
            "squares": list(self.squares),
            "square_mm": self.square_mm,
            "marker_mm": self.marker_mm,
            "dictionary": self.dictionary,
            "legacy": self.legacy,
            "inverted": self.inverted,
        }


Board = Union[Chessboard, Charuco]


def parse_board(data: dict) -> Board:
    """Build a board from the parsed TOML (or JSON) dictionary.

    Raises
    ------
    BoardError
        With a message naming the missing or invalid key.
    """
    if isinstance(data, (Chessboard, Charuco)):
        return data
    if not isinstance(data, dict):
        raise BoardError(f"board: expected a table of keys, got {type(data).__name__}")
    if "type" not in data and {"columns", "rows"} <= set(data):
        return _caliscope_charuco(data)
    kind = data.get("type")
    if kind == "chessboard":
        _check_keys(data, {"corners", "square_mm", "inverted"}, kind)
        for k in ("corners", "square_mm"):
            if k not in data:
                raise BoardError(f"board: missing key {k!r} (a chessboard needs corners = [cols, rows] and square_mm)")
        return Chessboard(corners=_pair(data, "corners", 2, "inner corners"), square_mm=_positive(data, "square_mm"),
                          inverted=_flag(data, "inverted"))
    if kind == "charuco":
        _check_keys(data, {"squares", "square_mm", "marker_mm", "dictionary", "legacy", "inverted"}, kind)
        for k in ("squares", "square_mm", "marker_mm"):
            if k not in data:
                raise BoardError(
                    f"board: missing key {k!r} (a ChArUco board needs squares = [cols, rows], square_mm, marker_mm)"
                )
        return Charuco(
            squares=_pair(data, "squares", 2, "squares"),
            square_mm=_positive(data, "square_mm"),
            marker_mm=_positive(data, "marker_mm"),
            dictionary=data.get("dictionary", "DICT_4X4_1000"),
            legacy=_flag(data, "legacy"),
            inverted=_flag(data, "inverted"),
        )
    raise BoardError(f"board: 'type' must be \"chessboard\" or \"charuco\", got {kind!r}")


_INCH_CM = {"inch": 2.54, "cm": 1.0, "mm": 0.1}


def _caliscope_charuco(data: dict) -> Charuco:
    """caliscope's ``charuco.toml`` (``columns``, ``rows``, ``aruco_scale``, ``square_size_override_cm`` or
    ``board_width`` / ``board_height`` in ``units``, ``dictionary``, ``inverted``, ``legacy_pattern``)."""
    cols, rows = data["columns"], data["rows"]
    if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 2 for v in (cols, rows)):
        raise BoardError(f"board: caliscope columns and rows must be integers >= 2, got {cols!r}, {rows!r}")
    if data.get("square_size_override_cm"):
        square_cm = float(data["square_size_override_cm"])
    else:
        unit = data.get("units", "inch")
        if unit not in _INCH_CM:
            raise BoardError(f"board: caliscope units {unit!r} unknown (inch, cm, mm)")
        try:
            w, h = float(data["board_width"]), float(data["board_height"])
        except (KeyError, TypeError, ValueError):
            raise BoardError("board: caliscope board needs square_size_override_cm or board_width and "
                             "board_height") from None
        square_cm = min(w / cols, h / rows) * _INCH_CM[unit]
    square_mm = 10.0 * square_cm
    scale = float(data.get("aruco_scale", 0.75))
    if not 0 < scale < 1:
        raise BoardError(f"board: caliscope aruco_scale must be within (0, 1), got {scale}")
    return Charuco(squares=(cols, rows), square_mm=square_mm, marker_mm=scale * square_mm,
                   dictionary=data.get("dictionary", "DICT_4X4_1000"), legacy=bool(data.get("legacy_pattern", False)),
                   inverted=bool(data.get("inverted", False)))


def load_board(path: str | Path) -> Board:
    """Read a board TOML file (see the module docstring)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"board file not found: {p}")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise BoardError(f"board file {p} is not valid TOML: {exc}") from None
    try:
        return parse_board(data)
    except BoardError as exc:
        raise BoardError(f"{p}: {exc}") from None


def save_board(board: Board, path: str | Path) -> None:
    """Write a board TOML file."""
    if not isinstance(board, (Chessboard, Charuco)):
        raise ValueError(f"board must be a Chessboard or Charuco, got {type(board).__name__}")
    Path(path).write_text(board.to_toml(), encoding="utf-8")
