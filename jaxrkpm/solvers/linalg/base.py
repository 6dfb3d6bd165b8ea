"""The linear-solver interface of the Newton iteration, with explicit state (in the manner of
lineax), and what a factorisation reports of the matrix.

A solver is a static, immutable description (part of the jit configuration); everything that
changes between calls is its *state*, a pytree returned and passed explicitly::

    state = solver.init(problem, blocks)       # factorise the tangent given as pair blocks
    state = solver.state_at(problem, u, g, load)   # the same at a state (u, g, load)
    x = solver.solve(state, rhs)               # K_ff x = rhs with that factorisation
    solver.stability(state)                    # Stability: STABLE / UNSTABLE / UNKNOWN / FAILED
    solver.negative_eigenvalues(state)         # inertia of K_ff (-1: unknown)
    x, state, stab = solver.newton_solve(state, problem, blocks, rhs, rtol)
                                               # a Newton step with the current tangent, reusing
                                               # ``state`` where the solver can
    state = solver.update(state, s, y, accept)  # learn from a secant pair (quasi-Newton)
    solver.work(state)                         # LinearStats: the work of the call that made it

``rhs`` is (Nf, d) or (Nf, d, m). One factorisation thus serves a Newton predictor, chord
corrections and implicit Jacobians, for every solver alike.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ...base.outcome import Outcome


class LinearStats(NamedTuple):
    """The linear algebra a solve did, returned with its result (``Solution.stats``,
    ``NewtonResult.stats``, ``TrackResult.stats``, ``EquilibriumPath.stats``): 0-d arrays
    (stacked by batched solves); ``a + b`` adds two up field by field.

    Counted by the nonlinear solver from what each linear call returns (``LinearSolver.work``),
    so they belong to that solve alone. Host seconds are measured by the host-side solvers
    (sparse, Krylov) and are 0 on the dense path, which runs inside XLA. The branch switch's
    eigenpairs and shifted factorisations (``jaxrkpm.solvers.branch``) are its own and not
    counted; nor are the host seconds of a solve with a kept factorisation (``solve`` returns
    no state), which counts as a solve."""

    factorisations: Any = 0    # factorisations made (Krylov: multigrid hierarchies built)
    refactorisations: Any = 0  # of which made again from their blocks after eviction from the host
    solves: Any = 0            # linear solves the nonlinear solver asked for
    cg_solves: Any = 0         # host conjugate-gradient solves (one per right-hand side)
    cg_iterations: Any = 0     # their iterations
    factorise_s: Any = 0.0     # host seconds factorising (Krylov: building hierarchies)
    triangular_s: Any = 0.0    # host seconds in triangular solves with a factorisation
    cg_s: Any = 0.0            # host seconds of CG's own work (products, updates)
    matrix_s: Any = 0.0        # host seconds making sparse matrices from the tangent blocks

    @staticmethod
    def of(**counts) -> "LinearStats":
        """Zero work but ``counts`` (field name -> value), as 0-d arrays (int64 counts,
        float64 seconds)."""
        return LinearStats(*(jnp.asarray(counts.get(name, default), jnp.result_type(default, jnp.int64))
                             for name, default in LinearStats._field_defaults.items()))

    @staticmethod
    def shape_dtypes() -> "LinearStats":
        """The ``jax.ShapeDtypeStruct`` of each field (a host callback's result type)."""
        return LinearStats(*(jax.ShapeDtypeStruct((), v.dtype) for v in LinearStats.of()))

    def __add__(self, other: "LinearStats") -> "LinearStats":
        """Field by field (not tuple concatenation)."""
        return LinearStats(*(a + b for a, b in zip(self, other)))

    def as_dict(self) -> dict:
        """Plain numbers by field name (for records)."""
        return {k: (float(v) if k.endswith("_s") else int(v)) for k, v in self._asdict().items()}


class Stability(Outcome):
    """What a factorisation says of K_ff (inside jit: the int code)."""

    STABLE = 0, "K_ff is positive definite (a stable equilibrium)"
    UNSTABLE = 1, "K_ff has negative eigenvalues (a limit or bifurcation point was passed)"
    UNKNOWN = 2, ("the factorisation could not tell the inertia of K_ff (pivots were perturbed "
                  "or permuted): stability is unknown")
    FAILED = 3, ("the iterative linear solve did not converge (the Krylov solver): the Newton "
                 "step is not trusted")


class LinearSolver:
    """The interface every linear solver implements (subclasses are frozen dataclasses): a
    solver written outside the package that implements ``empty``, ``init``, ``solve``,
    ``stability``, ``negative_eigenvalues`` and ``newton_solve`` serves ``Model(solver=...)``,
    the load path, the implicit Jacobians and tracking like the built-in ones. The model,
    path and tracking code never test a solver's type: what they may do with one is said by
    these capabilities (class attributes).

    ``name``: for messages and records. ``tight_rtol``: the relative residual of an iterative
    solver's accurate solves (None: direct solves, exact). ``modified_newton``: a factorisation
    of this solver may serve later Newton iterations as it is (modified Newton keeps it while
    the iteration contracts, and a control loop keeps it across steps); the sparse and Krylov
    solvers reuse theirs as a preconditioner inside ``newton_solve`` instead.
    ``branch_switching``: its stability report is exact and the dense tangent's eigenpairs
    are affordable at the sizes it serves, so solves may go on past a critical point
    (``jaxrkpm.solvers.branch``)."""

    name: str = "linear"
    tight_rtol: float | None = None
    modified_newton: bool = False
    branch_switching: bool = False

    def empty(self, problem, dtype) -> Any:
        """A state of the right shapes that factorises nothing (a loop's initial carry)."""
        raise NotImplementedError

    def init(self, problem, blocks) -> Any:
        """The factorisation of K_ff given as (P, d, d) pair blocks."""
        raise NotImplementedError

    def state_at(self, problem, u, g, load=1.0) -> Any:
        """The factorisation of K_ff at the state (u, g) and load scale ``load`` (a follower
        load's tangent depends on it)."""
        return self.init(problem, problem.tangent_blocks(u, g, load))

    def solve(self, state, rhs):
        """K_ff x = rhs with the factorisation ``state``."""
        raise NotImplementedError

    def stability(self, state):
        """The Stability code of a factorisation."""
        raise NotImplementedError

    def negative_eigenvalues(self, state):
        """Negative eigenvalues of K_ff (-1 where the solver cannot count them)."""
        raise NotImplementedError

    def newton_solve(self, state, problem, blocks, rhs, rtol=None):
        """A Newton step with the tangent ``blocks``: (x, new state, stability); ``rtol`` the
        relative residual an iterative solver may stop at (the inexact-Newton forcing term)."""
        raise NotImplementedError

    def work(self, state) -> LinearStats:
        """The work of the call (``init``, ``state_at`` or ``newton_solve``) that returned
        ``state``, without the solve itself (the nonlinear solver counts its solves): one
        factorisation by default, as a direct solver makes at each. Solvers that may reuse a
        factorisation, or that measure host time, carry their own in the state."""
        return LinearStats.of(factorisations=1)

    def update(self, state, s, y, accept=True):
        """The state after a correction s with residual change y (a secant pair): unchanged,
        except for solvers that learn from them (``QuasiNewton``)."""
        return state
