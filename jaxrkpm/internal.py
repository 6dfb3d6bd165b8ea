"""The pieces under the public API, for power users: the discrete problem as a jit-friendly
pytree, the terms of the energy it sums (and what a new term is written with), the solver
objects (Newton, chord, load path, stable-branch descent, arc length), the contract they
implement and their one iteration loop, the linear solvers with explicit state, implicit derivatives, batching of
many problems, and the building blocks of the tracking loop.

These names are supported, but they follow the implementation more closely than
:mod:`jaxrkpm`'s and may change with it; the modules they come from are private.
"""
from .base.outcome import Outcome
from .base.programs import memory_mappings, release_compiled_programs
from .control.batching import batch_axes, default_batching, map_batch, run_batched, stack_models
from .control.tracking import ControlledModel, Tracker, predicted_change, response_trend, track_loop
from .discretise.constraints import EssentialSets, Transformation
from .mechanics.constraint import Essential
from .mechanics.contact import ContactTerm
from .mechanics.loads import DeadLoad, SpringTerm
from .mechanics.pressure import PressureTerm
from .mechanics.problem import Problem
from .mechanics.strain import StrainEnergy
from .mechanics.term import Context, Pairs, Term, TermSpec, static, term
from .model.model import SolverChoice
from .model.solving import BranchOnDemand, Direct
from .solvers.branch import BranchSwitch, StableDescent
from .solvers.continuation import ArcLength, ArcLengthPath
from .solvers.implicit import implicit_jacobian, point_jacobian, response, sensitivity, solve_path_diff
from .solvers.iterate import IterativeSolver, iterate, run
from .solvers.linalg.base import LinearSolver, LinearStats
from .solvers.linalg.dense import DenseSolver
from .solvers.linalg.host import host_callback
from .solvers.linalg.krylov import KrylovSolver
from .solvers.linalg.quasi_newton import QuasiNewton
from .solvers.linalg.sparse import SparseSolver
from .solvers.minimise import minimise, stable_beyond
from .solvers.newton import Chord, Newton, NewtonResult, Tolerance
from .solvers.path import LoadPath
from .solvers.results import Critical, Limits

__all__ = [
    "Outcome", "memory_mappings", "release_compiled_programs",
    "batch_axes", "default_batching", "map_batch", "run_batched", "stack_models",
    "ControlledModel", "Tracker", "predicted_change", "response_trend", "track_loop",
    "EssentialSets", "Transformation",
    "Essential", "ContactTerm", "DeadLoad", "SpringTerm", "PressureTerm", "Problem", "StrainEnergy",
    "Context", "Pairs", "Term", "TermSpec", "static", "term",
    "SolverChoice", "Direct", "BranchOnDemand",
    "BranchSwitch", "StableDescent", "ArcLength", "ArcLengthPath",
    "implicit_jacobian", "point_jacobian", "response", "sensitivity", "solve_path_diff",
    "IterativeSolver", "iterate", "run",
    "LinearSolver", "LinearStats", "DenseSolver", "host_callback", "KrylovSolver", "QuasiNewton", "SparseSolver",
    "minimise", "stable_beyond",
    "Chord", "Newton", "NewtonResult", "Tolerance", "LoadPath",
    "Critical", "Limits",
]
