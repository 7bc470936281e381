"""What can be wrong with a session: `Problem`, `SessionError` and the checks of
matrices (intrinsics, rotations, rigid transforms) that reading and validation share."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np

ROTATION_TOL = 1e-4  # calibration and initial poses: orthonormality / det tolerance


GT_ROTATION_TOL = 1e-3  # ground-truth poses may be stored as float32


FOCAL_RANGE = (0.1, 10.0)  # plausible fx, fy as multiples of the image width


# cx, cy may lie this fraction of the image size from its centre: a lens's principal point lies within a few % of
# it; intrinsics of another resolution (twice: at the image's edge) or fx and cx swapped put it far out
PRINCIPAL_POINT_FROM_CENTRE = 0.25


MAX_TRANSLATION_M = 100.0  # camera and object positions farther from the world origin are implausible


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a session: which file (relative to the session root) and what."""

    path: str
    message: str
    fatal: bool

    def __str__(self) -> str:
        return f"{self.path}: {self.message}"


class SessionError(Exception):
    """The session cannot be used; `.problems` lists every fatal problem found (and the warnings)."""

    def __init__(self, root: Path | str, problems: list[Problem]):
        self.root = Path(root)
        self.problems = list(problems)
        fatal = [p for p in self.problems if p.fatal]
        lines = [f"session {self.root} cannot be used ({len(fatal)} fatal problems):"]
        lines += [f"  {p}" for p in fatal]
        super().__init__("\n".join(lines))


class ProblemList(list):
    """A list of Problem with shorthands; paths are made relative to the session root."""

    def __init__(self, root: Path):
        super().__init__()
        self.root = root

    def rel(self, path: Path | str) -> str:
        path = Path(path)
        try:
            rel = path.relative_to(self.root)
        except ValueError:
            return str(path)
        return rel.as_posix() if rel.parts else "."

    def fatal(self, path: Path | str, message: str) -> None:
        self.append(Problem(self.rel(path), message, True))

    def warn(self, path: Path | str, message: str) -> None:
        self.append(Problem(self.rel(path), message, False))

    @property
    def any_fatal(self) -> bool:
        return any(p.fatal for p in self)


def intrinsics_issue(K: Any, width: int | None = None, height: int | None = None) -> str | None:
    """Why K is not a pinhole matrix [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0 (None if it is);
    given the image size, also why its focal lengths or principal point are implausible for it."""
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        return "K is not a 3x3 matrix of numbers"
    if K.shape != (3, 3):
        return f"K is not 3x3 (shape {K.shape})"
    if not np.all(np.isfinite(K)):
        return "K has non-finite entries"
    zeros = np.array([K[0, 1], K[1, 0], K[2, 0], K[2, 1]])
    if np.any(np.abs(zeros) > 1e-9) or abs(K[2, 2] - 1.0) > 1e-9:
        return "K is not of the form [[fx,0,cx],[0,fy,cy],[0,0,1]]"
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return f"K has non-positive focal length (fx={K[0, 0]:g}, fy={K[1, 1]:g})"
    if width is None or height is None:
        return None
    return _intrinsics_plausibility_issue(K, width, height)


def _intrinsics_plausibility_issue(K: np.ndarray, width: int, height: int) -> str | None:
    """Why a well-formed K does not fit a width x height image: focal lengths outside FOCAL_RANGE
    times the width, or the principal point far from the image centre (PRINCIPAL_POINT_FROM_CENTRE)."""
    lo, hi = FOCAL_RANGE[0] * width, FOCAL_RANGE[1] * width
    for name, f in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if not lo <= f <= hi:
            return (f"K has implausible focal length {name}={f:g} px for an image {width} px wide "
                    f"(expected {lo:g}-{hi:g} px)")
    for name, c, size in (("cx", K[0, 2], width), ("cy", K[1, 2], height)):
        if abs(c - size / 2) > PRINCIPAL_POINT_FROM_CENTRE * size:
            key = "width" if name == "cx" else "height"
            where = "outside the image" if not 0 <= c <= size else "far from the centre of the image"
            return (f"K has principal point {name}={c:g} px {where} ({key} {size} px; a lens's lies within a few % "
                    f"of the centre): intrinsics of another resolution, or fx and cx swapped?")
    return None


def rotation_issue(R: Any, tol: float = ROTATION_TOL) -> str | None:
    """Why R is not a rotation matrix (orthonormal, det +1), or None."""
    try:
        R = np.asarray(R, dtype=np.float64)
    except (TypeError, ValueError):
        return "is not a 3x3 matrix of numbers"
    if R.shape != (3, 3):
        return f"is not 3x3 (shape {R.shape})"
    if not np.all(np.isfinite(R)):
        return "has non-finite entries"
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > tol:
        return f"is not orthonormal (max |R^T R - I| = {err:.2g})"
    det = np.linalg.det(R)
    if abs(det - 1.0) > tol:
        return f"has determinant {det:.4g}, not +1 (a reflection)"
    return None


def translation_issue(t: np.ndarray, limit: float = MAX_TRANSLATION_M) -> str | None:
    """Why a finite translation (metres) is implausibly far from the world origin, or None."""
    dist = float(np.linalg.norm(t))
    if dist > limit:
        return f"translation is {dist:.3g} m from the world origin (over {limit:g} m): is it in millimetres?"
    return None


def rigid_transform_issue(T: Any, tol: float = ROTATION_TOL, max_translation: float | None = None) -> str | None:
    """Why T is not a 4x4 rigid transform [[R, t], [0, 0, 0, 1]] (with |t| <= max_translation
    metres when given), or None."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        return "is not a 4x4 matrix of numbers"
    if T.shape != (4, 4):
        return f"is not 4x4 (shape {T.shape})"
    if not np.all(np.isfinite(T)):
        return "has non-finite entries"
    if np.abs(T[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        return f"last row is {T[3].tolist()}, not [0, 0, 0, 1]"
    issue = rotation_issue(T[:3, :3], tol)
    if issue is not None:
        return f"rotation part {issue}"
    return None if max_translation is None else translation_issue(T[:3, 3], max_translation)


def format_frame_list(ids: Iterable[int], limit: int = 20) -> str:
    """'3, 7-9, 12' for [3, 7, 8, 9, 12]; long lists are cut after `limit` runs."""
    ids = sorted(int(i) for i in ids)
    runs: list[tuple[int, int]] = []
    for i in ids:
        if runs and i == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], i)
        else:
            runs.append((i, i))
    parts = [str(a) if a == b else f"{a}-{b}" for a, b in runs[:limit]]
    if len(runs) > limit:
        parts.append("...")
    return ", ".join(parts)
