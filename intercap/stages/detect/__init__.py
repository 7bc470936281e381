"""Stage 2 (detect): whole-body 2D keypoints per view, in OpenPose order.

Rooms: config (settings), stage (run, outputs)."""
