"""Hardware side of the thesis' experimental rig (chapter 4): stereo marker tracking,
coordinate frames and calibration, and the robot link. A side module: it never imports
the jaxrkpm solver core (NumPy, SciPy, OpenCV and the standard library only)."""

from .frames import (
    PivotResult,
    Registration,
    RigidTransform,
    Units,
    arun_registration,
    label_l_markers,
    object_frame_from_l_markers,
    pivot_calibration,
    register_from_three_touches,
)
from .link import (
    MAX_LINE_BYTES,
    PROTOCOL_VERSION,
    LinkClosed,
    LinkError,
    LinkTimeout,
    Pose,
    RemoteError,
    RobotClient,
    SafetyError,
    SafetyLimits,
    SimulatedRobotServer,
    decode_message,
    encode_message,
)
from .stereo import (
    AmbiguousMatchError,
    CalibratedStereo,
    MarkerCountError,
    ParallelStereo,
    StereoFrame,
    StereoTracker,
    auto_threshold,
    detect_blobs,
    draw_blobs,
    match_by_row,
    render_markers,
)

__all__ = [
    # stereo
    "MarkerCountError", "AmbiguousMatchError", "StereoFrame", "auto_threshold", "detect_blobs", "match_by_row",
    "ParallelStereo", "CalibratedStereo", "draw_blobs", "render_markers", "StereoTracker",
    # frames
    "Units", "RigidTransform", "object_frame_from_l_markers", "label_l_markers",
    "PivotResult", "pivot_calibration", "Registration", "arun_registration",
    "register_from_three_touches",
    # link
    "PROTOCOL_VERSION", "MAX_LINE_BYTES", "LinkError", "LinkTimeout", "LinkClosed",
    "RemoteError", "SafetyError", "SafetyLimits", "Pose", "encode_message", "decode_message",
    "SimulatedRobotServer", "RobotClient",
]
