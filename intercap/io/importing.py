"""What the dataset importers share: a staging folder renamed into place at the end (so a
failed import never leaves a half-written session that looks valid), our calibration.json,
and frame files copied or converted into the session layout."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

WORLD_NOTE = "metres; any right-handed frame; gravity is not assumed to be an axis"


class DatasetImportError(ValueError):
    """Bad dataset input; the message is one line naming the file."""


@contextlib.contextmanager
def staging(out_session: str | Path, overwrite: bool = False):
    """Yield a temporary folder next to `out_session`; on success it is renamed to it."""
    out = Path(out_session)
    if out.exists() and not overwrite:
        raise DatasetImportError(f"{out}: already exists (pass --overwrite to replace it)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.importing-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
        if out.exists():
            shutil.rmtree(out)
        os.rename(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def camera_entry(name: str, width: int, height: int, K, dist, T_world_from_cam) -> dict:
    """One camera of our calibration.json (plain Python floats: JSON round-trips them exactly)."""
    return {"name": name, "width": int(width), "height": int(height),
            "K": [[float(v) for v in row] for row in np.asarray(K, np.float64)],
            "dist": [float(v) for v in np.asarray(dist, np.float64).reshape(-1)],
            "T_world_from_cam": [[float(v) for v in row] for row in np.asarray(T_world_from_cam, np.float64)]}


def write_calibration(root: Path, cameras: list[dict], world: str = WORLD_NOTE) -> None:
    (root / "calibration.json").write_text(json.dumps({"world": world, "cameras": cameras}, indent=1) + "\n")


def read_json_file(path: Path) -> dict:
    """A JSON file's content; DatasetImportError naming the file when it is missing or malformed."""
    if not path.is_file():
        raise DatasetImportError(f"{path}: missing")
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetImportError(f"{path}: unreadable JSON ({exc})") from exc


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file; DatasetImportError naming it when it cannot be decoded."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetImportError(f"{path}: cannot be decoded as an image")
    return img.shape[1], img.shape[0]


def copy_color(src: Path, dst_dir: Path, frame: int) -> None:
    """Colour frame: JPEG/PNG bytes copied unchanged (no re-encoding loss), other formats as PNG."""
    ext = src.suffix.lower()
    if ext in (".jpg", ".jpeg", ".png"):
        shutil.copyfile(src, dst_dir / f"{frame:06d}{'.jpg' if ext == '.jpeg' else ext}")
        return
    img = cv2.imread(str(src), cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetImportError(f"{src}: cannot be decoded as an image")
    cv2.imwrite(str(dst_dir / f"{frame:06d}.png"), img)


def write_depth(src: Path, dst_dir: Path, frame: int, size: tuple[int, int], scale_to_mm: float = 1.0) -> None:
    """Depth frame as uint16 millimetres at the colour size `size` (w, h): copied when it already
    is, else scaled and/or resized by nearest neighbour (registered depth stored at a lower
    resolution of the same aspect)."""
    depth = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    if depth is None or depth.ndim != 2 or depth.dtype != np.uint16:
        raise DatasetImportError(f"{src}: not a single-channel 16-bit depth image")
    h, w = depth.shape
    if (w, h) == tuple(size) and scale_to_mm == 1.0 and src.suffix.lower() == ".png":
        shutil.copyfile(src, dst_dir / f"{frame:06d}.png")
        return
    if (w, h) != tuple(size):
        if abs(w * size[1] - h * size[0]) > max(w, h):
            raise DatasetImportError(f"{src}: depth {w}x{h} has another aspect than the colour image {size[0]}x{size[1]}; "
                               "it must be registered to colour")
        depth = cv2.resize(depth, tuple(size), interpolation=cv2.INTER_NEAREST)
    if scale_to_mm != 1.0:
        depth = np.clip(np.rint(depth.astype(np.float64) * scale_to_mm), 0, 65535).astype(np.uint16)
    cv2.imwrite(str(dst_dir / f"{frame:06d}.png"), depth)


def write_mask(src: Path, dst_dir: Path, frame: int, size: tuple[int, int]) -> bool:
    """Mask (any 8-bit image, > 127 = inside) as our binary PNG at the colour size; False when unreadable."""
    mask = cv2.imread(str(src), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        return False
    if (mask.shape[1], mask.shape[0]) != tuple(size):
        mask = cv2.resize(mask, tuple(size), interpolation=cv2.INTER_NEAREST)
    dst_dir.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(dst_dir / f"{frame:06d}.png"), np.where(mask > 127, 255, 0).astype(np.uint8))
    return True


def rigid(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.asarray(R, np.float64).reshape(3, 3), np.asarray(t, np.float64).reshape(3)
    return T


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 with R^T (exact for rotations)."""
    R, t = T[:3, :3], T[:3, 3]
    return rigid(R.T, -R.T @ t)
