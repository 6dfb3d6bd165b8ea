"""Jacobian path tracking (thesis Algorithm 3): MP <- MP + K J^-1 e.

The whole tracking run is one jitted while-loop (``Tracker``, an ``IterativeSolver`` run by
``jaxrkpm.solvers.iterate.iterate``): at each iteration the controller model's
implicit Jacobian J = d CP / d MP is taken at its converged state, the manipulation point
(a rigidly driven essential set, or the position of a contact tool that can only push) moves
by K J^+ e clamped to ``clamp`` per component, and the models re-equilibrate. The plant
(whose control point is measured) is the controller itself, or a second model (reduced ->
refined control, section 5.3.1).

Cost per iteration: one tangent assembly and one factorisation of K_ff at the converged
state (the linear solver's explicit state, dense or sparse alike), shared by the Jacobian
(m solves), the Newton predictor of the next solve and its chord corrections
(``jaxrkpm.solvers.newton.newton(chord=True)``); the adaptive ``solve_path`` runs only if those fail
(a tangent that is not positive definite, no residual decrease, det F <= 0).
With ``track(reuse=...)`` the factorisation is kept across iterations instead (quasi-Newton
chord corrections, ``linear.QuasiNewton``) and made again only where a correction cuts the
residual by less than ``reuse``: same residual tolerance, and the Jacobian then comes from the
kept factorisation (of a nearby earlier state) by iterative refinement with exact
Hessian-vector products (``jaxrkpm.solvers.implicit.sensitivity(refine=...)``): the implicit Jacobian of
the current state, to a relative residual of ``jacobian_rtol``. That refinement starts from the
response predicted along the path (``response_trend``), and the chord from the move's
second-order prediction (``predicted_change``): on the 9x9 box path, 0-1 CG iterations and
1.6 chord solves a control step.
"""
from __future__ import annotations

from functools import partial
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.checks import count, flag
from ..base.outcome import Outcome
from ..discretise.polygons import distance_to_segment
from ..mechanics.contact import ContactTerm
from ..mechanics.problem import Problem
from ..model.model import Model
from ..solvers.implicit import parameter_response, point_jacobian, response
from ..solvers.iterate import IterativeSolver, run as run_solver, when
from ..solvers.linalg.base import LinearStats
from ..solvers.linalg.quasi_newton import secant
from ..solvers.newton import Chord, Newton
from ..solvers.path import LoadPath
from ..solvers.results import Limits, Solution, Status, reached_equilibrium


class TrackStatus(Outcome):
    DONE = 0, "every waypoint reached"
    SOLVE_FAILED = 1, "a model solve failed; the history up to it is kept"
    ITERATION_CAP = 2, "the waypoint was not reached within the iteration cap"
    NO_PROGRESS = 3, ("the control point error stopped decreasing: the waypoint looks "
                      "unreachable with this manipulation")
    HISTORY_FULL = 4, "the total iteration budget (max_steps) ran out"


def control_increment(J, e, gain, clamp, damping=0.0):
    """K J^+ e, clamped so no component exceeds ``clamp``.

    Square J: J^-1 e. Otherwise damped least squares: (J^T J + damping^2 I)^-1 J^T e
    (more control than manipulation coordinates) or J^T (J J^T + damping^2 I)^-1 e."""
    m, n = J.shape
    if m >= n:
        step = jnp.linalg.solve(J.T @ J + damping**2 * jnp.eye(n), J.T @ e)
    else:
        step = J.T @ jnp.linalg.solve(J @ J.T + damping**2 * jnp.eye(m), e)
    if m == n:  # undamped square J: the plain inverse (better conditioned than the normal equations)
        step = jnp.where(damping > 0, step, jnp.linalg.solve(J, e))
    step = gain * step
    # a J of zeros (a contact tool that has lost contact moves nothing) gives no finite step: no move
    step = jnp.where(jnp.all(jnp.isfinite(step)), step, 0.0)
    biggest = jnp.max(jnp.abs(step))
    return jnp.where(biggest > clamp, step * (clamp / biggest), step)


def contact_tools(problem: Problem) -> list:
    """The names of the problem's contact tools (its ``Contact`` terms)."""
    return [t.name for t in problem.terms if isinstance(t, ContactTerm)]


@partial(jax.tree_util.register_dataclass, data_fields=("problem", "G", "idx", "psi"),
         meta_fields=("driver", "chord", "jacobian_rtol", "corrections", "tool"))
