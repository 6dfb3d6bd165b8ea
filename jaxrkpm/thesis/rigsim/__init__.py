"""The simulated rig (section 5.3.2 closed in software) and model calibration from rig data.

Unlike the hardware package :mod:`jaxrkpm.rig`, this package depends on the solver core
openly: the physical object and the controller are :class:`jaxrkpm.Model` s, the loop
uses the core's Jacobian and tracking law (:mod:`jaxrkpm.control.tracking`), and calibration
differentiates through the solve (JAX, optax). It drives the hardware package's stereo
pipeline, frames and robot link with synthetic images and a simulated robot.

:mod:`.sim`: the closed loop (vision -> object frame -> controller -> robot link ->
physical object). :mod:`.calibrate`: fitting material parameters to a recording, and the
Broyden Jacobian correction.
"""

from . import calibrate as _calibrate, sim as _sim
from .calibrate import *  # noqa: F401,F403  (the names in calibrate.__all__)
from .sim import *  # noqa: F401,F403  (the names in sim.__all__)

__all__ = [*_sim.__all__, *_calibrate.__all__]
