"""jaxrkpm: a differentiable meshfree (RKPM) large-deformation solver in JAX, and the robot
manipulation planning built on it.

The public API is the names below (declared once, in ``__init__.pyi``, which type checkers and
IDEs read); they load on first use, so ``jaxrkpm --help`` answers without importing JAX. Power
users reach the pieces underneath through :mod:`jaxrkpm.internal`; the thesis application is
:mod:`jaxrkpm.thesis`, the hardware side of the rig :mod:`jaxrkpm.rig`. The layer folders
(``discretise``, ``mechanics``, ``solvers``, ``model``, ``control``, ``io``, ``sweeps``) are
the implementation.

Importing the package enables float64 in JAX (``jax_enable_x64``: solid mechanics needs it)
and makes BLAS/LAPACK single-threaded (:mod:`jaxrkpm.base.threads` says why;
``JAXRKPM_BLAS_THREADS`` overrides).
"""
import os
import sys

import lazy_loader as _lazy

# float64 before any JAX array exists: if JAX is already imported, switch it now; if not,
# JAX reads JAX_ENABLE_X64 when it is first imported (by any module, ours or the user's)
if "jax" in sys.modules:
    sys.modules["jax"].config.update("jax_enable_x64", True)
else:
    os.environ["JAX_ENABLE_X64"] = "1"

# BLAS threads before any BLAS library loads
from .base import threads as _threads  # noqa: E402

_threads.configure()

__version__ = "0.1.0"

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
