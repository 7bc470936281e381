"""Camera rigs: calibration files of known rigs (`rigs/*.json`, the session format's
calibration.json) and the check that aligns neighbouring cameras' point clouds."""
from pathlib import Path

RIGS_DIR = Path(__file__).resolve().parent / "rigs"
_ALIGNMENT = ("PairAgreement", "check_calibration", "format_agreement", "neighbour_pairs")


def rig_path(name: str) -> Path:
    """calibration.json of a shipped rig, e.g. 'sample_ring4' (the sample session's 4-camera ring)."""
    path = RIGS_DIR / f"{name}.json"
    if not path.exists():
        known = sorted(p.stem for p in RIGS_DIR.glob("*.json"))
        raise FileNotFoundError(f"no rig {name!r}; shipped rigs: {known}")
    return path


def __getattr__(name):
    # Lazy: importing a submodule (the light `options` of `intercap calibrate --help`) runs this
    # file, and the alignment check imports open3d.
    if name in _ALIGNMENT:
        from intercap.calib import alignment

        return getattr(alignment, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [*_ALIGNMENT, "rig_path", "RIGS_DIR"]