@dataclass(frozen=True)
class ControlledModel:
    """One model inside the tracking loop (a pytree: the problem and the tables are its
    arrays; the solvers and settings its static part): its manipulation point, the control
    points' shape functions, the adaptive solve (``driver``) and the chord that settles each
    move (``chord``).

    The manipulation point mp (d_mp,) is a displacement from the start of the run: of a
    rigidly driven essential set (the prescribed values g + mp . G, G its rigid directions;
    ``tool`` None), or of a contact tool (``tool``: the name of a ``Contact`` term of the
    problem, whose position at load scale 1 moves by mp, its rotation held; G is zero, the
    prescribed values stay). Both are driven by the same loop: ``at`` gives the problem at
    mp, and ``response`` the implicit sensitivity to mp (through g or the tool's position).

    jacobian_rtol  with a kept factorisation the Jacobian is refined until
                   |K x - rhs| <= jacobian_rtol |rhs|: it only sets the direction of a gained,
                   clamped increment (the equilibria keep the solver's own tolerance), and each
                   correction costs m Hessian-vector products (``experiments/bench_cube3d.py``).
    corrections    chord corrections allowed with a kept factorisation (each must still cut |r|
                   by the chord's ``reuse``: 0.5**30 ~ 1e-9 of the predictor's residual)."""

    problem: Problem
    G: jax.Array     # (d_mp, Nb, d) rigid directions of the driven set
    idx: jax.Array   # (C, K) control point neighbours
    psi: jax.Array   # (C, K)
    driver: LoadPath
    chord: Chord
    jacobian_rtol: float = 1e-6
    corrections: int = 30
    tool: str | None = None

    @staticmethod
    def of(model: Model, driven: str, control_points, params=None, reuse: float = 0.0,
           memory: int = 8) -> "ControlledModel":
        """``driven``: an essential set of ``model`` (moved rigidly) or a ``Contact`` term
        (its position moved, from its value in ``params``; frictionless only: the lagged
        friction parameters would have to follow every control step). ``reuse`` in (0, 1):
        keep factorisations across control steps (``keeps``); the chord corrections must
        then cut |r| by at least this factor each. A dense model then solves with
        ``QuasiNewton(DenseSolver(inverse=True), memory)``: L^-1 is kept (solves are
        matrix-vector products, and a kept factorisation serves many) and the corrections'
        secant pairs improve it (L-BFGS), across control steps too."""
        problem = model.problem(params)
        tools = contact_tools(problem)
        if driven in model.set_names:
            G, tool = model.directions(driven), None
        elif driven in tools:
            G, tool = jnp.zeros((model.dim,) + model.initial().g.shape), driven
        else:
            raise ValueError(f"driven must name an essential set of the model ({list(model.set_names)}) or one of "
                             f"its Contact terms ({tools}), got {driven!r}")
        if tool is not None and float(problem.term(tool).mu) > 0:
            raise ValueError(f"contact {tool!r} has friction (mu = {float(problem.term(tool).mu)}): tracking drives "
                             "frictionless tools only (the lagged friction parameters would have to follow every "
                             "control step); give params={name: {'mu': 0.0}} or a tool with mu=0")
        sf = model.shape_functions(np.atleast_2d(np.asarray(control_points, float)), gradients=False)
        linear = model.linear
        if reuse:
            linear = secant(linear, memory)
        newton = Newton(linear, reuse=reuse)
        return ControlledModel(problem, G, jnp.asarray(sf.idx), jnp.asarray(sf.psi), LoadPath(newton),
                               Chord(linear, reuse=reuse), tool=tool)

    def at(self, mp) -> "ControlledModel":
        """This model with the manipulation point at ``mp`` (from the start): a tool's problem
        with the tool moved there; a driven set's as it is (its move is in the prescribed
        values, ``_moved``)."""
        if self.tool is None:
            return self
        start = self.problem.term(self.tool).position
        return replace(self, problem=self.problem.replace(params={self.tool: {"position": start + mp}}))

    @property
    def keeps(self) -> bool:
        """Whether a factorisation is kept across control steps (static: the chord's reuse
        > 0) and refactorised only where the chord corrections contract too slowly; else every
        control step factorises K_ff at its converged state."""
        return self.chord.reuse > 0

    @property
    def linear(self):
        return self.chord.linear

    def factorise(self, sol: Solution):
        """The linear solver's factorisation of K_ff at ``sol``."""
        return self.linear.state_at(self.problem, sol.u, sol.g, sol.load)

    def roundoff_floor(self, sol: Solution):
        """The round-off floor of the residual test at ``sol`` (``Tolerance``)."""
        return self.chord.tolerance.floor(self.problem.force_scales(sol.u, sol.g)[1])

    def measure(self, sol: Solution):
        """Control point displacements, flattened (C*d,)."""
        return self.problem.point_values(self.idx, self.psi, sol.u, sol.g).ravel()

    def response(self, sol: Solution, state, guess=None):
        """du (d_mp, Nf, d): the free coefficients' sensitivity to the manipulation point at
        ``sol`` from its factorisation ``state`` (with ``keeps``, of an earlier state: refined
        with exact products to this state's, to ``jacobian_rtol``, from ``guess``, e.g. the
        response of the previous control step, where given). Of a tool: to its position
        (the residual's derivative in that parameter), the problem being this one's at the
        manipulation point of ``sol`` (``at``)."""
        refine = self.jacobian_rtol if self.keeps else 0.0
        if self.tool is None:
            return response(self.problem, self.linear, sol.u, sol.g, sol.load, self.G, state, refine=refine,
                            guess=guess)
        return parameter_response(self.problem, self.linear, sol.u, sol.g, sol.load, self.tool, "position", state,
                                  refine=refine, guess=guess)

    def jacobian(self, sol: Solution, state, du=None):
        """J = d CP / d MP (C*d, d_mp) at ``sol`` from its factorisation ``state`` (see
        ``response``), or from the ``response`` ``du`` there where it is already known."""
        du = self.response(sol, state) if du is None else du
        J = point_jacobian(self.problem, self.idx, self.psi, sol.u, sol.g, du, self.G)
        return J.reshape(-1, self.G.shape[0])

    def settle(self, sol: Solution, state, g1, lim: Limits, max_corr: int, du=None, floor=None):
        """Equilibrium at the prescribed values g1 (and, of a tool, at this model's problem:
        ``at`` the new manipulation point) from the converged ``sol``: returns
        (Solution, the factorisation to keep). ``du`` (Nf, d): the change of the free
        coefficients predicted for the move (``predicted_change``); where given, the chord
        starts at g1 from sol.u + du (from sol.u where du is not finite) instead of from the
        kept factorisation's own predictor. ``floor``: the round-off floor of the chord's
        residual test (``roundoff_floor``), where the caller keeps one (default: the chord
        computes it).

        The Newton predictor and up to ``max_corr`` (with ``keeps``: ``corrections``) chord
        corrections with the factorisation ``state`` (no assembly), to the solver's residual
        tolerance. Where they fail (a tangent that is not positive definite, no residual
        decrease, det F <= 0, or with ``keeps`` a correction that cuts |r| by less than the
        chord's reuse): with ``keeps``, a fresh factorisation at the chord's last iterate and
        chord corrections from there (that factorisation is the one kept); then, if still not
        converged, the full adaptive load path (and, with ``keeps``, a factorisation at its
        end).

        With ``keeps`` the ``state`` may factorise an earlier state than ``sol``: the
        stability reported is that of the factorisation used (of a nearby, earlier state),
        and a loss of stability shows as a chord that stops contracting (a refactorisation,
        whose stability is then checked).

        The Solution returned carries the settle's linear work (``stats``)."""
        prob = self.problem
        # the loop carries its factorisations itself (``state``), and counts the work apart
        sol = sol._replace(linear=None, params=None, stats=LinearStats.of())
        # a kept factorisation is given up by its contraction (the chord's reuse), not a count
        cap = max(max_corr, self.corrections) if self.keeps else max_corr

        def chord(u, g0, st):
            return self.chord.solve(prob, u, g0, g1, sol.load, sol.load, st, max_iter=cap + 1, floor=floor)

        # a tool's move is in the problem, not in g: the first solve is a Newton step at the
        # moved tool from the last state (the predictor's linearisation along g would be zero)
        u0, g0 = sol.u, (sol.g if self.tool is None else None)
        if du is not None:
            # from the predicted state at g1; where the prediction is not finite (after a failed
            # solve), from the last state moved to g1, whose residual the first step takes up
            u0, g0 = jnp.where(jnp.all(jnp.isfinite(du)), sol.u + du, sol.u), None
        u, st, its, rn, learned, work = chord(u0, g0, state)
        if self.keeps:
            state = learned   # with a quasi-Newton solver: the secant pairs of the corrections

            def refactorised():
                fresh = self.linear.state_at(prob, u, g1, sol.load)
                v, st2, its2, rn2, kept, work2 = chord(u, None, fresh)
                return v, st2, its + its2, rn2, kept, work + self.linear.work(fresh) + work2

            u, st, its, rn, state, work = when(st != Status.CONVERGED, refactorised, (u, st, its, rn, state, work))
        quick = Solution(u, g1, sol.load, jnp.zeros_like(sol.status), jnp.ones_like(sol.t),
                         its.astype(sol.iterations.dtype), jnp.ones_like(sol.steps),
                         jnp.zeros_like(sol.cuts), rn.astype(sol.residual_norm.dtype),
                         jnp.zeros_like(sol.branch), sol.critical, stats=work)

        def full():
            new = self.driver.solve(prob, lim, sol.u, sol.g, g1, sol.load, sol.load)
            kept = self.factorise(new) if self.keeps else state
            stats = work + new.stats + (self.linear.work(kept) if self.keeps else LinearStats.of())
            new = jax.tree.map(lambda a, b: a.astype(b.dtype), new._replace(stats=stats), sol)   # the carry's dtypes
            return new, kept

        return when(st != Status.CONVERGED, full, (quick, state))


