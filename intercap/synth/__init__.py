"""The synthetic session generator behind `intercap synth`: scripted whole-body motions
(motions.py) handling rigid objects (objects.py), rendered into N calibrated RGB-D cameras
with sensor noise, written in the session format with exact ground truth (generator.py)."""

__all__ = ["PRESETS", "SynthConfig", "apply_preset", "generate_session"]


def __getattr__(name):
    # Lazy: importing a submodule (the light `options` of `intercap synth --help`) runs this file,
    # and the generator imports torch, trimesh and pyrender.
    if name in ("PRESETS", "SynthConfig", "apply_preset"):
        from intercap.synth import options

        return getattr(options, name)
    if name == "generate_session":
        from intercap.synth.generator import generate_session

        return generate_session
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
