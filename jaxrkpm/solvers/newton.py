"""Newton's method on the free RK coefficients, as solver objects with named state.

``Newton`` (full Newton; modified Newton with ``reuse`` > 0) and ``Chord`` (every solve with a
given factorisation; quasi-Newton chord with a ``QuasiNewton`` linear solver) differ by one
flag. Each is an ``IterativeSolver`` (``init`` / ``step`` / ``terminate`` / ``postprocess`` over
a ``NewtonState``), run by the one loop of :func:`jaxrkpm.solvers.iterate.iterate`; ``solve``
does it all::

    newton = Newton(linear=DenseSolver(), rtol=1e-10)
    res = newton.solve(problem, u, g0, g1, l0, l1, state, max_iter=25)   # NewtonResult

Every tuning constant is a field of the object it tunes (a test builds an object with another
value instead of patching a module global).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.checks import count, flag, positive
from .iterate import IterativeSolver, run, when
from .linalg.base import LinearSolver, LinearStats, Stability
from .linalg.dense import DenseSolver
from .results import Status


@dataclass(frozen=True)
class Tolerance:
    """The residual test of every nonlinear solver: converged when
    |r| <= max(rtol max(|r_ref|, force scale), floor), the floor being ``roundoff`` x machine
    epsilon x the problem's stiffness scale: the residual that rounding the strain to machine
    precision produces, below which |r| carries no information. Without the floor a tiny load
    step (steps=10**6, or a 1e-9 prescribed displacement) asks for |r| <= rtol x (a tiny force)
    and never converges; the round-off actually left in |r| is a few percent of the floor."""

    rtol: float = 1e-10
    roundoff: float = 100.0

    def __post_init__(self):
        positive("rtol", self.rtol)
        positive("roundoff", self.roundoff)

    def floor(self, stiffness):
        """The round-off floor from the problem's stiffness scale (``Problem.force_scales``)."""
        return self.roundoff * jnp.finfo(stiffness.dtype).eps * stiffness

    def of(self, scale, floor, r_ref=None):
        """The residual norm that counts as converged."""
        ref = scale if r_ref is None else jnp.maximum(r_ref, scale)
        return jnp.maximum(self.rtol * ref, floor)


class Increment(NamedTuple):
    """What one Newton solve is asked, from the equilibrium at (g0, l0) to (g1, l1): its
    constants inside the loop."""

    g0: jax.Array         # (Nb, d) prescribed values at the start (the predictor's tangent)
    g1: jax.Array         # (Nb, d) prescribed values at the end
    l0: jax.Array         # () load scale at the start (the predictor's tangent)
    l1: jax.Array         # () load scale at the end
    rhs0: jax.Array       # (Nf, d) the predictor's right-hand side r(u, g0, l0) + dr/d(g, l) (g1 - g0, l1 - l0)
    r_ref: jax.Array      # () |rhs0|: the out-of-balance force the increment puts on
    max_iter: jax.Array   # () iteration cap
    floor: Any            # () round-off floor given by the caller, or None (computed once)
    linear: Any = None    # the linear solver's state the iteration starts from (a chord's
    #                       factorisation; modified Newton's predictor where it is stable)


class NewtonState(NamedTuple):
    """The Newton iteration's state (a pytree: the loop's carry)."""

    iteration: jax.Array  # () iterations done
    u: jax.Array          # (Nf, d) the iterate
    energy: jax.Array     # () Pi at u
    residual: jax.Array   # (Nf, d) r at u (before the first step: the predictor's right-hand side)
    done: jax.Array       # () the iteration is over
    status: jax.Array     # () its Status (while running: MAX_ITERATIONS, the status of a stop there)
    linear: Any           # the linear solver's state (its factorisation)
    keep: jax.Array       # () modified Newton: the kept factorisation serves the next iteration
    scale: jax.Array      # () the force scale of the tolerance
    floor: jax.Array      # () the round-off floor of the tolerance
    factorised: jax.Array  # () modified Newton: a tangent of this load step has been factorised
    stats: LinearStats    # the linear work so far


class NewtonResult(NamedTuple):
    u: jax.Array
    status: jax.Array
    iterations: jax.Array
    residual_norm: jax.Array
    linear: Any           # the linear solver's last state
    stats: LinearStats    # the solve's linear work


