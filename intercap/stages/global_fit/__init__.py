"""The `global` stage: body and object over all frames jointly, with contact (InterCap's last step).

Rooms: config (settings), observations (what the data gives the fit), terms (the energy table),
fitter (the optimisation), stage (run, chunks, outputs)."""
