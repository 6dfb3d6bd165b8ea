"""jaxrkpm: a differentiable meshfree (RKPM) large-deformation solver in JAX.

Importing the package enables float64 in JAX (``jax_enable_x64``): solid mechanics needs it,
and makes BLAS/LAPACK single-threaded (``jaxrkpm.threads``; ``JAXRKPM_BLAS_THREADS`` overrides).
The package itself imports no JAX: its public names (``jaxrkpm.Model``, ...) and submodules
(``jaxrkpm.control``, ...) load on first use, so the command line (``jaxrkpm --help``)
answers without the seconds a JAX import takes.
"""
import importlib
import importlib.util
import os
import sys

# float64 before any JAX array exists: if JAX is already imported, switch it now; if not,
# JAX reads JAX_ENABLE_X64 when it is first imported (by any module, ours or the user's)
if "jax" in sys.modules:
    sys.modules["jax"].config.update("jax_enable_x64", True)
else:
    os.environ["JAX_ENABLE_X64"] = "1"

# BLAS threads before any BLAS library loads (jaxrkpm.threads says why; JAXRKPM_BLAS_THREADS
# overrides)
from . import threads as _threads  # noqa: E402

_threads.configure()

__version__ = "0.1.0"

# public name -> the submodule that defines it (loaded on first access)
_PUBLIC = {
    "Springs": "boundary", "Body": "geometry",
    "Fung": "materials", "Material": "materials", "NeoHookean": "materials", "Quadratic": "materials",
    "SaintVenantKirchhoff": "materials", "pk2": "materials", "green_lagrange": "materials",
    "det": "materials",
    "Model": "model", "SolveError": "model", "Solution": "solve", "Status": "solve",
    "arc_length": "continuation", "point_load": "continuation", "EquilibriumPath": "continuation",
    "PathStatus": "continuation",
}

__all__ = ["mesh", "Body", "Model", "Springs", "Solution", "Status", "SolveError", "Material", "Quadratic", "Fung",
           "SaintVenantKirchhoff", "NeoHookean", "pk2", "green_lagrange", "det", "arc_length", "point_load",
           "EquilibriumPath", "PathStatus"]


def __getattr__(name):
    """``jaxrkpm.Model`` and the other public names, and submodules (``jaxrkpm.control``),
    imported when first asked for (PEP 562)."""
    if name in _PUBLIC:
        value = getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
        globals()[name] = value
        return value
    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted([*globals(), *_PUBLIC])