@dataclass(frozen=True)
class Newton(IterativeSolver):
    """Newton from the equilibrium at (g0, l0) to (g1, l1).

    The first linear solve is the predictor: it carries the prescribed increment,
    K_ff(u, g0) du = -(r(u, g0, l1) + K_fg (g1 - g0)); later ones are Newton steps at g1.
    ``g0`` None: u is an iterate at g1 (e.g. a state predicted by the caller) and the first
    solve a Newton step there (a residual pass instead of the predictor's linearisation).
    Converged by ``tolerance`` with r_ref = |r + K_fg dg|: the force scale at the iterate after
    the last step that assembled the tangent (or after the predictor: chord steps reuse it),
    the floor after the predictor unless the caller gives it (the control loop keeps one from
    a nearby state: the floor's own pass through the material costs as much as a chord
    correction). The force scale comes from the stresses each residual evaluation computes.

    Every iteration assembles the tangent and solves through ``linear.newton_solve`` (which
    may reuse the state, e.g. as a preconditioner), then a backtracking line search (energy
    decrease or residual decrease; ``line_search`` halvings, ``armijo`` its sufficient
    decrease).

    ``reuse`` > 0 (modified Newton, for solvers with ``modified_newton``): an iteration solves
    with the kept, stable factorisation (no assembly) where the previous step cut |r| by at
    least ``reuse`` (the predictor: where the given state, the previous load step's last, is
    stable), else assembles and factorises; the line search stays. Once |r| is small enough
    that one Newton step meets the tolerance, the tangent there is factorised (once per load
    step, where the chord has not already made one) and serves the rest of the step.
    Convergence is declared only after a tangent of this load step was factorised (its
    stability is the one reported: with one of the previous step only, a solve passed a
    critical point). Assembly dominates 3D solves, so this roughly halves their cost at the
    same residual tolerance (``experiments/bench_cube3d.py``).

    ``check_stability``: an equilibrium whose last factorised tangent is not positive definite
    ends with UNSTABLE_TANGENT (STABILITY_UNKNOWN where the factorisation cannot tell); off,
    iterative solvers may also stop their solves early (the inexact-Newton forcing term).
    ``predictor_rtol``: the relative residual of an iterative solver's predictor solve (the
    predictor is a linearised step, off by O(increment^2) whatever its solve's accuracy)."""

    linear: LinearSolver = DenseSolver()
    tolerance: Tolerance = Tolerance()
    line_search: int = 8
    armijo: float = 1e-4
    reuse: float = 0.0
    check_stability: bool = True
    predictor_rtol: float = 1e-4
    chord: ClassVar[bool] = False

    def __post_init__(self):
        if not isinstance(self.linear, LinearSolver):
            raise ValueError(f"linear must be a jaxrkpm linear solver, got {type(self.linear).__name__}")
        if not isinstance(self.tolerance, Tolerance):
            raise ValueError(f"tolerance must be a Tolerance, got {self.tolerance!r}")
        count("line_search", self.line_search)
        positive("armijo", self.armijo)
        positive("predictor_rtol", self.predictor_rtol)
        if isinstance(self.reuse, (bool, np.bool_)) or not (isinstance(self.reuse, (int, float)) and 0 <= self.reuse < 1):
            raise ValueError(f"reuse must be a number in [0, 1) (0: full Newton), got {self.reuse!r}")
        flag("check_stability", self.check_stability)

    @property
    def rtol(self) -> float:
        return self.tolerance.rtol

    @property
    def halvings(self) -> int:
        """Line-search halvings: none for a chord (each correction must lower |r|)."""
        return 0 if self.chord else self.line_search

    @property
    def modified(self) -> bool:
        """Modified Newton (static): a kept factorisation serves later iterations. Not for
        the sparse and Krylov solvers, whose newton_solve already reuses theirs as a
        preconditioner, and whose kept state may factorise an older tangent than the last."""
        return (not self.chord) and self.reuse > 0 and self.linear.modified_newton

    # ------------------------------------------------------------------- the protocol
    def increment(self, problem, u, g0, g1, l0, l1, max_iter, floor=None, linear=None) -> Increment:
        """The loop's constants for a solve from u (an equilibrium at g0, or with g0 None an
        iterate at g1), the linear solver's state starting from ``linear`` (default: empty)."""
        if g0 is None:   # no increment: the residual at (u, g1), not a linearisation along zero
            g0, l0, rhs0 = g1, l1, problem.residual(u, g1, l1)
        else:
            # the predictor linearises the residual in the prescribed values and in the load
            # scale at the start: a term whose load is not linear in the scale (a tool that the
            # scale moves) then contributes the motion of what touches it, where its residual at
            # the end load would carry the forces of a tool already pushed through the body
            r0, dr = jax.jvp(lambda g, l: problem.residual(u, g, l), (g0, l0), (g1 - g0, l1 - l0))
            rhs0 = r0 + dr
        given = None if floor is None else jnp.asarray(floor, u.dtype)
        if linear is None:
            linear = self.linear.empty(problem, jnp.result_type(u))
        return Increment(g0, g1, l0, l1, rhs0, jnp.linalg.norm(rhs0), max_iter, given, linear)

    def init(self, problem, inc: Increment, u) -> NewtonState:
        linear = inc.linear
        stable = self.linear.stability(linear) == Stability.STABLE
        if self.chord:
            # the chord's first solve is the predictor (right-hand side rhs0, accepted whenever
            # admissible): the energy and residual at (u, g1) would go unused, not evaluated
            energy, residual = jnp.array(jnp.inf, u.dtype), inc.rhs0
            done = ~stable
        else:
            energy, _, residual, _ = problem.energy_residual(u, inc.g1, inc.l1)
            done = jnp.array(False)
        status = jnp.where(done, Status.UNSTABLE_TANGENT, Status.MAX_ITERATIONS)
        keep = jnp.asarray(self.modified) & stable
        zero = jnp.zeros((), u.dtype)
        return NewtonState(jnp.array(0), u, energy, residual, done, status, linear, keep, zero, zero,
                           jnp.array(False), LinearStats.of())

    def terminate(self, s: NewtonState):
        return s.done, s.status

    def step(self, problem, inc: Increment, s: NewtonState) -> NewtonState:
        first = s.iteration == 0
        rhs = jnp.where(first, inc.rhs0, s.residual)
        dx, state, stab, made, work = self._linear_step(problem, inc, s, first, rhs)
        ok, v, Pi_v, r_v, aux_v, why = self._line_search(problem, inc, s, -dx, first)
        if self.chord:
            # a quasi-Newton solver learns from each correction (the predictor's step also
            # changes the load: not a secant pair of one residual)
            state = self.linear.update(state, v - s.u, r_v - s.residual, ok & ~first)
        rn = jnp.linalg.norm(r_v)
        scale, floor = self._tolerance_scales(problem, inc, s, first | made, first, aux_v, v)
        tol = self.tolerance.of(scale, floor, inc.r_ref)
        converged = ok & (rn <= tol)
        cap = self._cap(inc, s, first, converged, rn)
        keep, factorised = s.keep, s.factorised
        if self.modified:
            converged, keep, factorised = self._modified_bookkeeping(inc, s, ok, converged, made, first, rn, tol,
                                                                     state)
        done, status = self._outcome(ok, why, converged, stab, s.iteration + 1 >= cap)
        return NewtonState(s.iteration + 1, jnp.where(ok, v, s.u), jnp.where(ok, Pi_v, s.energy),
                           jnp.where(ok, r_v, s.residual), done, status, state, keep, scale, floor, factorised,
                           s.stats + work)

    def postprocess(self, problem, inc: Increment, s: NewtonState, status) -> NewtonResult:
        return NewtonResult(s.u, status, s.iteration, jnp.linalg.norm(s.residual), s.linear, s.stats)

    def solve(self, problem, u, g0, g1, l0, l1, linear=None, *, max_iter=25, floor=None) -> NewtonResult:
        """The whole solve: ``increment``, then ``run`` (init, the loop, postprocess);
        ``linear`` the solver's state to start from (a chord needs the factorisation it
        reuses)."""
        if linear is None and self.chord:
            raise ValueError("a chord solve needs the factorisation to reuse (linear=...)")
        inc = self.increment(problem, u, g0, g1, jnp.asarray(l0, jnp.float64), jnp.asarray(l1, jnp.float64),
                             max_iter, floor, linear)
        return run(self, problem, inc, u)

    # -------------------------------------------------------------------------- parts
    def _linear_step(self, problem, inc: Increment, s: NewtonState, first, rhs):
        """The step's linear solve: (dx, linear state, its stability, whether a tangent was
        assembled and factorised, LinearStats). A chord solves with its factorisation;
        modified Newton with the kept one where it still serves (``keep``), else both
        assemble and factorise."""
        state = s.linear
        if self.chord:
            return (self.linear.solve(state, rhs), state, self.linear.stability(state), False,
                    LinearStats.of(solves=1))
        def assembled():
            dx, new, stab, work = self._assemble_and_solve(problem, inc, s.u, first, rhs, state)
            return dx, new, stab, True, work

        if self.modified:
            return jax.lax.cond(
                s.keep, lambda: (self.linear.solve(state, rhs), state, self.linear.stability(state), False,
                                 LinearStats.of(solves=1)), assembled)
        return assembled()

    def _tolerance_scales(self, problem, inc: Increment, s: NewtonState, assembled, first, aux_v, v):
        """(force scale, round-off floor) of the residual test after a step to v: the force
        scale at the iterate after each assembled step, kept through the chord steps that
        follow it (they move the state by less than the step before them, so the scale by a
        relative O(|du|)); the round-off floor once a call, after the predictor, where the
        caller did not give it."""
        scale = when(assembled, lambda: problem.force_scale(aux_v), s.scale)
        if inc.floor is None:
            floor = when(first, lambda: self.tolerance.floor(problem.force_scales(v, inc.g1)[1]), s.floor)
        else:
            floor = inc.floor
        return scale, floor

    def _cap(self, inc: Increment, s: NewtonState, first, converged, rn):
        """The iteration cap after this step: a chord with ``reuse`` > 0 stops at once where a
        correction cut |r| by less than ``reuse`` (a kept factorisation that no longer
        contracts fast is not worth more corrections)."""
        if not (self.chord and self.reuse > 0):
            return inc.max_iter
        slow = ~first & ~converged & (rn > self.reuse * jnp.linalg.norm(s.residual))
        return jnp.where(slow, s.iteration + 1, inc.max_iter)

    def _modified_bookkeeping(self, inc: Increment, s: NewtonState, ok, converged, made, first, rn, tol, state):
        """Modified Newton: (converged, keep, factorised) after the step. The equilibrium is
        declared only once a tangent of this step (at g1: not the predictor's) has been
        factorised, so the stability reported is, as in full Newton, that of an iterate of
        this step's Newton sequence; a chord step that meets the tolerance before that is
        followed by one. That factorisation is made where it does most: once |r| is low
        enough that a Newton step from there meets the tolerance (quadratic convergence,
        |r|^2 <= tol r_ref), so the chord steps after it contract at once."""
        factorised = s.factorised | (made & ~first)
        met = converged
        # (without the stability check no factorisation is owed: chords while they contract)
        converged = converged & (factorised | (not self.check_stability))
        owed = self.check_stability & ~factorised & (rn * rn <= tol * inc.r_ref)
        keep = ok & ~met & (rn <= self.reuse * jnp.linalg.norm(s.residual)) & \
            (self.linear.stability(state) == Stability.STABLE) & ~owed
        return converged, keep, factorised

    def _outcome(self, ok, why, converged, stab, capped):
        """(done, status) after a step. Stability from the last factorised tangent (at the
        iterate before the converged one); a linear solve that did not converge (Krylov)
        gives an untrusted step: unless the residual met the tolerance anyway, the attempt
        ends."""
        if self.check_stability:
            reached = jnp.where(stab == Stability.STABLE, Status.CONVERGED,
                                jnp.where(stab == Stability.UNSTABLE, Status.UNSTABLE_TANGENT,
                                          Status.STABILITY_UNKNOWN))
        else:
            reached = Status.CONVERGED
        failed_solve = (stab == Stability.FAILED) & ~converged
        status = jnp.where(~ok, why, jnp.where(converged, reached, Status.MAX_ITERATIONS))
        status = jnp.where(failed_solve, Status.LINEAR_SOLVE, status)
        return ~ok | converged | capped | failed_solve, status

    def _assemble_and_solve(self, problem, inc: Increment, u, first, rhs, state):
        """A Newton step with the tangent at u (at g0 for the predictor): (dx, state,
        stability, LinearStats)."""
        blocks = problem.tangent_blocks(u, jnp.where(first, inc.g0, inc.g1), jnp.where(first, inc.l0, inc.l1))
        # inexact Newton (iterative linear solvers): far from equilibrium the linear solve
        # need only be as accurate as the step is good (a forcing term proportional to the
        # residual keeps the convergence quadratic), near it solves are tight. With the
        # stability check only the predictor's solve may stop early: an iterative solver
        # finds negative curvature only in a rich Krylov space (with loose early corrections
        # a buckling column's CG path passed the critical point and reported the state beyond
        # it as stable), and the predictor's tangent is the previous equilibrium's, which that
        # equilibrium's own tight solves checked
        forcing = None
        if not self.check_stability:
            rel = jnp.linalg.norm(rhs) / jnp.maximum(inc.r_ref, 1e-300)
            forcing = jnp.where(rel > 1e-4, jnp.minimum(1e-2 * rel, 1e-4), 1e-11)
        elif self.linear.tight_rtol is not None:
            forcing = jnp.where(first, self.predictor_rtol, self.linear.tight_rtol)
        dx, state, stab = self.linear.newton_solve(state, problem, blocks, rhs, forcing)
        return dx, state, stab, self.linear.work(state) + LinearStats.of(solves=1)

    def _line_search(self, problem, inc: Increment, s: NewtonState, du, first):
        """Backtracking along du from s.u: (accepted, v, Pi, r, aux, status if refused)."""
        u, Pi, r = s.u, s.energy, s.residual
        slope = jnp.sum(du * r)
        rn = jnp.linalg.norm(r)
        start_ok = jnp.isfinite(Pi) & jnp.all(jnp.isfinite(r))
        halvings = self.halvings

        def cond(c):
            return (~c[1]) & (c[0] <= halvings)

        def body(c):
            k, _, _, _, _, _, any_finite, _ = c
            alpha = 0.5 ** k
            v = u + alpha * du
            Pi_v, det_v, r_v, aux_v = problem.energy_residual(v, inc.g1, inc.l1)
            finite = jnp.isfinite(Pi_v) & jnp.all(jnp.isfinite(r_v))
            valid = finite & (det_v > 0)
            lower_r = jnp.linalg.norm(r_v) < rn
            if self.chord:   # the predictor need only be admissible; corrections must lower |r|
                decrease = first | lower_r
            else:
                decrease = (Pi_v <= Pi + self.armijo * alpha * slope) | lower_r | ~start_ok
            return (k + 1, valid & decrease, v, Pi_v, r_v, aux_v, any_finite | finite, det_v > 0)

        init = (jnp.array(0), jnp.array(False), u, Pi, r, problem.no_aux(u), jnp.array(False), jnp.array(True))
        # no halvings (chord): the one trial step, without a loop around it
        _, accepted, v, Pi_v, r_v, aux_v, any_finite, det_ok = (
            body(init) if halvings == 0 else jax.lax.while_loop(cond, body, init))
        why = jnp.where(~any_finite, Status.NONFINITE, jnp.where(~det_ok, Status.INVERTED, Status.LINE_SEARCH))
        return accepted, v, Pi_v, r_v, aux_v, why


@dataclass(frozen=True)
class Chord(Newton):
    """The chord (modified Newton) iteration of a kept tangent: every solve uses the given
    factorisation as it is (no assembly; with a ``QuasiNewton`` linear solver each
    correction's secant pair improves it: quasi-Newton corrections); no line search, each
    correction must lower |r|; a factorisation that is not stable gives UNSTABLE_TANGENT at
    once. With ``reuse`` > 0 a correction must cut |r| by at least that factor, else the chord
    stops at once with MAX_ITERATIONS (it contracts too slowly: the caller refactorises)."""

    chord: ClassVar[bool] = True
