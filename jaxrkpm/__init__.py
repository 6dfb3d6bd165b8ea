"""jaxrkpm: a differentiable meshfree (RKPM) large-deformation solver in JAX.

Importing the package enables float64 in JAX (``jax_enable_x64``): solid mechanics needs it.
"""
import jax

jax.config.update("jax_enable_x64", True)

from . import mesh  # noqa: E402  (meshio / gmsh: reading, checking, shapes; jr.mesh.half_ellipsoid)
from .boundary import Springs  # noqa: E402
from .geometry import Body  # noqa: E402
from .materials import (Fung, Material, NeoHookean, Quadratic,  # noqa: E402
                        SaintVenantKirchhoff, pk2, green_lagrange)
from .model import Model, SolveError  # noqa: E402
from .solve import Solution, Status  # noqa: E402

__all__ = ["mesh", "Body", "Model", "Springs", "Solution", "Status", "SolveError", "Material", "Quadratic", "Fung",
           "SaintVenantKirchhoff", "NeoHookean", "pk2", "green_lagrange"]
__version__ = "0.1.0"