@dataclass(frozen=True)
class TrackResult:
    """History of a tracking run (numpy arrays, n = iterations run).

    mp (n+1, d_mp) manipulation point displacement, cp (n+1, C*d) control point displacement
    (plant), error (n+1,) |e| against the current waypoint, waypoint (n+1,) its index,
    newton (n+1,) nonlinear iterations (linear solves: predictor + corrections) of the step,
    solve_status (n+1,); reached (W,) iteration at which each waypoint was reached (-1 if
    not); achieved (W, C*d) the control point there; desired (W, C*d); tool_start (d,) where
    a contact tool was driven, its position at the start (the plant's; None for a set);
    stats the run's linear algebra (``LinearStats``).
    Where a solve failed, its iteration's row holds the last converged state and the failed
    solve's status."""

    mp: np.ndarray
    cp: np.ndarray
    error: np.ndarray
    waypoint: np.ndarray
    newton: np.ndarray
    solve_status: np.ndarray
    reached: np.ndarray
    achieved: np.ndarray
    desired: np.ndarray
    status: TrackStatus
    controller_solution: Solution
    plant_solution: Solution
    tool_start: np.ndarray | None = None
    stats: LinearStats | None = None   # the run's linear work (every solve and Jacobian)

    @property
    def tool_position(self) -> np.ndarray:
        """(n+1, d) the driven contact tool's position at every iteration (the plant's tool:
        its start plus ``mp``); a ``ValueError`` where an essential set was driven."""
        if self.tool_start is None:
            raise ValueError("this run drove an essential set, not a contact tool: its displacement is mp")
        return self.tool_start + self.mp

    @property
    def waypoint_errors(self) -> np.ndarray:
        err = np.linalg.norm(self.achieved - self.desired, axis=1)
        return np.where(self.reached >= 0, err, np.nan)

    @property
    def max_waypoint_error(self) -> float:
        return float(np.nanmax(self.waypoint_errors)) if np.any(self.reached >= 0) else float("nan")

    @property
    def message(self) -> str:
        n = int(np.sum(self.reached >= 0))
        return f"{self.status.name}: {self.status.message} ({n}/{len(self.reached)} waypoints, " \
               f"{len(self.error) - 1} iterations)"


