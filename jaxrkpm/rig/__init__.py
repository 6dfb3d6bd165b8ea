"""Hardware side of the thesis' experimental rig (chapter 4): stereo marker tracking
(:mod:`.stereo`), coordinate frames, pivot calibration and registration (:mod:`.frames`) and
the JSON-lines robot link (:mod:`.link`).

Its modules import nothing from the jaxrkpm solver core and not JAX: only the standard
library, NumPy, SciPy, OpenCV and each other (checked on the source by
``tests/rig/test_layering.py``). Importing it as ``jaxrkpm.rig`` still runs the parent
package's ``jaxrkpm/__init__.py`` (which loads JAX and the core); the separation is that no
rig module needs the core, not that Python skips the parent.

The simulated rig and the material calibration, which do use the core, are in
:mod:`jaxrkpm.thesis.rigsim`."""

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
    ProtocolError,
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
    "RemoteError", "ProtocolError", "SafetyError", "SafetyLimits", "Pose", "encode_message", "decode_message",
    "SimulatedRobotServer", "RobotClient",
]
