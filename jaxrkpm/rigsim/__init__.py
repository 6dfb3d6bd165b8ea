"""The simulated rig (section 5.3.2 closed in software) and model calibration from rig data.

Unlike the hardware package :mod:`jaxrkpm.rig`, this package depends on the solver core
openly: the physical object and the controller are :class:`jaxrkpm.Model` s, the loop
uses the core's Jacobian and tracking law (:mod:`jaxrkpm.control`), and calibration
differentiates through the solve (JAX, optax). It drives the hardware package's stereo
pipeline, frames and robot link with synthetic images and a simulated robot.

:mod:`.sim`: the closed loop (vision -> object frame -> controller -> robot link ->
physical object). :mod:`.calibrate`: fitting material parameters to a recording, and the
Broyden Jacobian correction.
"""

from .calibrate import CalibrationResult, Recording, broyden_update, calibrate, predict, region_index
from .sim import (
    CONTROL_POINT,
    ClosedLoop,
    InProcessRobot,
    Inclusion,
    PhysicalObject,
    RigGeometry,
    RigRun,
    RigSettings,
    RigStatus,
    Vision,
    planar_object,
)

__all__ = [
    # sim
    "CONTROL_POINT", "Inclusion", "planar_object", "PhysicalObject", "RigGeometry", "Vision",
    "InProcessRobot", "RigSettings", "RigStatus", "RigRun", "ClosedLoop",
    # calibrate
    "Recording", "CalibrationResult", "predict", "calibrate", "region_index", "broyden_update",
]