def response_trend(du, dmp, du_last, last_move):
    """The change of the response du = d u / d mp (d_mp, Nf, d) over the move ``dmp`` (d_mp,)
    of the manipulation point, H[dmp, .] with H = d^2 u / d mp^2, estimated from its change
    along the last move: du - du_last ~ H[last_move, .] (``du_last``: the response at the state
    before ``last_move``), so H[dmp, .] ~ c (du - du_last) with c = dmp . last_move /
    |last_move|^2. Exact to first order where the moves are parallel (a path's straight legs,
    where the control moves by the increment clamp); where they turn it misses the part across
    the last move. Zero where no move preceded (``last_move`` = 0) or ``du_last`` is not finite
    (after a failed solve)."""
    p2 = jnp.sum(last_move * last_move)
    valid = (p2 > 0) & jnp.all(jnp.isfinite(du_last))
    c = jnp.where(valid, jnp.sum(dmp * last_move) / jnp.where(valid, p2, 1.0), 0.0)
    return c * jnp.where(valid, du - du_last, 0.0)


def predicted_change(du, dmp, trend=None):
    """The change of the free coefficients (Nf, d) for the move ``dmp`` (d_mp,) from the
    response ``du`` (d_mp, Nf, d): du . dmp, to first order; with the ``response_trend`` over
    that move, plus the second-order term 1/2 H[dmp, dmp] (second-order accurate along a
    straight leg of the path, first-order where it turns)."""
    first = jnp.einsum("a,aij->ij", dmp, du)
    return first if trend is None else first + 0.5 * jnp.einsum("a,aij->ij", dmp, trend)


class TrackModels(NamedTuple):
    """The tracking loop's problem: the controller (whose Jacobian drives the moves) and the
    plant (moved and measured; the controller itself where ``Tracker.same``)."""

    ctrl: ControlledModel
    plant: ControlledModel


class TrackArgs(NamedTuple):
    """The tracking loop's constants (arrays: other values do not recompile)."""

    lim: Limits          # the adaptive solve's limits, where a settle needs it
    desired: jax.Array   # (W, C*d) the waypoints
    gain: jax.Array      # () K
    clamp: jax.Array     # () the largest component of a move
    tol: jax.Array       # () a waypoint is reached when |e| < tol
    damping: jax.Array   # () of the least-squares increment (``control_increment``)
    c_base: jax.Array    # (Nb, d) the controller's prescribed values at the start: the
    p_base: jax.Array    # (Nb, d) plant's; the manipulation point moves relative to them
    c_floor: jax.Array   # () the controller's chord round-off floor (``Tracker.constants``)
    p_floor: jax.Array   # () the plant's


class History(NamedTuple):
    """The history of a tracking run (``TrackResult`` holds it as numpy arrays): arrays of
    max_steps + 1 rows, or one row of them (``Tracker.record``)."""

    mp: jax.Array            # (H, d_mp) manipulation point displacement
    cp: jax.Array            # (H, C*d) control point displacement (plant)
    error: jax.Array         # (H,) |e| against the current waypoint
    waypoint: jax.Array      # (H,) its index
    newton: jax.Array        # (H,) nonlinear iterations of the step
    solve_status: jax.Array  # (H,) the worse of the two solves' statuses


class TrackState(NamedTuple):
    """The tracking loop's state between iterations (``Tracker``)."""

    k: jax.Array             # () iterations run (history rows written after the first)
    wp: jax.Array            # () the waypoint tracked
    it_wp: jax.Array         # () iterations spent on it
    best: jax.Array          # () the smallest error towards it that counted as progress
    since_best: jax.Array    # () iterations since that error
    mp: jax.Array            # (d_mp,) manipulation point displacement
    c: Solution              # the controller's last converged state
    p: Solution              # the plant's
    cp: jax.Array            # (C*d,) control point displacement there (plant)
    hist: History
    reached: jax.Array       # (W,) iteration at which each waypoint was reached (-1 if not)
    achieved: jax.Array      # (W, C*d) the control point there
    done: jax.Array          # () the run is over (short of the waypoints)
    status: jax.Array        # () its TrackStatus (while running: HISTORY_FULL, what a stop there is)
    c_state: Any             # the kept factorisations (``ControlledModel.keeps``; else unused)
    p_state: Any
    du: jax.Array            # (d_mp, Nf, d) the controller's last response
    last_move: jax.Array     # (d_mp,) the last iteration's move (zero where it hit a waypoint or failed)
    du_next: jax.Array       # the response predicted at the current state (keeps: where its CG starts)
    stats: LinearStats       # the linear work so far


class TrackStep(NamedTuple):
    """What one control iteration changes (``Tracker.move``)."""

    mp: jax.Array
    c: Solution
    p: Solution
    cp: jax.Array
    newton: jax.Array
    solve_status: jax.Array
    c_state: Any
    p_state: Any
    du: jax.Array
    trend: jax.Array   # the response's predicted change over the move (``response_trend``)
    stats: LinearStats   # the iteration's linear work


