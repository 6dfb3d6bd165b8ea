"""How a model's solve runs, as objects: the path solver (a ``LoadPath`` from the ``solve``
options, or the caller's own), the plan that runs it (``Direct``, or ``BranchOnDemand``: a
branch switch only where the plain path stops at a critical point) and the mode of the
call (``Eager`` keeps the linear solver's state and ramps changed parameters; ``Traced``,
under jit/vmap/derivatives, does neither).

A path solver is a static (hashable) object with ``linear`` (its ``LinearSolver``, which the
implicit derivatives use) and ``solve(problem, lim, u0, g0, g1, l0, l1, state0, params0) ->
Solution`` (the equilibrium at (g1, l1) reached from (u0, g0, l0); see ``LoadPath.solve``),
usually ``iterate`` over its ``init`` / ``step`` / ``terminate``.
"""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics.contact import ContactPenetrationWarning, ContactTerm, penetration
from ..mechanics.problem import Problem
from ..solvers.branch import BranchSwitch, StableDescent
from ..solvers.implicit import solve_path_jit
from ..solvers.linalg.base import LinearSolver
from ..solvers.newton import Newton, Tolerance
from ..solvers.path import LoadPath
from ..solvers.results import Limits, Solution, Status, joined
from .inputs import concrete, is_concrete

# the options of ``Model.solve``: fields of the solver objects (``Model.solver``)
NEWTON_OPTIONS = ("line_search", "armijo", "reuse", "check_stability")
SOLVER_OPTIONS = ("rtol", *NEWTON_OPTIONS, "easy", "growth", "locate", "stable_branch")


class SolveError(RuntimeError):
    """A solve did not converge; ``.solution`` holds the last converged state."""

    def __init__(self, solution: Solution):
        super().__init__(solution.message)
        self.solution = solution


def load_path(linear: LinearSolver, **options) -> LoadPath:
    """A ``LoadPath`` over a ``Newton`` with ``linear`` from the ``solve`` options (each a
    field of the object it tunes; ``stable_branch`` True: a ``BranchSwitch`` past critical
    points); see ``Model.solver``."""
    unknown = set(options) - set(SOLVER_OPTIONS)
    if unknown:
        raise ValueError(f"unknown solver option(s) {sorted(unknown)}; the options are {list(SOLVER_OPTIONS)}")
    options = dict(options)
    stable_branch = options.pop("stable_branch", False)
    if not isinstance(stable_branch, (bool, np.bool_)):
        raise ValueError(f"stable_branch must be True, False or None (automatic), got {stable_branch!r}")
    tolerance = Tolerance(options.pop("rtol")) if "rtol" in options else Tolerance()
    newton = Newton(linear, tolerance, **{k: options.pop(k) for k in NEWTON_OPTIONS if k in options})
    branch = None
    if stable_branch:
        branch = BranchSwitch(StableDescent(tolerance, newton.line_search, newton.armijo))
    return LoadPath(newton, branch=branch, **options)


class Request(NamedTuple):
    """One solve asked of a model: from the equilibrium ``start`` to the prescribed values
    ``g`` and load scale ``loads`` of ``problem``, within ``lim``."""

    problem: Problem
    lim: Limits
    start: Solution
    g: jax.Array
    loads: jax.Array


def params_at(p0, p1, t):
    """The parameters at the fraction t of a path that ramps them from p0 to p1 (None: p0 None)."""
    if p0 is None:
        return None
    t = float(t)
    return jax.tree.map(lambda a, b: b if t >= 1.0 or not jnp.issubdtype(jnp.result_type(b), jnp.inexact)
                        else a + t * (b - a), p0, p1)


def ramped_from(start: Solution, problem: Problem):
    """The parameters that ``start`` was solved with where they differ from ``problem``'s (then
    the path ramps them, so that step cutting shrinks a pose change made at a converged
    state); None where they are the same, unknown or of another model."""
    p0 = start.params
    if p0 is None or jax.tree.structure(p0) != jax.tree.structure(problem.params):
        return None
    pairs = list(zip(jax.tree.leaves(p0), jax.tree.leaves(problem.params)))
    if any(np.shape(a) != np.shape(b) for a, b in pairs):
        return None
    if all(a is b or np.array_equal(np.asarray(a), np.asarray(b)) for a, b in pairs):
        return None
    return p0


def kept_linear(linear: LinearSolver, sol: Solution, problem: Problem):
    """``sol.linear`` where it is a state of ``linear`` on this problem (a Solution of another
    model, or one that kept none: None)."""
    state = sol.linear
    if state is None:
        return None
    want = jax.eval_shape(lambda: linear.empty(problem, jnp.float64))
    if jax.tree.structure(state) != jax.tree.structure(want):
        return None
    same = all(np.shape(a) == b.shape and jnp.result_type(a) == b.dtype
               for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(want)))
    return state if same else None


