"""The linear solver a model takes: ``Model(solver=...)`` as a string chosen by size and
device (``SolverChoice``), or a ``LinearSolver`` instance used as given.
"""
from __future__ import annotations

from dataclasses import dataclass

import jax
import numpy as np

from ..discretise.discretisation import Discretisation
from ..mechanics.build import Assembled
from ..solvers.linalg.base import LinearSolver
from ..solvers.linalg.dense import DenseSolver
from ..solvers.linalg.factorisations import SaddlePointSystem, factoriser
from ..solvers.linalg.krylov import KrylovSolver
from ..solvers.linalg.multigrid import KrylovSystem
from ..solvers.linalg.sparse import SparseSolver

SOLVERS = ("auto", "dense", "sparse", "krylov")   # Model(solver=...)
PRECISIONS = ("auto", "double", "mixed")          # Model(precision=...): dense and PARDISO factorisations


@dataclass(frozen=True)
class SolverChoice:
    """How a Model chooses its solvers where the user leaves it to it (``solver="auto"``,
    ``precision="auto"``, ``reuse=None``), each choice a field (a test or a user gives
    another value by passing ``Model(..., choice=SolverChoice(...))``).

    dense_2d, dense_3d   free DOFs up to which "auto" takes the dense factorisation on a CPU.
                         3D: where one Newton iteration's linear work (assemble, factorise,
                         solve) costs the same dense and sparse (PARDISO)
                         (``experiments/bench_cube3d.py --only-crossover``). 2D stays higher
                         although sparse wins earlier there, because the stable-branch and
                         modified-Newton options are dense-only.
    mixed_min            free DOFs from which "auto" factorises dense K_ff in single precision
                         and refines its solves in double: where the Cholesky factorisation is
                         most of a Newton iteration (``experiments/bench_cube3d.py --precision``);
                         below it the 2D models and their stability studies stay in double.
    dense_copies, accelerator_dense
                         on an accelerator the sparse paths are host callbacks and the dense one
                         runs on the device, so "auto" goes dense while about ``dense_copies``
                         n^2 doubles fit in its memory (``accelerator_dense`` free DOFs where the
                         device does not report it).
    newton_reuse         modified Newton's ``reuse`` for an eager solve on the dense path: a
                         kept factorisation while each step cuts |r| by this factor (same
                         residual tolerance, fewer factorisations:
                         ``experiments/bench_cube3d.py``). Not under jit/vmap: a vmapped
                         lax.cond evaluates both branches, so lock-step members would assemble
                         at every iteration and iterate more."""

    dense_2d: int = 2500
    dense_3d: int = 4400
    mixed_min: int = 1000
    dense_copies: int = 4
    accelerator_dense: int = 20_000
    newton_reuse: float = 0.1

    def dense_limit(self, dim: int, device=None) -> int:
        """Free DOFs up to which ``solver="auto"`` takes the dense path on ``device`` (default:
        JAX's first device): ``dense_2d``/``dense_3d`` on a CPU; on a GPU/TPU as many as
        ``dense_copies`` dense n x n float64 matrices fit in its memory."""
        cpu = self.dense_2d if dim == 2 else self.dense_3d
        device = jax.devices()[0] if device is None else device
        if device.platform == "cpu":
            return cpu
        try:
            memory = (device.memory_stats() or {}).get("bytes_limit")
        except (AttributeError, NotImplementedError, RuntimeError):   # no memory statistics there
            memory = None
        if not memory:
            return max(self.accelerator_dense, cpu)
        return max(int((memory / (8 * self.dense_copies)) ** 0.5), cpu)


def check_options(solver, factorisation: str, precision: str, choice: SolverChoice) -> None:
    """The linear-solver options of ``Model``, checked before anything is built."""
    if not isinstance(solver, LinearSolver) and solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}: choose " + ", ".join(repr(k) for k in SOLVERS)
                         + ", or pass a jaxrkpm.internal.LinearSolver instance")
    factoriser(factorisation)   # a clear error now, even where the dense path is chosen
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}: choose "
                         + ", ".join(repr(k) for k in PRECISIONS))
    if not isinstance(choice, SolverChoice):
        raise ValueError(f"choice must be a SolverChoice, got {type(choice).__name__}")


def linear_solver(disc: Discretisation, built: Assembled, solver="auto", factorisation: str = "auto",
                  precision: str = "auto", choice: SolverChoice = SolverChoice()) -> LinearSolver:
    """The model's linear solver (the options as ``Model``'s)."""
    check_options(solver, factorisation, precision, choice)
    if isinstance(solver, LinearSolver):   # the user's own, used as given
        return solver
    d, partial = disc.body.dim, disc.sets.partial
    if partial and solver in ("sparse", "krylov"):
        raise ValueError(f"solver {solver!r} does not take Roller sets (held components) yet: use "
                         "solver='dense' or 'auto'")
    n_free = len(disc.sets.free) * d
    if solver == "dense" or (solver == "auto" and (partial or n_free <= choice.dense_limit(d))):
        return DenseSolver(mixed=precision == "mixed" or (precision == "auto" and n_free >= choice.mixed_min))
    if solver == "krylov":
        return KrylovSolver(KrylovSystem(disc.body.X, built.pair_i, built.pair_j, disc.constraint_matrix(),
                                         disc.sets.free, disc.sets.bnd))
    return sparse_solver(disc, built, factorisation, precision)


def sparse_solver(disc: Discretisation, built: Assembled, factorisation: str, precision: str) -> SparseSolver:
    """The sparse saddle-point solver over the tangent's pattern and the essential constraint."""
    d = disc.body.dim
    a, b = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
    rows = (built.pair_i[:, None, None] * d + a[None]).ravel()
    cols = (built.pair_j[:, None, None] * d + b[None]).ravel()
    free_dofs = (disc.sets.free[:, None] * d + np.arange(d)[None]).ravel()
    return SparseSolver(SaddlePointSystem(disc.body.X, rows, cols, disc.constraint_matrix(), free_dofs,
                                          disc.sets.bnd, d, factorisation, precision))
