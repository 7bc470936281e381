"""The pipeline's stages, one package each, in run order: prepare, detect, object, body,
contact, global_fit (the `global` stage), physics, export.

Every stage package has the same rooms: `config` (its settings, one what/why line each)
and `stage` (its `run` and the files it writes). The fitting stages (object, body,
global_fit) also have `observations` (what the data gives the fit), `terms` (the declared
energy table: name, energy function, weight setting) and `fitter` (the optimisation), and
they cut a take into chunks with the one chunk runner, `intercap.stages.chunks`.

A stage reads the session and earlier stages' saved results and writes its own under
OUT/<stage>/. Stages may use geometry, energies, session, io and body_models (and, for
shared observation code, an earlier stage); nothing outside the runner, the CLI and the
tools imports a stage. A package's `__init__` imports nothing, so reading the config tree
loads no stage code."""
