"""The solver protocol: solver objects with named state run by one loop, their settings as
validated fields (a test builds an object with another value instead of patching a global),
the declared linear-solver interface, and the options of Model.solve checked where they
become those objects."""
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.control.tracking import Tracker
from jaxrkpm.internal import (BranchSwitch, Chord, DenseSolver, LinearSolver, LoadPath, Newton, QuasiNewton,
                              StableDescent, Tolerance, iterate)
from jaxrkpm.solvers.continuation import ArcLength, ArcLengthPath
from jaxrkpm.solvers.iterate import IterativeSolver, run
from jaxrkpm.solvers.linalg.krylov import KrylovSolver
from jaxrkpm.solvers.linalg.quasi_newton import secant
from jaxrkpm.solvers.linalg.sparse import SparseSolver
from jaxrkpm.solvers.results import Limits
from tests.problems import block


@pytest.fixture(scope="module")
def square():
    _, _, model = block(5)
    return model


@pytest.mark.parametrize("option, value, match", [
    ("stable_branch", [True], "stable_branch must be True, False or None"),
    ("stable_branch", "no", "stable_branch must be True, False or None"),
    ("check_stability", "False", "check_stability must be True or False"),
    ("locate", "x", "locate must be an int >= 0"),
    ("locate", -1, "locate must be an int >= 0"),
    ("line_search", 2.5, "line_search must be an int >= 0"),
    ("rtol", 0.0, "rtol must be a positive number"),
    ("rtol", float("nan"), "rtol must be a positive number"),
    ("armijo", True, "armijo must be a positive number"),
    ("reuse", 1.0, r"reuse must be a number in \[0, 1\)"),
    ("growth", -1.0, "growth must be a positive number"),
    ("easy", "4", "easy must be an int >= 0"),
    ("tolerance", 1e-8, "unknown solver option"),
])
def test_bad_solve_options_are_named_before_any_work(square, option, value, match):
    with pytest.raises(ValueError, match=match):
        square.solve({"right": [0.01, 0.0]}, **{option: value})


def test_options_become_fields_of_the_solver_objects(square):
    path = square.solver(rtol=1e-12, line_search=3, reuse=0.2, easy=2, locate=4, stable_branch=True)
    assert isinstance(path, LoadPath) and isinstance(path.newton, Newton)
    assert path.newton.tolerance == Tolerance(1e-12) and path.newton.line_search == 3 and path.newton.reuse == 0.2
    assert path.easy == 2 and path.locate == 4 and path.switches
    # the descent past a critical point uses the same tolerance and line search
    assert path.branch.descent.tolerance == path.newton.tolerance and path.branch.descent.line_search == 3
    assert square.solver() == LoadPath(Newton(square.linear))      # the defaults are the fields'
    assert not square.solver(stable_branch=True, check_stability=False).switches


def test_every_linear_solver_declares_the_interface():
    """No name tests and no hasattr: every solver is a LinearSolver; only the quasi-Newton one
    learns from secant pairs, only the dense one serves modified Newton as it is."""
    for cls in (DenseSolver, SparseSolver, KrylovSolver, QuasiNewton):
        assert issubclass(cls, LinearSolver)
    assert DenseSolver().modified_newton and not QuasiNewton().modified_newton
    assert not SparseSolver.modified_newton and not KrylovSolver.modified_newton
    assert DenseSolver().update("state", 1, 2) == "state"       # the default: nothing learnt
    # capabilities, not types: only the dense solver switches branches and learns secants
    assert DenseSolver.branch_switching and not SparseSolver.branch_switching
    assert isinstance(secant(DenseSolver(), 4), QuasiNewton) and secant(DenseSolver(), 4).memory == 4
    assert secant(EigenSolver(), 4) == EigenSolver()   # one that cannot learn stays itself


def test_newton_and_chord_differ_by_one_flag(square):
    """A chord with the factorisation of the start lands on full Newton's equilibrium; it
    needs the factorisation; with a stable factorisation it needs no line search."""
    prob = square.problem()
    start = square.initial()
    g1 = square.prescribed({"right": [0.02, 0.01]})
    newton = Newton(square.linear)
    chord = Chord(square.linear)
    assert not newton.chord and chord.chord and chord.halvings == 0 and newton.halvings == 8
    full = jax.jit(lambda p: newton.solve(p, start.u, start.g, g1, 1.0, 1.0))(prob)
    state = square.linear.state_at(prob, start.u, start.g)
    quick = jax.jit(lambda p, st: chord.solve(p, start.u, start.g, g1, 1.0, 1.0, st, max_iter=30))(prob, state)
    assert jr.Status.of(full.status) == jr.Status.CONVERGED == jr.Status.of(quick.status)
    assert int(quick.iterations) > int(full.iterations)          # linear against quadratic
    assert np.abs(np.asarray(quick.u - full.u)).max() < 1e-9 * np.abs(np.asarray(full.u)).max()
    with pytest.raises(ValueError, match="a chord solve needs the factorisation"):
        chord.solve(prob, start.u, start.g, g1, 1.0, 1.0)


