"""The `export` stage: meshes per frame, one self-describing dataset file, and.

Rooms: config (settings), stage (run, outputs)."""
