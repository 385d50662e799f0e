"""``stage board``: print a board definition as a PNG or a PDF at its true size."""

from __future__ import annotations

import argparse
from pathlib import Path

ORDER = 29


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "board", help="make a printable image (PNG/PDF) of a board file",
        description="Render BOARD.toml (chessboard or ChArUco) with a white margin of one square. PDF pages "
        "have the board's physical size (print at 100%%, no 'fit to page'); PNG files carry the DPI. "
        "Measure a printed square and put the measured size in the board file.",
    )
    p.add_argument("board", type=Path, metavar="BOARD.toml")
    p.add_argument("--out", required=True, type=Path, metavar="board.png|board.pdf")
    p.add_argument("--dpi", type=float, default=300.0, help="resolution (default 300)")
    p.add_argument("--margin-mm", type=float, default=None, help="white margin (default: one square)")
    p.set_defaults(func=run)


def write_board_image(board, out: Path, *, dpi: float = 300.0, margin_mm: float | None = None) -> tuple[int, int]:
    """Write ``board`` to ``out`` (.png or .pdf) at ``dpi``; returns the pixel size (w, h)."""
    from PIL import Image

    if not dpi > 0:
        raise ValueError(f"dpi must be > 0, got {dpi}")
    ext = out.suffix.lower()
    if ext not in (".png", ".pdf"):
        raise ValueError(f"--out must end in .png or .pdf, got {out.name}")
    img = board.image(px_per_mm=dpi / 25.4, margin_mm=margin_mm)
    pil = Image.fromarray(img, mode="L")
    if ext == ".pdf":
        pil.save(out, "PDF", resolution=dpi)
    else:
        pil.save(out, "PNG", dpi=(dpi, dpi))
    return img.shape[1], img.shape[0]


def run(args: argparse.Namespace) -> int:
    from calib.boards import load_board

    board = load_board(args.board)
    w, h = write_board_image(board, args.out, dpi=args.dpi, margin_mm=args.margin_mm)
    print(f"wrote {args.out}: {w}x{h} px at {args.dpi:g} dpi = {w / args.dpi * 25.4:.1f} x {h / args.dpi * 25.4:.1f} mm")
    return 0