@dataclass(frozen=True)
class Eager:
    """A solve with concrete inputs: its path solver keeps the linear solver's last state in
    the Solution, and starts from the one the initial Solution kept (the predictor of modified
    Newton, the sparse path's preconditioner and the implicit Jacobian at the new state need
    no factorisation of their own: ``experiments/bench_cube3d.py``'s public-API control step;
    an empty state where none is kept, so the first and the warm-started solves share one
    compiled program); parameters changed since the initial Solution are ramped along the
    path; ``reuse``: Newton's where the options give none (``Model.newton_reuse``)."""

    reuse: float = 0.0

    def driver(self, driver):
        """``driver`` keeping the linear state, where it has that field."""
        if dataclasses.is_dataclass(driver) and "keep_linear" in {f.name for f in dataclasses.fields(driver)}:
            return dataclasses.replace(driver, keep_linear=True)
        return driver

    def state0(self, driver, request: Request):
        kept = kept_linear(driver.linear, request.start, request.problem)
        return driver.linear.empty(request.problem, jnp.float64) if kept is None else kept

    def params0(self, request: Request):
        return ramped_from(request.start, request.problem)

    def finish(self, sol: Solution, request: Request, params0) -> Solution:
        """The parameters where the path stopped: the start of the next solve's ramp."""
        return sol._replace(params=params_at(params0, request.problem.params, sol.t) or request.problem.params)


@dataclass(frozen=True)
class Traced:
    """A solve under jit, vmap or a derivative: full Newton (a vmapped lax.cond evaluates both
    branches, so lock-step members would assemble at every iteration and iterate more), no
    linear state kept (it would be stacked or differentiated for nothing), no ramp."""

    reuse: float = 0.0

    def driver(self, driver):
        return driver

    def state0(self, driver, request: Request):
        return None

    def params0(self, request: Request):
        return None

    def finish(self, sol: Solution, request: Request, params0) -> Solution:
        return sol


def mode_of(reuse: float, *inputs) -> Eager | Traced:
    """``Eager`` (with Newton ``reuse``) where every leaf of the solve's ``inputs`` (its
    prescribed values, loads, parameters, initial Solution) is concrete, else ``Traced``."""
    return Eager(reuse) if all(map(is_concrete, jax.tree.leaves(inputs))) else Traced()


def path_solve(driver, request: Request, start: Solution, state0, params0, solve=solve_path_jit) -> Solution:
    """``driver``'s path from ``start`` to the request's end, differentiable (``solve``)."""
    return solve(driver, request.problem, request.lim, start.u, start.g, request.g,
                 jnp.asarray(start.load, jnp.float64), request.loads, state0, params0)


@dataclass(frozen=True)
class Direct:
    """One path solver from the start to the end."""

    driver: Any

    def run(self, request: Request, mode, solve=solve_path_jit) -> Solution:
        driver = mode.driver(self.driver)
        params0 = mode.params0(request)
        sol = path_solve(driver, request, request.start, mode.state0(driver, request), params0, solve)
        return mode.finish(sol, request, params0)


@dataclass(frozen=True)
class BranchOnDemand:
    """The plain path; only where it stops at a critical point (UNSTABLE_TANGENT, its status
    known here: not under jit) does the rest run with the ``branching`` path from the last
    stable state, so the stable-branch solve's longer compile is paid on first need."""

    plain: LoadPath
    branching: LoadPath

    def run(self, request: Request, mode, solve=solve_path_jit) -> Solution:
        driver = mode.driver(self.plain)
        params0 = mode.params0(request)
        sol = path_solve(driver, request, request.start, mode.state0(driver, request), params0, solve)
        if self.branching.switches and concrete(sol.status) == Status.UNSTABLE_TANGENT:
            rest = path_solve(mode.driver(self.branching), request, sol, None,
                              params_at(params0, request.problem.params, sol.t), solve)
            sol = joined(sol, rest)
        return mode.finish(sol, request, params0)


def plan(linear: LinearSolver, options: dict, mode, solver=None) -> Direct | BranchOnDemand:
    """How a solve runs: the caller's ``solver`` (a path solver or a plan) as it is, else the
    model's ``LoadPath`` from the ``options`` (``reuse`` None: the mode's; ``stable_branch``
    None: ``BranchOnDemand``)."""
    if solver is not None:
        if options:
            raise ValueError(f"the solve options {sorted(options)} tune the model's own solver: with "
                             "solver=... set them as fields of that solver")
        return solver if isinstance(solver, (Direct, BranchOnDemand)) else Direct(solver)
    options = dict(options)
    if options.get("reuse") is None:
        options["reuse"] = mode.reuse
    if options.get("stable_branch", None) is not None:
        return Direct(load_path(linear, **options))
    options.pop("stable_branch", None)
    return BranchOnDemand(load_path(linear, **options), load_path(linear, **options, stable_branch=True))


def check_penetration(problem: Problem, sol: Solution) -> None:
    """Warn where a converged solve left contact points inside a tool: its status says
    CONVERGED, but the contact it describes is not what the tool allows."""
    terms = [t for t in problem.terms if isinstance(t, ContactTerm)]
    if not terms:
        return
    d = problem.constraint.coefficients(sol.u, sol.g)
    for t in terms:
        gap = penetration(t, d, sol.load)
        if gap < 0:
            warnings.warn(f"the solve converged with points of contact {t.name!r} inside the tool (min gap "
                          f"{gap:.3g} < 0): raise Contact.pressure, or take more load steps (steps=...), "
                          "and check contact_forces(...).min_gap", ContactPenetrationWarning, stacklevel=5)


def outcome(sol: Solution, request: Request, mode, throw: bool) -> Solution:
    """``sol``, or a SolveError where it failed and ``throw`` (under jax.jacfwd / jax.grad the
    fields are tracers: the error carries their values); a converged eager solve is checked
    for tool penetration."""
    status = concrete(sol.status)
    if throw and status is not None and not Status.of(status).equilibrium:
        raise SolveError(Solution(*jax.tree.map(concrete, tuple(sol))))
    if isinstance(mode, Eager) and status is not None and Status.of(status).equilibrium:
        check_penetration(request.problem, sol)
    return sol