class Tracked(NamedTuple):
    """``Tracker.run``'s result: what ``TrackResult`` is made of (the history in full)."""

    iterations: jax.Array
    status: jax.Array   # the TrackStatus
    hist: History
    reached: jax.Array
    achieved: jax.Array
    controller: Solution
    plant: Solution
    stats: LinearStats


@dataclass(frozen=True)
class Tracker(IterativeSolver):
    """Algorithm 3 as a driver of ``iterate`` (see ``track`` for the settings): each ``step``
    is one control iteration over ``TrackModels`` with ``TrackArgs``. One factorisation of the
    controller at its converged state serves the Jacobian and the settling of the next state
    (``ControlledModel.settle``); a separate plant is settled the same way with its own.

    same        the plant is the controller (``TrackModels.plant`` is the controller, not
                solved twice)
    max_iter    iterations per waypoint (then ITERATION_CAP)
    max_steps   iterations in all (then HISTORY_FULL; the history has max_steps + 1 rows)
    window      iterations without a 1% error decrease (then NO_PROGRESS)
    max_corr    chord corrections of a settle (``ControlledModel.settle``)

    Static: ``run`` compiles once per setting, the models' arrays and ``TrackArgs`` traced."""

    same: bool
    max_iter: int
    max_steps: int
    window: int
    max_corr: int = 6

    def __post_init__(self):
        flag("same", self.same)
        for name in ("max_iter", "max_steps", "window"):
            count(name, getattr(self, name), 1)
        count("max_corr", self.max_corr)

    @partial(jax.jit, static_argnums=0)
    def run(self, ctrl: ControlledModel, plant: ControlledModel, lim: Limits, c0: Solution, p0: Solution,
            desired, gain, clamp, tol, damping) -> Tracked:
        """Track ``desired`` (W, C*d) from the equilibria c0 and p0 (one jitted while-loop)."""
        models = TrackModels(ctrl, plant)
        # the loop carries its own factorisations and counts its work apart: the ones the
        # Solutions kept stay out of its carry
        c0, p0 = (x._replace(linear=None, params=None, stats=LinearStats.of()) for x in (c0, p0))
        args = self.constants(models, lim, c0, p0, desired, gain, clamp, tol, damping)
        return run_solver(self, models, args, (c0, p0))

    def constants(self, models: TrackModels, lim, c0, p0, desired, gain, clamp, tol, damping) -> TrackArgs:
        # the chords' round-off floors, once, at the start: the floor is a stiffness times machine
        # epsilon with a wide margin over the round-off actually left in |r| (``Tolerance``), and
        # the tracked object moves by small increments, so the floor of the start serves the whole
        # path; its own pass through the material costs as much as a chord correction
        # (``experiments/bench_tracking.py``)
        c_floor = models.ctrl.roundoff_floor(c0)
        p_floor = c_floor if self.same else models.plant.roundoff_floor(p0)
        return TrackArgs(lim, desired, gain, clamp, tol, damping, c0.g, p0.g, c_floor, p_floor)

    def init(self, models: TrackModels, args: TrackArgs, start) -> TrackState:
        """From the equilibria ``start`` = (controller's, plant's)."""
        ctrl, plant = models
        c0, p0 = start
        dim_mp = ctrl.G.shape[0]
        n_wp, n_cp = args.desired.shape
        H = self.max_steps + 1
        hist = History(jnp.zeros((H, dim_mp)), jnp.zeros((H, n_cp)), jnp.zeros(H), jnp.zeros(H, jnp.int32),
                       jnp.zeros(H, jnp.int32), jnp.zeros(H, jnp.int32))
        cp0 = plant.measure(p0)
        hist = hist._replace(cp=hist.cp.at[0].set(cp0),
                             error=hist.error.at[0].set(jnp.linalg.norm(args.desired[0] - cp0)))
        c_state0, work = self._first_factorisation(ctrl, c0)
        p_state0 = c_state0
        if not self.same:
            p_state0, p_work = self._first_factorisation(plant, p0)
            work = work + p_work
        return TrackState(jnp.array(0), jnp.array(0), jnp.array(0), jnp.array(jnp.inf), jnp.array(0), jnp.zeros(dim_mp),
                          c0, p0, cp0, hist, -jnp.ones(n_wp, jnp.int32), jnp.zeros((n_wp, n_cp)), jnp.array(False),
                          jnp.array(TrackStatus.HISTORY_FULL), c_state0, p_state0,
                          jnp.zeros((dim_mp,) + c0.u.shape, c0.u.dtype), jnp.zeros(dim_mp),
                          jnp.zeros((dim_mp,) + c0.u.shape, c0.u.dtype), work)

    def terminate(self, s: TrackState):
        """Done on a stop (``status``) or once every waypoint is reached (DONE)."""
        finished = s.wp >= s.reached.shape[0]
        return s.done | finished, jnp.where(finished & ~s.done, TrackStatus.DONE, s.status)

    def postprocess(self, models: TrackModels, args: TrackArgs, s: TrackState, status) -> Tracked:
        return Tracked(s.k, status, s.hist, s.reached, s.achieved, s.c, s.p, s.stats)

    def step(self, models: TrackModels, args: TrackArgs, s: TrackState) -> TrackState:
        """One control iteration; where the control point is already at its waypoint (|e| <
        tol), the next waypoint instead: no solve counts, the states and history stay."""
        e = args.desired[s.wp] - s.cp
        hit = jnp.linalg.norm(e) < args.tol
        # the step is taken and discarded on the (few) iterations that hit a waypoint: cheaper
        # than a lax.cond around it on every iteration. The factorisations it made are kept
        # even then (and after a failed solve): each is of a nearby state, which is all a kept
        # factorisation is (the residual test decides convergence), and a select would copy
        # them (3 n^2 doubles) at every iteration
        new = self.move(models, args, s, e)
        st = self.taken(s, new, hit)
        moved = ~hit
        ok = reached_equilibrium(st.c.status) & reached_equilibrium(st.p.status)
        k = s.k + moved
        # a failed solve keeps the last converged states: the history row of that iteration
        # holds them (with the failed solve's status), never the attempted, unbalanced move
        c, p, mp, cp = jax.tree.map(lambda a, b: jnp.where(ok, a, b), (st.c, st.p, st.mp, st.cp),
                                    (s.c, s.p, s.mp, s.cp))
        e_new = jnp.linalg.norm(args.desired[s.wp] - cp)
        best, since = self.progress(s, e_new)
        at = jnp.where(moved, k, self.max_steps + 1)   # out of range: dropped (no row for a waypoint hit)
        hist = self.record(s.hist, at, History(mp, cp, e_new, s.wp, st.newton, st.solve_status))
        after = self.next_waypoint(s, hit, best, since, *self.status(s, ok, k, since))
        return after._replace(k=k, mp=mp, c=c, p=p, cp=cp, hist=hist, c_state=new.c_state, p_state=new.p_state,
                              du=new.du, last_move=jnp.where(ok & moved, st.mp - s.mp, 0.0),
                              du_next=jnp.where(ok & moved, new.du + new.trend, new.du), stats=s.stats + new.stats)

    # -------------------------------------------------------------------------- parts
    def move(self, models: TrackModels, args: TrackArgs, s: TrackState, e) -> TrackStep:
        """The control increment K J^+ e from the controller's Jacobian at its state, and both
        models settled at the moved manipulation point."""
        ctrl, plant = models
        # a tool's problem moves with the manipulation point (``ControlledModel.at``; a driven set's stays)
        here = ctrl.at(s.mp)
        state, work = self._factorisation(here, s.c, s.c_state)
        # with a kept factorisation the response is refined by CG: it starts from the one
        # predicted for this state (the last one plus its trend), which saves most of CG's
        # iterations (``experiments/bench_tracking.py``, ``experiments/bench_cube3d.py``);
        # one that is not finite, after a failed solve, is no guess: CG starts from 0
        guess = jnp.where(jnp.all(jnp.isfinite(s.du_next)), s.du_next, 0.0) if ctrl.keeps else None
        du = here.response(s.c, state, guess)
        dmp = control_increment(here.jacobian(s.c, state, du), e, args.gain, args.clamp, args.damping)
        mp = s.mp + dmp
        # with a kept factorisation (of an earlier state) its own predictor is poor: the
        # response, refined to this state's, predicts the move, to second order along the path
        trend = response_trend(du, dmp, s.du, s.last_move) if ctrl.keeps else jnp.zeros_like(du)
        du_move = predicted_change(du, dmp, trend) if ctrl.keeps else None
        c, c_state = ctrl.at(mp).settle(s.c, state, _moved(ctrl, args.c_base, mp), args.lim, self.max_corr,
                                        du_move, args.c_floor)
        # the response's solve (one block of right-hand sides) and the controller's settle
        work = work + LinearStats.of(solves=1) + c.stats
        if self.same:
            p, p_state = c, c_state
        else:
            p_factorised, p_work = self._factorisation(plant.at(s.mp), s.p, s.p_state)
            p, p_state = plant.at(mp).settle(s.p, p_factorised, _moved(plant, args.p_base, mp), args.lim,
                                             self.max_corr, floor=args.p_floor)
            work = work + p_work + p.stats
        return TrackStep(mp, c, p, plant.measure(p), c.iterations + (0 if self.same else p.iterations),
                         jnp.maximum(c.status, p.status), c_state, p_state, du, trend, work)

    @staticmethod
    def taken(s: TrackState, new: TrackStep, hit) -> TrackStep:
        """The step kept: ``new``, or where the waypoint was hit, none (the state as it was,
        no iterations); the factorisations and responses are not selected (``step``)."""
        keep = TrackStep(s.mp, s.c, s.p, s.cp, jnp.array(0, s.c.iterations.dtype), jnp.array(0, s.c.status.dtype),
                         None, None, None, None, None)
        return jax.tree.map(lambda a, b: jnp.where(hit, a, b), keep,
                            new._replace(c_state=None, p_state=None, du=None, trend=None, stats=None))

    @staticmethod
    def progress(s: TrackState, error):
        """(best, since_best) after an iteration that ended at ``error``: an error 1% below
        the best so far counts as progress."""
        improved = error < 0.99 * s.best
        return jnp.where(improved, error, s.best), jnp.where(improved, 0, s.since_best + 1)

    @staticmethod
    def record(hist: History, at, row: History) -> History:
        """The history with ``row`` written at ``at`` (dropped where out of range)."""
        return History(*(h.at[at].set(v.astype(h.dtype), mode="drop") for h, v in zip(hist, row)))

    def status(self, s: TrackState, ok, k, since):
        """(stop, why) after an iteration from ``s``: whether the run stops, and its
        TrackStatus (HISTORY_FULL where it goes on: the status of a stop there)."""
        stop = ~ok | (s.it_wp + 1 >= self.max_iter) | (since >= self.window) | (k >= self.max_steps)
        why = jnp.where(~ok, TrackStatus.SOLVE_FAILED,
                        jnp.where(s.it_wp + 1 >= self.max_iter, TrackStatus.ITERATION_CAP,
                                  jnp.where(since >= self.window, TrackStatus.NO_PROGRESS, TrackStatus.HISTORY_FULL)))
        return stop, why

    @staticmethod
    def next_waypoint(s: TrackState, hit, best, since, stop, status) -> TrackState:
        """``s`` with the waypoint bookkeeping of the iteration from it: where the waypoint
        was hit, its record (the iteration and control point of ``s``) and the next
        waypoint, its counters reset and the run going on (no solve counted, the states
        and history stay); else the iteration's counters (``progress``), ``stop`` and
        ``status``."""
        at_wp = jnp.where(hit, s.wp, s.reached.shape[0])   # out of range: dropped
        return s._replace(wp=s.wp + hit, it_wp=jnp.where(hit, 0, s.it_wp + 1), best=jnp.where(hit, jnp.inf, best),
                          since_best=jnp.where(hit, 0, since),
                          reached=s.reached.at[at_wp].set(s.k.astype(s.reached.dtype), mode="drop"),
                          achieved=s.achieved.at[at_wp].set(s.cp, mode="drop"), done=jnp.where(hit, s.done, stop),
                          status=jnp.where(hit, s.status, status))

    @staticmethod
    def _factorisation(side: ControlledModel, sol: Solution, kept):
        """The factorisation a control step of ``side`` uses at ``sol`` and its LinearStats:
        the ``kept`` one, or one made there."""
        if side.keeps:
            return kept, LinearStats.of()
        state = side.factorise(sol)
        return state, side.linear.work(state)

    @staticmethod
    def _first_factorisation(side: ControlledModel, sol: Solution):
        """The factorisation kept from the start (a placeholder if none is) and its
        LinearStats."""
        if side.keeps:
            state = side.factorise(sol)
            return state, side.linear.work(state)
        return side.linear.empty(side.problem, sol.u.dtype), LinearStats.of()


