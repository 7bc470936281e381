"""The calibration board as a file to print (`intercap board`): PNG or PDF at its true size.

The image is drawn from the same `Board` that `intercap calibrate` detects (ChArUco: OpenCV's
own drawing of the board; checkerboard: the top-left square black, as `Board.detect` expects), so
what is printed is what is looked for. The file carries its physical size: a PDF page exactly
the board plus its white margin, a PNG with its resolution (dots per inch) in its header; print
at 100 % ("actual size"), then measure one square and pass that length to `intercap calibrate`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

INCH_M = 0.0254


def board_image(board, dpi: float, margin_m: float) -> np.ndarray:
    """(H, W) uint8 image of `board` at `dpi` dots per inch with a white margin of `margin_m` metres."""
    if dpi <= 0 or margin_m < 0:
        raise ValueError(f"dpi must be positive and the margin at least 0, got dpi {dpi}, margin {margin_m} m")
    per_m = dpi / INCH_M
    cols, rows = board.squares
    square = round(board.square_m * per_m)  # whole dots: every square the same size on paper
    if square < 20:
        raise ValueError(f"a square of {board.square_m * 1000:g} mm is {square} dots at {dpi:g} dpi: "
                         "too few to print its marker; raise --dpi")
    width, height = cols * square, rows * square
    margin = round(margin_m * per_m)
    if board.kind == "charuco":
        inner = board._board.generateImage((width, height), marginSize=0, borderBits=1)
    else:
        y, x = np.mgrid[0:height, 0:width]
        dark = ((np.minimum(x // square, cols - 1) + np.minimum(y // square, rows - 1)) % 2) == 0
        inner = np.where(dark, 0, 255).astype(np.uint8)
    return np.pad(inner, margin, constant_values=255)


def write_board(board, path, dpi: float = 300.0, margin_m: float = 0.01) -> dict:
    """Write `board` to `path` (.png or .pdf) at its true size; returns what was written: the path, the
    image's pixels, its printed size in millimetres (board and margin) and a square's (whole dots: within
    half a dot of the board's)."""
    from PIL import Image

    path = Path(path)
    kind = path.suffix.lower()
    if kind not in (".png", ".pdf"):
        raise ValueError(f"{path}: the board is written as .png or .pdf, not {kind or 'a file without extension'}")
    image = board_image(board, dpi, margin_m)
    path.parent.mkdir(parents=True, exist_ok=True)
    picture = Image.fromarray(image).convert("1", dither=Image.Dither.NONE)  # black and white: lossless in a PDF
    if kind == ".pdf":
        picture.save(path, "PDF", resolution=float(dpi))
    else:
        picture.save(path, "PNG", dpi=(float(dpi), float(dpi)))
    height, width = image.shape
    mm = INCH_M * 1000 / dpi
    return {"path": str(path), "pixels": (width, height), "size_mm": (width * mm, height * mm),
            "square_mm": round(board.square_m * dpi / INCH_M) * mm}
