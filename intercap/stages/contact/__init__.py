"""Stage 5, `contact`: which frames have body-object contact, and which body regions touch.

Rooms: config (settings), stage (run, outputs)."""