def _moved(side: ControlledModel, g_base, mp):
    """The prescribed values of ``side`` with the manipulation point at ``mp``."""
    return g_base + jnp.einsum("a,abi->bi", mp, side.G)


def track_loop(ctrl: ControlledModel, plant: ControlledModel, same: bool, lim: Limits, c0: Solution,
               p0: Solution, desired, gain, clamp, tol, damping, max_iter: int, max_steps: int,
               window: int, max_corr: int = 6):
    """Algorithm 3 as one jitted while-loop: ``Tracker(same, max_iter, max_steps, window,
    max_corr).run(...)`` (see ``track`` for the arguments). Returns (iterations, TrackStatus
    code, history dict, reached, achieved, controller Solution, plant Solution)."""
    out = Tracker(same, max_iter, max_steps, window, max_corr).run(ctrl, plant, lim, c0, p0, desired, gain, clamp,
                                                                  tol, damping)
    return out.iterations, out.status, out.hist._asdict(), out.reached, out.achieved, out.controller, out.plant


def _kept(model: Model, reuse: float | None) -> float:
    """``track``'s reuse for ``model`` where none is given: factorisations kept across control
    steps on the dense path, refactorised where a chord correction cuts |r| by less than 2x
    (the same waypoints at the same iterations, fewer factorisations:
    ``experiments/bench_tracking.py``, ``experiments/bench_cube3d.py``); not on the sparse
    path, whose chord corrections are refined host solves with no secant update."""
    if reuse is not None:
        return reuse
    return 0.5 if model.linear.modified_newton else 0.0


