"""Camera rigs: the calibration check that aligns neighbouring cameras' point clouds."""
from calib.alignment import PairAgreement, check_calibration, format_agreement, neighbour_pairs

__all__ = ["PairAgreement", "check_calibration", "format_agreement", "neighbour_pairs"]
