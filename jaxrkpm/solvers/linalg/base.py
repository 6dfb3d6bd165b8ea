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

``rhs`` is (Nf, d) or (Nf, d, m). One factorisation thus serves a Newton predictor, chord
corrections and implicit Jacobians, for every solver alike.
"""
from __future__ import annotations

from typing import Any

from ...base.outcome import Outcome


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

    def update(self, state, s, y, accept=True):
        """The state after a correction s with residual change y (a secant pair): unchanged,
        except for solvers that learn from them (``QuasiNewton``)."""
        return state
