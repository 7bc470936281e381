"""Presenting an evaluation: the plain-text table `intercap eval` prints and the JSON file it writes."""
from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from intercap.evaluation.evaluate import EvalResult


_UNITS = (("_frames_missing", "frames"), ("_frames", "frames"), ("_mm_s", "mm/s"), ("_mm", "mm"), ("_kg", "kg"),
          ("_nm", "N m"), ("_n", "N"), ("_deg", "deg"), ("_pct", "%"), ("_mps2", "m/s^2"))


def _unit(name: str) -> str:
    for key, unit in _UNITS:
        if name.endswith(key) or (key + "_") in name:
            return unit
    return "frames" if name in ("frames", "penetration_frames") else ""


def format_table(result: EvalResult) -> str:
    """A plain-text table (metric, value, unit) followed by the notes."""
    rows = [("metric", "value", "unit")]
    for name, value in result.metrics.items():
        if value is None:
            text = "n/a"
        elif isinstance(value, str):
            text = value
        elif isinstance(value, (int, np.integer)):
            text = str(int(value))
        else:
            text = f"{value:.3f}"
        rows.append((name, text, _unit(name)))
    w0, w1 = max(len(r[0]) for r in rows), max(len(r[1]) for r in rows)
    lines = [f"{a:<{w0}}  {b:>{w1}}  {c}".rstrip() for a, b, c in rows]
    lines.insert(1, "-" * len(lines[0]))
    if result.notes:
        lines += ["", "notes:"] + [f"  - {n}" for n in result.notes]
    return "\n".join(lines)


def json_list(arr) -> list:
    """Array -> list with None where NaN (JSON has no NaN)."""
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(arr, np.float64).ravel()]


def jsonable(obj):
    if isinstance(obj, dict):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    return obj


def write_json(result: EvalResult, path) -> None:
    """metrics, per_frame and notes as JSON (NaN written as null)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        json.dump(result.to_dict(), fh, indent=2)
