"""Stage 3, `object`: per-frame 6-DoF object tracking by silhouette and depth rendering.

Rooms: config (settings), observations (what the data gives the fit), terms (the energy table),
fitter (the optimisation), stage (run, chunks, outputs)."""
