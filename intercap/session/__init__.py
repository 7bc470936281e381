"""The session contract (docs/session_format.md): reading a capture session folder, checking it,
and the OpenPose keypoint files it may carry. `Session.load` is the entry point."""
from intercap.session.format import CameraInfo, GroundTruth, ObjectInfo, load_mesh_file
from intercap.session.openpose import NUM_KEYPOINTS_2D, NUM_KEYPOINTS_3D, OPENPOSE_PARTS, openpose_to_array
from intercap.session.problems import Problem, SessionError
from intercap.session.session import Session
from intercap.session.validate import format_report, validate

__all__ = ["NUM_KEYPOINTS_2D", "NUM_KEYPOINTS_3D", "OPENPOSE_PARTS", "openpose_to_array", "Problem", "SessionError",
           "CameraInfo", "GroundTruth", "ObjectInfo", "load_mesh_file", "Session", "format_report", "validate"]
