"""The pieces under the public API, for power users: the discrete problem as a jit-friendly
pytree, the Newton solver and load stepping as functions, the linear solvers with explicit
state, implicit derivatives, batching of many problems, and the building blocks of the
tracking loop.

These names are supported, but they follow the implementation more closely than
:mod:`jaxrkpm`'s and may change with it; the modules they come from are private.
"""
from .base.outcome import Outcome
from .base.programs import memory_mappings, release_compiled_programs
from .control.batching import batch_axes, default_batching, map_batch, run_batched, stack_models
from .control.tracking import ControlledModel, predicted_change, response_trend, track_loop
from .discretise.constraints import EssentialSets, Transformation
from .mechanics.assembly import Ops, Params, coefficients, dense_tangent, pair_blocks, point_values
from .model.model import dense_limit
from .solvers.config import Config
from .solvers.implicit import point_jacobian, response, sensitivity, solve_path_diff
from .solvers.linalg.base import Stability
from .solvers.linalg.dense import DenseSolver
from .solvers.linalg.host import host_callback
from .solvers.linalg.krylov import KrylovSolver
from .solvers.linalg.quasi_newton import QuasiNewton
from .solvers.linalg.sparse import SparseSolver
from .solvers.minimise import minimise, stable_beyond
from .solvers.newton import newton
from .solvers.path import solve_path
from .solvers.problem import Problem
from .solvers.results import Critical, Limits

__all__ = [
    "Outcome", "memory_mappings", "release_compiled_programs",
    "batch_axes", "default_batching", "map_batch", "run_batched", "stack_models",
    "ControlledModel", "predicted_change", "response_trend", "track_loop",
    "EssentialSets", "Transformation",
    "Ops", "Params", "coefficients", "dense_tangent", "pair_blocks", "point_values",
    "dense_limit",
    "Config",
    "point_jacobian", "response", "sensitivity", "solve_path_diff",
    "Stability", "DenseSolver", "host_callback", "KrylovSolver", "QuasiNewton", "SparseSolver",
    "minimise", "stable_beyond", "newton", "solve_path", "Problem", "Critical", "Limits",
]