def track(model: Model, path, driven: str, control_points, *, plant: Model | None = None,
          plant_driven: str | None = None, gain: float = 0.05, clamp: float = 0.01,
          tol: float = 1e-4, damping: float = 0.0, max_iter: int = 2000, max_steps: int = 20000,
          window: int = 300, initial: Solution | None = None, plant_initial: Solution | None = None,
          params=None, plant_params=None, reuse: float | None = None) -> TrackResult:
    """Track a path of control point displacements (W, C*d) by moving ``driven``
    (Algorithm 3), the name of either

    - an essential set of ``model``: moved rigidly (translated), glued to the body; the run
      starts from ``initial`` (default: the undeformed, unloaded state); or
    - a ``Contact`` term of ``model`` (a tool that can push the body, never pull it): its
      position at load scale 1 is moved (its rotation held at its value in ``params``),
      and J = d CP / d(tool position) comes from the residual's derivative in that
      parameter. The run starts from ``initial``, a solution at load scale 1 with the tool at
      its ``params`` pose (default: ``model.solve(params=params)``, which raises where it
      fails). Frictionless tools only (mu = 0; a ``ValueError`` otherwise). A waypoint that
      needs the tool to pull is not reached (NO_PROGRESS or ITERATION_CAP): once the tool
      leaves the body J is zero and the increment too (so a tool must touch the body at
      the start to move it). The moves are not load-stepped, so
      ``clamp`` should be a few of the tool's ``gap``; ``TrackResult.tool_position`` is the
      tool's position at every iteration.

    ``plant``: a second model that is actually moved and measured (its driven set or tool
    ``plant_driven``, default the same name, of the same kind as ``driven``); the
    controller's Jacobian drives it. Stops with a status (never raises on an unreachable
    waypoint or a failed solve) and keeps the whole history.

    ``reuse`` in (0, 1): keep factorisations across iterations, refactorised only where a
    chord correction cuts the residual by less than this factor (see ``ControlledModel.of``;
    same residual tolerance; the Jacobian then comes from the kept factorisation of a nearby
    earlier state, refined to this state's: ``ControlledModel.jacobian``); 0: one
    factorisation per iteration; None (default): 0.5 for a model on the dense path, 0 on the
    sparse and Krylov paths."""
    path = np.atleast_2d(np.asarray(path, float))
    cps = np.atleast_2d(np.asarray(control_points, float))
    _check_path(path, cps)
    _check_track_options(gain, clamp, tol, damping, max_iter, max_steps, window, reuse)
    ctrl = ControlledModel.of(model, driven, cps, params, _kept(model, reuse))
    same = plant is None
    plant_model = model if same else plant
    pside = ctrl if same else ControlledModel.of(plant_model, plant_driven or driven, cps, plant_params,
                                                 _kept(plant_model, reuse))
    _check_sides(ctrl, pside, driven, plant_driven)
    c0 = _start(model, ctrl, initial, params, "initial")
    p0 = c0 if same else _start(plant_model, pside, plant_initial, plant_params, "plant_initial")
    # a tool's move is in the problem, not along the load path: cutting a failed step moves nothing
    lim = Limits.of(steps=1) if ctrl.tool is None else Limits.of(steps=1, max_cuts=0)
    out = Tracker(same, int(max_iter), int(max_steps), int(window)).run(
        ctrl, pside, lim, c0, p0, jnp.asarray(path), gain, clamp, tol, damping)
    n = int(out.iterations) + 1
    h = History(*(np.asarray(v)[:n] for v in out.hist))
    start = None if pside.tool is None else np.asarray(pside.problem.term(pside.tool).position)
    return TrackResult(*h, np.asarray(out.reached), np.asarray(out.achieved), path, TrackStatus.of(out.status),
                       out.controller, out.plant, start, LinearStats(*(np.asarray(v) for v in out.stats)))


