"""`intercap calibrate`'s options, apart from the calibration (calib/board.py, which imports cv2,
scipy and open3d) so that `intercap calibrate --help` and a usage error answer at once."""
from __future__ import annotations


def add_board_arguments(p) -> None:
    """The board's options, shared by `intercap calibrate` and `intercap board`."""
    p.add_argument("--board", choices=["charuco", "checkerboard"], default="charuco")
    p.add_argument("--squares", default="7x5", help="squares across x down, e.g. 7x5 (default)")
    p.add_argument("--square-m", type=float, default=0.04, help="square side in metres (default 0.04)")
    p.add_argument("--marker-m", type=float, default=0.03, help="ChArUco marker side in metres (default 0.03)")
    p.add_argument("--dictionary", default="DICT_5X5_100", help="ChArUco ArUco dictionary (default DICT_5X5_100)")


def add_print_arguments(p) -> None:
    """`intercap board`'s options: where to write the board, at what resolution and margin, and which board."""
    p.add_argument("out", metavar="OUT", help="board.pdf (a page of the board's true size) or board.png")
    add_board_arguments(p)
    p.add_argument("--dpi", type=float, default=300.0, help="dots per inch (default 300)")
    p.add_argument("--margin-m", type=float, default=0.01, help="white margin round the board, metres (default 0.01)")


def add_calibrate_arguments(p) -> None:
    """`intercap calibrate`'s options."""
    p.add_argument("session", metavar="SESSION_DIR", help="recording: calibration.json (intrinsics) and <camera>/color, depth")
    add_board_arguments(p)
    p.add_argument("--world", choices=["camera", "board"], default="camera",
                   help="world frame: the first camera (default) or the board's first shared pose")
    p.add_argument("--no-depth-refine", action="store_true", help="report the depth agreement but keep the board poses")
    p.add_argument("--out", help="calibration.json to write (default: SESSION_DIR/calibration.json)")
