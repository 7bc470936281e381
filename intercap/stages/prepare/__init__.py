"""Stage 1, `prepare`: world point clouds, the ground plane, the calibration check.

Rooms: config (settings), stage (run, outputs)."""
