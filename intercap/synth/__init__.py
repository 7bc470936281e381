"""The synthetic session generator behind `intercap synth`: scripted whole-body motions
(motions.py) handling rigid objects (objects.py), rendered into N calibrated RGB-D cameras
with sensor noise, written in the session format with exact ground truth (generator.py)."""
from intercap.synth.generator import PRESETS, SynthConfig, apply_preset, generate_session

__all__ = ["PRESETS", "SynthConfig", "apply_preset", "generate_session"]
