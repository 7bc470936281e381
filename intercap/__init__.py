"""intercap: multi-view RGB-D capture of a person handling a rigid object.

Python API::

    import intercap
    session = intercap.Session.load("data_samples/sample")
    metrics = intercap.run("data_samples/sample", "out/sample")          # every built stage
    result = intercap.evaluate("out/sample", "data_samples/sample")      # against ground truth
"""
from __future__ import annotations

__version__ = "0.1.0"


def __getattr__(name):
    # Lazy, so `import intercap` stays light and the CLI starts fast.
    if name in ("Session", "SessionError", "validate"):
        from intercap import session

        return getattr(session, name)
    if name in ("Config", "load_config"):
        from intercap import config

        return getattr(config, name)
    if name == "run":
        from intercap.pipeline import run_pipeline

        return run_pipeline
    if name == "evaluate":
        from intercap.evaluation.evaluate import evaluate

        return evaluate
    raise AttributeError(f"module 'intercap' has no attribute {name!r}")


__all__ = ["Session", "SessionError", "validate", "Config", "load_config", "run", "evaluate"]
