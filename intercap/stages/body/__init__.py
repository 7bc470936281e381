"""The `body` stage: per-frame whole-body fitting to multi-view keypoints and depth (PROX-D).

Rooms: config (settings), observations (what the data gives the fit), terms (the energy table),
fitter (the optimisation), stage (run, chunks, outputs)."""
