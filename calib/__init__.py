"""Camera rigs: calibration files of known rigs (`rigs/*.json`, the session format's
calibration.json) and the check that aligns neighbouring cameras' point clouds."""
from pathlib import Path

from intercap.calib.alignment import PairAgreement, check_calibration, format_agreement, neighbour_pairs

RIGS_DIR = Path(__file__).resolve().parent / "rigs"


def rig_path(name: str) -> Path:
    """calibration.json of a shipped rig, e.g. 'sample_ring4' (the sample session's 4-camera ring)."""
    path = RIGS_DIR / f"{name}.json"
    if not path.exists():
        known = sorted(p.stem for p in RIGS_DIR.glob("*.json"))
        raise FileNotFoundError(f"no rig {name!r}; shipped rigs: {known}")
    return path


__all__ = ["PairAgreement", "check_calibration", "format_agreement", "neighbour_pairs", "rig_path", "RIGS_DIR"]
