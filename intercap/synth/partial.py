"""A view that sees part of the scene: one camera's images seeing nothing outside a box.

Real rigs often have a camera close in, or aimed so the feet or the head leave its image (BEHAVE's
and InterCap's side cameras, a desk rig). Our generator frames the whole person in every ring camera;
`crop_view` makes one of them look like such a camera: outside the box its colour is black, its
depth missing (0) and its masks empty, and keypoints there are undetected (confidence 0), as a
detector on a smaller image would leave them. Its intrinsics and image size stay those of the lens
(a real partial view is a whole image aimed elsewhere; cropping the files would put the principal
point at their edge, which validate refuses as intrinsics of another resolution). The ground truth,
the other cameras and the world are unchanged, so evaluation compares as before.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2

from intercap.io.files import read_json, write_json
from intercap.synth.reframe import link_tree

_KEYPOINT_KEYS = ("pose_keypoints_2d", "hand_left_keypoints_2d", "hand_right_keypoints_2d", "face_keypoints_2d")


def _crop_keypoints(doc: dict, x0: int, y0: int, w: int, h: int) -> dict:
    """OpenPose JSON with the points outside the box undetected."""
    for person in doc.get("people", []):
        for key in _KEYPOINT_KEYS:
            flat = person.get(key)
            if not flat:
                continue
            out = []
            for x, y, c in zip(flat[0::3], flat[1::3], flat[2::3]):
                u, v = x - x0, y - y0
                inside = c > 0 and 0 <= u <= w - 1 and 0 <= v <= h - 1
                out += [x, y, c] if inside else [0.0, 0.0, 0.0]
            person[key] = out
    return doc


def crop_view(session_dir, out_dir, camera: int | str, box: tuple[int, int, int, int]) -> Path:
    """Write a copy of the session at `out_dir` in which `camera` sees only `box` = (x0, y0, width,
    height) of its image (pixels): nothing outside it. Other cameras' files are hard links to the originals."""
    src, dst = Path(session_dir), Path(out_dir)
    if dst.exists():
        raise FileExistsError(f"{dst} exists; choose a new folder")
    calib = read_json(src / "calibration.json")
    cams = calib["cameras"]
    cam = cams[camera] if isinstance(camera, int) else next((c for c in cams if c["name"] == camera), None)
    if cam is None:
        raise ValueError(f"{camera!r}: no such camera in {src / 'calibration.json'}")
    x0, y0, w, h = (int(v) for v in box)
    if x0 < 0 or y0 < 0 or w < 1 or h < 1 or x0 + w > cam["width"] or y0 + h > cam["height"]:
        raise ValueError(f"box {box} does not lie inside {cam['name']}'s {cam['width']}x{cam['height']} image")

    dst.mkdir(parents=True)
    for path in src.iterdir():
        if path.name == cam["name"] or path.name == "calibration.json":
            continue
        if path.is_dir():
            link_tree(path, dst / path.name)
        else:
            shutil.copy2(path, dst / path.name)
    for path in (src / cam["name"]).rglob("*"):
        target = dst / cam["name"] / path.relative_to(src / cam["name"])
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
        elif path.suffix == ".json":
            target.write_text(json.dumps(_crop_keypoints(json.loads(path.read_text()), x0, y0, w, h)))
        else:
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if image is None:  # an unreadable file stays what it was: a dropped frame
                shutil.copy2(path, target)
                continue
            params = [cv2.IMWRITE_JPEG_QUALITY, 95] if path.suffix.lower() in (".jpg", ".jpeg") else []
            seen = image[y0:y0 + h, x0:x0 + w].copy()
            image[...] = 0
            image[y0:y0 + h, x0:x0 + w] = seen
            cv2.imwrite(str(target), image, params)
    write_json(dst / "calibration.json", calib)
    return dst