def test_one_loop_runs_every_solver(square):
    """``iterate`` runs a solver's step until it terminates, with its named state; the load
    path's own step/terminate give the same Solution as its solve."""
    prob = square.problem()
    start = square.initial()
    g1 = square.prescribed({"right": [0.05, 0.0]})
    lim = Limits.of(steps=2)
    driver = square.solver()
    path = driver.path(lim, start.g, g1, jnp.float64(1.0), jnp.float64(1.0))
    s = jax.jit(lambda p: iterate(driver, p, path, driver.init(p, path, start.u)))(prob)
    sol = jax.jit(lambda p: driver.solve(p, lim, start.u, start.g, g1, jnp.float64(1.0), jnp.float64(1.0)))(prob)
    assert float(s.t) == 1.0 and int(s.steps) == int(sol.steps) == 2
    assert np.array_equal(np.asarray(s.u), np.asarray(sol.u))


def test_another_tolerance_is_another_object(square):
    """A tighter tolerance is built, not patched: it asks for a smaller residual."""
    loose = square.solve({"right": [0.05, 0.0]}, rtol=1e-6, reuse=0)
    tight = square.solve({"right": [0.05, 0.0]}, rtol=1e-12, reuse=0)
    assert float(tight.residual_norm) < float(loose.residual_norm)
    with pytest.raises(ValueError, match="roundoff must be a positive number"):
        Tolerance(1e-10, roundoff=0.0)
    with pytest.raises(ValueError, match="newton must be a Newton solver"):
        LoadPath(Chord(DenseSolver()))
    with pytest.raises(ValueError, match="descent must be a StableDescent"):
        BranchSwitch(descent=Newton())
    with pytest.raises(ValueError, match="collapse_det must be a positive number"):
        StableDescent(collapse_det=0.0)


@dataclass(frozen=True)
class EigenSolver(LinearSolver):
    """A linear solver written outside the package: K_ff by its symmetric eigendecomposition
    (slow, but its inertia is exact), implementing only the declared interface."""

    name = "eigen"

    def empty(self, problem, dtype):
        n = problem.n_free * problem.dim
        return jnp.zeros((n,), dtype), jnp.eye(n, dtype=dtype)

    def init(self, problem, blocks):
        return tuple(jnp.linalg.eigh(problem.dense_tangent(blocks)))

    def solve(self, state, rhs):
        lam, V = state
        flat = rhs.reshape(lam.shape[0], -1)
        return (V @ ((V.T @ flat) / lam[:, None])).reshape(rhs.shape)

    def stability(self, state):
        return jnp.where(jnp.min(state[0]) > 0, jr.Stability.STABLE, jr.Stability.UNSTABLE)

    def negative_eigenvalues(self, state):
        return jnp.sum(state[0] < 0)

    def newton_solve(self, state, problem, blocks, rhs, rtol=None):
        state = self.init(problem, blocks)
        return self.solve(state, rhs), state, self.stability(state)


def test_a_solver_written_outside_the_package_serves_the_model(square):
    """``Model(solver=instance)`` takes any LinearSolver: the solve, the load path run by
    ``iterate`` and the implicit Jacobian equal the dense path's; nothing tests its type."""
    body, sets = square.body, {k: square.set_indices(k) for k in square.set_names}
    own = jr.Model(body, square.material, essential=sets, solver=EigenSolver())
    assert isinstance(own.linear, EigenSolver) and own.newton_reuse == 0.0
    move = {"right": [0.05, 0.02]}
    ref, sol = square.solve(move, reuse=0), own.solve(move)
    assert jr.Status.of(sol.status) == jr.Status.CONVERGED
    assert np.abs(np.asarray(sol.u - ref.u)).max() < 1e-10
    centre = [[0.5, 0.5]]
    assert np.abs(np.asarray(own.jacobian(sol, "right", centre) - square.jacobian(ref, "right", centre))).max() < 1e-9
    newton = Newton(EigenSolver())
    prob, start = own.problem(), own.initial()
    res = jax.jit(lambda p: newton.solve(p, start.u, start.g, own.prescribed(move), 1.0, 1.0))(prob)
    assert jr.Status.of(res.status) == jr.Status.CONVERGED
    assert np.abs(np.asarray(res.u - ref.u)).max() < 1e-10
    with pytest.raises(ValueError, match="pass a jaxrkpm.internal.LinearSolver instance"):
        jr.Model(body, square.material, essential=sets, solver=object())


# -------------------------------------------------------------- a solver written outside
class Fixed(NamedTuple):
    """The damped iteration's constants."""

    g: jax.Array
    load: jax.Array
    max_iter: jax.Array
    tol: jax.Array


class DampedState(NamedTuple):
    iteration: jax.Array
    u: jax.Array
    residual: jax.Array
    done: jax.Array
    status: jax.Array


