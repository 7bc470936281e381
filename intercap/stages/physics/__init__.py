"""Stage 7, `physics`: contact forces, joint torques and free flight from the 4D result.

Rooms: config (settings), stage (run, outputs)."""