def _check_path(path, cps):
    if path.ndim != 2 or path.shape[1] != cps.size or len(path) == 0:
        raise ValueError(f"path must have {cps.size} columns (control points x dimensions), got {path.shape}")
    if not np.all(np.isfinite(path)):
        raise ValueError(f"path has non-finite waypoints (rows {np.flatnonzero(~np.isfinite(path).all(1)).tolist()})")


def _check_track_options(gain, clamp, tol, damping, max_iter, max_steps, window, reuse):
    for name, v in (("gain", gain), ("clamp", clamp), ("tol", tol)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be positive, got {v}")
    if not (np.isfinite(damping) and damping >= 0):
        raise ValueError(f"damping must be a finite number >= 0, got {damping}")
    for name, v in (("max_iter", max_iter), ("max_steps", max_steps), ("window", window)):
        count(name, v, 1)
    if not (reuse is None or (isinstance(reuse, (int, float)) and 0 <= reuse < 1)):
        raise ValueError(f"reuse must be None or a number in [0, 1) (0: factorise at every iteration), "
                         f"got {reuse!r}")


def _check_sides(ctrl: ControlledModel, pside: ControlledModel, driven, plant_driven):
    if pside.G.shape[0] != ctrl.G.shape[0]:
        raise ValueError("controller and plant must drive the same number of coordinates")
    if (pside.tool is None) != (ctrl.tool is None):
        raise ValueError("controller and plant must both drive an essential set or both a contact tool, got "
                         f"{driven!r} and {plant_driven or driven!r}")


def _start(model: Model, side: ControlledModel, initial: Solution | None, params, what: str) -> Solution:
    """Where ``side`` starts: ``initial``, or by default the undeformed, unloaded state (a
    driven set) or the equilibrium with the tool at its ``params`` pose (a tool, whose pose
    is that of load scale 1)."""
    if side.tool is None:
        return model.initial() if initial is None else initial
    if initial is None:
        return model.solve(params=params)
    if float(initial.load) != 1.0:
        raise ValueError(f"{what}: a contact tool is moved at load scale 1 (its pose there is its params' "
                         f"position), so the run must start from a solution at loads=1, got load {float(initial.load)}")
    return initial


# ----------------------------------------------------------------- analysis of a TrackResult
def waypoint_table(res: TrackResult) -> list[dict]:
    """Per waypoint: desired, achieved, error, the iterations spent on it, and when."""
    rows, prev = [], 0
    for i, (des, ach, k) in enumerate(zip(res.desired, res.achieved, res.reached)):
        k = int(k)
        if k >= 0:
            rows.append({"index": i, "desired": des.tolist(), "achieved": ach.tolist(),
                         "error": float(np.linalg.norm(ach - des)), "iterations": k - prev,
                         "reached_at": k})
            prev = k
        else:
            spent = int(np.sum(res.waypoint[1:] == i))
            last = res.cp[-1]
            rows.append({"index": i, "desired": des.tolist(), "achieved": None,
                         "error": None, "iterations": spent, "reached_at": None,
                         "closest": float(np.min(res.error[1:][res.waypoint[1:] == i]))
                         if spent else float(np.linalg.norm(last - des))})
    return rows


def path_deviation(res: TrackResult) -> np.ndarray:
    """Distance of the control point, at every iteration, from the desired segment it is
    travelling along (previous waypoint -> current waypoint): (n+1,)."""
    w = np.asarray(res.waypoint).astype(int)
    return distance_to_segment(np.asarray(res.cp, float), res.desired[np.maximum(w - 1, 0)],
                               res.desired[w])
