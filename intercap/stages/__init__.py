"""The pipeline's stages, one module each, in run order: prepare, detect, object, body,
contact, global_fit (the `global` stage). A stage reads the session and earlier stages'
saved results and writes its own under OUT/<stage>/. Stages may use geometry, energies,
session, io and body_models (and, for shared observation code, an earlier stage); nothing
outside the runner, the CLI and the tools imports a stage."""
