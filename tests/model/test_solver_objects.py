"""A model's solve modes are objects: a path solver written here, outside the package, runs
through ``iterate`` and through ``Model.solve`` (and its derivative through the implicit
JVP, with the solver's own linear solver); the default plans are the objects the options
name."""
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrkpm.internal import BranchOnDemand, DenseSolver, Direct, IterativeSolver, LinearSolver, run
from jaxrkpm.model.model import SolveError
from jaxrkpm.solvers.results import Critical, Limits, Solution, Status
from tests.problems import block

PUSH = np.array([0.04, 0.01])
PROBE = np.array([[0.5, 0.5], [0.25, 0.75]])


class Goal(NamedTuple):
    g: jax.Array
    load: jax.Array
    max_iter: jax.Array


class State(NamedTuple):
    iteration: jax.Array
    u: jax.Array
    residual: jax.Array
    reference: jax.Array
    status: jax.Array
    max_iter: jax.Array


@dataclass(frozen=True)
class PlainNewton(IterativeSolver):
    """Full Newton straight at the end values (no load steps, no line search, no predictor):
    converged when |r| falls by ``rtol`` from its first value; the package's solver contract
    (``init``, ``step``, ``terminate`` -> (done, status), ``postprocess``)."""

    linear: LinearSolver = DenseSolver()
    rtol: float = 1e-12

    def init(self, problem, goal: Goal, u) -> State:
        r = problem.residual(u, goal.g, goal.load)
        return State(jnp.array(0), u, r, jnp.linalg.norm(r), jnp.array(Status.MAX_ITERATIONS), goal.max_iter)

    def step(self, problem, goal: Goal, s: State) -> State:
        state = self.linear.state_at(problem, s.u, goal.g, goal.load)
        u = s.u - self.linear.solve(state, s.residual)
        r = problem.residual(u, goal.g, goal.load)
        done = jnp.linalg.norm(r) <= self.rtol * s.reference
        status = jnp.where(done, Status.CONVERGED, Status.MAX_ITERATIONS)
        return State(s.iteration + 1, u, r, s.reference, status, s.max_iter)

    def terminate(self, s: State):
        # the status it would have if stopped here: converged, or out of iterations
        done = (s.status == Status.CONVERGED) | (s.iteration >= s.max_iter)
        return done, s.status

    def postprocess(self, problem, goal: Goal, s: State, status) -> Solution:
        ok = status == Status.CONVERGED
        return Solution(s.u, goal.g, goal.load, status, jnp.where(ok, 1.0, 0.0), s.iteration, jnp.array(1),
                        jnp.array(0), jnp.linalg.norm(s.residual), jnp.array(0), Critical.empty(s.u))

    def solve(self, problem, lim: Limits, u0, g0, g1, l0, l1, state0=None, params0=None) -> Solution:
        return run(self, problem, Goal(g1, jnp.asarray(l1, jnp.float64), lim.max_iter), u0)


@pytest.fixture(scope="module")
def square():
    _, _, model = block(5)
    return model


def test_a_solver_written_outside_the_package_runs_through_iterate_and_model(square):
    solver = PlainNewton(square.linear)
    sol = square.solve({"right": PUSH}, solver=solver)
    assert sol.outcome == Status.CONVERGED and int(sol.steps) == 1 and int(sol.cuts) == 0
    assert int(sol.iterations) > 1
    r, scale = square.problem().residual(sol.u, sol.g), square.reactions(sol)
    assert float(jnp.linalg.norm(r)) < 1e-10 * float(jnp.linalg.norm(scale))   # an equilibrium
    # its own loop, not the model's load path: at one iteration it stops there, uncut
    with pytest.raises(SolveError, match="MAX_ITERATIONS") as failed:
        square.solve({"right": PUSH}, solver=solver, max_iter=1)
    assert int(failed.value.solution.iterations) == 1 and int(failed.value.solution.cuts) == 0
    # differentiable through the implicit JVP with the solver's linear solver: against central
    # differences of its own solves
    def probe(a):
        return square.displacement(square.solve({"right": a}, solver=solver), PROBE)

    J = np.asarray(jax.jacfwd(probe)(jnp.asarray(PUSH)))
    eps = 1e-5
    fd = np.stack([(np.asarray(probe(PUSH + eps * e)) - np.asarray(probe(PUSH - eps * e))) / (2 * eps)
                   for e in np.eye(2)], -1)
    assert np.abs(J).max() > 0.1 and np.abs(J - fd).max() < 1e-6 * np.abs(J).max()


def test_options_tune_only_the_models_own_solver(square):
    with pytest.raises(ValueError, match="set them as fields of that solver"):
        square.solve({"right": PUSH}, solver=PlainNewton(square.linear), rtol=1e-8)


def test_the_options_name_the_plans(square):
    """stable_branch None: the plain path, the branch switch only where it stops at a
    critical point; True / False: one path. A plan passed as ``solver`` runs as it is."""
    from jaxrkpm.model import solving
    mode = solving.Eager(0.1)
    auto = solving.plan(square.linear, {}, mode)
    assert isinstance(auto, BranchOnDemand) and auto.branching.switches and not auto.plain.switches
    assert auto.plain == square.solver(reuse=0.1)
    assert solving.plan(square.linear, {"stable_branch": False}, solving.Traced()) == Direct(square.solver(reuse=0.0))
    fixed = Direct(square.solver(stable_branch=False))
    assert solving.plan(square.linear, {}, mode, fixed) is fixed
    a = square.solve({"right": PUSH}, solver=fixed)
    b = square.solve({"right": PUSH}, stable_branch=False, reuse=0.0)
    assert np.array_equal(np.asarray(a.u), np.asarray(b.u))
