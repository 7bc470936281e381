"""`intercap board`: the calibration board written to print at its true size, and found again by
the detector `intercap calibrate` uses."""
import re

import cv2
import numpy as np
import pytest

from intercap.calib.board import Board
from intercap.calib.print_board import write_board


@pytest.mark.parametrize("kind, squares", [("charuco", (7, 5)), ("checkerboard", (8, 5))])
def test_a_printed_board_is_found_whole_and_has_its_size(tmp_path, kind, squares):
    board = Board(kind, squares, 0.1, 0.075)
    written = write_board(board, tmp_path / "board.png", dpi=60, margin_m=0.02)
    image = cv2.imread(written["path"], cv2.IMREAD_GRAYSCALE)
    ids, corners = board.detect(image)
    assert len(ids) == len(board.object_points)  # every inner corner
    # the corners lie where the board's geometry puts them: 0.1 m squares of whole dots at 60 dpi, a 2 cm margin
    per_m = 60 / 0.0254
    expected = board.object_points[ids, :2] / 0.1 * round(0.1 * per_m) + round(0.02 * per_m)
    assert np.abs(np.sort(corners, 0) - np.sort(expected, 0)).max() < 1.0
    width_mm, height_mm = written["size_mm"]
    assert abs(width_mm - (squares[0] * 100 + 40)) < 1 and abs(height_mm - (squares[1] * 100 + 40)) < 1


def test_the_pdf_page_is_the_board_at_true_size(tmp_path):
    written = write_board(Board("charuco", (7, 5), 0.04, 0.03), tmp_path / "board.pdf", dpi=300, margin_m=0.01)
    data = (tmp_path / "board.pdf").read_bytes()
    box = [float(v) for v in re.search(rb"MediaBox \[ ([\d. ]+) \]", data).group(1).split()]
    points_per_mm = 72 / 25.4
    assert abs(box[2] / points_per_mm - 300) < 0.5 and abs(box[3] / points_per_mm - 220) < 0.5  # 28 x 20 cm + 1 cm
    assert b"CCITTFaxDecode" in data  # black and white, not a lossy JPEG
    square, margin = round(0.04 / 0.0254 * 300), round(0.01 / 0.0254 * 300)
    assert written["pixels"] == (7 * square + 2 * margin, 5 * square + 2 * margin)


def test_a_board_that_cannot_be_printed_says_why(tmp_path):
    with pytest.raises(ValueError, match="raise --dpi"):
        write_board(Board("charuco", (7, 5), 0.04, 0.03), tmp_path / "b.png", dpi=10)
    with pytest.raises(ValueError, match=r"\.png or \.pdf"):
        write_board(Board("charuco", (7, 5), 0.04, 0.03), tmp_path / "b.svg")


def test_the_board_command_writes_what_calibrate_looks_for(tmp_path, capsys):
    """`intercap board` takes calibrate's board options and says the printed size."""
    from intercap.cli import main

    assert main(["board", str(tmp_path / "b.png"), "--squares", "5x4", "--square-m", "0.05", "--marker-m", "0.035",
                 "--dpi", "100", "--margin-m", "0"]) == 0
    said = capsys.readouterr().out
    width, height, square = (float(v) for v in re.search(r"([\d.]+) x ([\d.]+) mm, squares of ([\d.]+) mm", said).groups())
    assert abs(width - 250) < 1 and abs(height - 200) < 1 and abs(square - 50) < 0.13  # within half a dot
    board = Board("charuco", (5, 4), 0.05, 0.035)
    ids, _ = board.detect(cv2.imread(str(tmp_path / "b.png"), cv2.IMREAD_GRAYSCALE))
    assert len(ids) == len(board.object_points)