@dataclass(frozen=True)
class DampedFixedPoint:
    """A nonlinear solver written outside the package against the contract only (it imports
    nothing of the solvers but the Status codes): the damped fixed-point iteration
    u <- u - theta K(u)^-1 r(u) at fixed prescribed values and load, converging linearly
    (by 1 - theta an iteration) where Newton converges quadratically."""

    theta: float = 0.6

    def init(self, problem, args: Fixed, start) -> DampedState:
        r = problem.residual(start, args.g, args.load)
        return DampedState(jnp.array(0), start, r, jnp.array(False), jnp.array(jr.Status.MAX_ITERATIONS))

    def step(self, problem, args: Fixed, s: DampedState) -> DampedState:
        K = problem.tangent(s.u, args.g, args.load)
        u = s.u - self.theta * jnp.linalg.solve(K, s.residual.reshape(-1)).reshape(s.u.shape)
        r = problem.residual(u, args.g, args.load)
        converged = jnp.linalg.norm(r) <= args.tol
        finite = jnp.all(jnp.isfinite(r))
        done = converged | ~finite | (s.iteration + 1 >= args.max_iter)
        status = jnp.where(converged, jr.Status.CONVERGED,
                           jnp.where(finite, jr.Status.MAX_ITERATIONS, jr.Status.NONFINITE))
        return DampedState(s.iteration + 1, u, r, done, status)

    def terminate(self, s: DampedState):
        return s.done, s.status

    def postprocess(self, problem, args: Fixed, s: DampedState, status):
        return s.u, status, s.iteration


def test_a_solver_defined_here_runs_through_the_one_loop(square):
    """The contract is declared once (``IterativeSolver``): a solver defined in this test
    implements it, and ``iterate`` (its final state) and ``run`` (init, loop, postprocess)
    drive it as they drive Newton; it lands on Newton's equilibrium. Every solver of the
    package subclasses the contract and reports (done, status) from ``terminate``."""
    assert isinstance(DampedFixedPoint(), IterativeSolver)
    for cls in (Newton, Chord, LoadPath, StableDescent, ArcLength, ArcLengthPath, Tracker):
        assert issubclass(cls, IterativeSolver), cls
    prob, start = square.problem(), square.initial()
    ref = square.solve({"right": [0.02, 0.01]}, reuse=0)    # one load step of full Newton
    tol = 1e-10 * float(prob.force_scale(prob.energy_residual(ref.u, ref.g)[3]))
    args = Fixed(ref.g, jnp.float64(1.0), jnp.array(200), jnp.float64(tol))
    solver = DampedFixedPoint()

    @jax.jit
    def both(p, a):   # the whole solve, and the loop alone from the solver's own init
        return run(solver, p, a, start.u), iterate(solver, p, a, solver.init(p, a, start.u))

    (u, status, its), final = both(prob, args)
    # the 2% stretch from the undeformed state: a fixed-point iteration from u = 0 converges
    assert jr.Status.of(status) == jr.Status.CONVERGED and 10 < int(its) < 200
    assert int(its) > int(ref.iterations)          # linear against Newton's quadratic
    assert np.abs(np.asarray(u - ref.u)).max() < 1e-9 * np.abs(np.asarray(ref.u)).max()
    assert np.array_equal(np.asarray(final.u), np.asarray(u)) and bool(final.done)
    # a cap it cannot converge within: done, with the status of a stop there
    (_, status, its), _ = both(prob, args._replace(max_iter=jnp.array(3)))
    assert jr.Status.of(status) == jr.Status.MAX_ITERATIONS and int(its) == 3
    # the package's solvers answer terminate with (done, status) too
    newton = Newton(square.linear)
    done, status = jax.jit(lambda p: newton.terminate(newton.init(
        p, newton.increment(p, start.u, start.g, ref.g, jnp.float64(1.0), jnp.float64(1.0), 25), start.u)))(prob)
    assert not bool(done) and jr.Status.of(status) == jr.Status.MAX_ITERATIONS


def test_solves_return_their_own_linear_statistics(square):
    """A solve's linear work comes back with it (``Solution.stats``), not in a module-wide
    tally: full Newton factorises at every iteration, modified Newton less often, both solve
    once an iteration; two solves in a row report the same work each."""
    move = {"right": [0.05, 0.02]}
    full = square.solve(move, reuse=0)
    again = square.solve(move, reuse=0)
    stats = full.stats.as_dict()
    assert stats["factorisations"] == stats["solves"] == int(full.iterations)
    assert again.stats.as_dict() == stats
    assert stats["cg_solves"] == 0 and stats["factorise_s"] == 0.0     # the dense path: inside XLA
    modified = square.solve(move, reuse=0.5)
    assert int(modified.stats.solves) == int(modified.iterations)
    assert int(modified.stats.factorisations) < int(modified.iterations)
    assert square.initial().stats is None
