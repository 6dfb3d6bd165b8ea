"""Adaptive load stepping from one equilibrium to another: ``LoadPath``, the driver of every
solve, over a ``Newton`` solver (and a ``BranchSwitch`` past critical points).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.checks import count, flag, positive
from .branch import BranchSwitch
from .iterate import IterativeSolver, run, when
from .linalg.base import LinearStats
from .newton import Newton
from .results import Critical, Limits, Solution, Status, Stop


class Path(NamedTuple):
    """The driver's constants: the increment asked for and the step sizes it may take."""

    g0: jax.Array         # (Nb, d) prescribed values at the start
    g1: jax.Array         # (Nb, d) at the end
    l0: jax.Array         # () load scale at the start
    l1: jax.Array         # () at the end
    dt0: jax.Array        # () the initial (and largest) step, as a fraction of the increment
    dt_min: jax.Array     # () the smallest step allowed
    dt_locate: jax.Array  # () the step that pins a critical point before a branch switch
    nominal: jax.Array    # () a converging solve's nominal Newton work (steps x easy)
    max_iter: jax.Array   # () Newton iterations per step
    p0: Any = None        # the problem's parameters at the start (None: its own throughout)
    state0: Any = None    # the linear solver's state at the start (None: an empty one)

    def problem_at(self, problem, t):
        """``problem`` with its parameters at the fraction t of the increment: from ``p0`` to
        its own, like g, so that cutting a step also shrinks a change of parameters (a tool's
        pose)."""
        if self.p0 is None:
            return problem

        def lerp(a, b):
            if not jnp.issubdtype(jnp.result_type(b), jnp.inexact):
                return b
            return jnp.where(t >= 1.0, b, jnp.where(t > 0.0, a + t * (b - a), a))
        return problem.replace(params=jax.tree.map(lerp, self.p0, problem.params))

    def at(self, t):
        """(g, load) at the fraction t of the increment: exactly g0 before the first converged
        step (a NaN in g1 must not leak into the kept state: 0 * NaN is NaN) and exactly g1 at
        the end."""
        def lerp(a, b):
            return jnp.where(t >= 1.0, b, jnp.where(t > 0.0, a + t * (b - a), a))
        return lerp(self.g0, self.g1), lerp(self.l0, self.l1)


class PathState(NamedTuple):
    t: jax.Array              # () fraction of the increment reached
    dt: jax.Array             # () the next step
    u: jax.Array              # (Nf, d) the last converged state
    status: jax.Array         # () 0 while running (or done), else the failing Status
    iterations: jax.Array     # () Newton iterations, all attempts
    steps: jax.Array          # () accepted steps
    cuts: jax.Array           # () failed (cut) steps
    residual_norm: jax.Array  # () |r| of the last converged state
    unknown: jax.Array        # () an accepted state's stability was unknown
    linear: Any               # the linear solver's state, carried from step to step
    branch: jax.Array         # () critical points passed by switching to a stable branch
    critical: Critical        # the critical points passed (fixed size)
    wasted: jax.Array         # () Newton iterations spent in failed attempts
    stats: LinearStats        # the linear work of every attempt


@dataclass(frozen=True)
class LoadPath(IterativeSolver):
    """Adaptive load stepping from the equilibrium (u0, g0, l0) to (g1, l1) by ``newton``.

    Halves the step on failure (up to ``Limits.max_cuts`` times below the initial step), grows
    it by ``growth`` after steps that converge within ``easy`` iterations (never above the
    initial step). On failure the last converged state is returned with the failing status.
    The linear solver's state runs through every step (a sparse factorisation keeps
    preconditioning later steps); the solve may start from a factorisation of K_ff at the
    start (``state0``, e.g. the one an implicit Jacobian there made), which the first step
    uses where the solver keeps states (modified Newton's predictor; the sparse path's
    preconditioner), so the same matrix is not factorised twice; full Newton ignores it.

    Past a critical point (``branch`` given, with the stability check and the dense solver):
    a step whose equilibrium has a K_ff that is not positive definite is cut (as any failure)
    until it is at most dt0 / 2**``locate`` long, which pins the critical point between the
    last stable state and that step's end; then the ``BranchSwitch`` goes on from that unstable
    equilibrium to a stable equilibrium of the same load, and the step is accepted there; if
    none is found the solve stops there with UNSTABLE_TANGENT (the last stable state kept). A
    step whose Newton fails is cut as before (on the Fung squares, a descent from where Newton
    stalled did not reach a stable state within max_iter, at several times a Newton attempt's
    cost). Where K_ff had a negative eigenvalue there, the critical point is recorded in
    ``Solution.critical`` and counted in ``Solution.branch``.

    Failure in bounded time: the Newton iterations spent in failed attempts (cut steps and
    failed switches) may not exceed ``failed_work`` x max(iterations of the accepted steps,
    steps x easy) + 2 x max_iter; the solve gives up (with the failing attempt's status) once
    they would. So a solve that cannot proceed costs at most (1 + failed_work) x the larger of
    the work it did and a converging solve's nominal work, plus two attempts, whatever
    max_cuts allows (without the budget, a solve stuck at a limit point spent tens of times a
    converging solve's work).

    ``keep_linear``: the Solution carries the linear solver's state where the solve ended
    (``Solution.linear``), so that the next solve from it and the implicit Jacobian at it need
    no factorisation of their own. Off inside batched and differentiated solves, where the
    state would be stacked or differentiated for nothing."""

    newton: Newton = Newton()
    easy: int = 4
    growth: float = 1.5
    branch: BranchSwitch | None = None
    locate: int = 6
    failed_work: int = 2
    keep_linear: bool = False   # the Solution carries the linear solver's last state

    def __post_init__(self):
        if not isinstance(self.newton, Newton) or self.newton.chord:
            raise ValueError(f"newton must be a Newton solver (not a chord), got {self.newton!r}")
        count("easy", self.easy)
        positive("growth", self.growth)
        count("locate", self.locate)
        count("failed_work", self.failed_work)
        flag("keep_linear", self.keep_linear)
        if self.branch is not None and not isinstance(self.branch, BranchSwitch):
            raise ValueError(f"branch must be a BranchSwitch or None, got {self.branch!r}")

    @property
    def linear(self):
        return self.newton.linear

    @property
    def switches(self) -> bool:
        """Whether solves go on past a critical point (static): the branch switch needs the
        stability check and the dense tangent (its eigenpairs); other paths stop with
        UNSTABLE_TANGENT."""
        return bool(self.branch is not None and self.newton.check_stability
                    and self.newton.linear.branch_switching)

    def path(self, lim: Limits, g0, g1, l0, l1) -> Path:
        dt0 = 1.0 / lim.steps
        dt_min = dt0 * 0.5 ** lim.max_cuts
        return Path(g0, g1, l0, l1, dt0, dt_min, jnp.maximum(dt0 * 0.5 ** self.locate, dt_min),
                    lim.steps * max(int(self.easy), 1), lim.max_iter)

    def init(self, problem, path: Path, u0) -> PathState:
        zero = jnp.array(0)
        linear = self.linear.empty(problem, u0.dtype) if path.state0 is None else path.state0
        return PathState(jnp.array(0.0), jnp.array(path.dt0), u0, zero, zero, zero, zero, jnp.array(0.0),
                         jnp.array(False), linear, zero, Critical.empty(u0), zero, LinearStats.of())

    def terminate(self, s: PathState):
        """Done at the end of the increment or on a failure (a Status code above 0); an
        accepted state of unknown stability makes a finished path STABILITY_UNKNOWN."""
        done = ~((s.t < 1.0) & (s.status <= 0))
        return done, jnp.where((s.status == 0) & s.unknown, Status.STABILITY_UNKNOWN, s.status)

    def postprocess(self, problem, path: Path, s: PathState, status) -> Solution:
        g, load = path.at(s.t)
        return Solution(s.u, g, load, status, s.t, s.iterations, s.steps, s.cuts, s.residual_norm, s.branch,
                        s.critical, s.linear if self.keep_linear else None, stop=self._stop(path, s), stats=s.stats)

    def step(self, problem, path: Path, s: PathState) -> PathState:
        t, dt, u = s.t, s.dt, s.u
        t1 = jnp.minimum(t + dt, 1.0)
        t1 = jnp.where(1.0 - t1 < 1e-12, 1.0, t1)
        ga, la = path.at(t)
        gb, lb = path.at(t1)
        start, linear, work = u, s.linear, LinearStats.of()
        if path.p0 is not None:   # its factorisation is the one a modified Newton then keeps
            start, linear, work = self._parameter_predictor(path.problem_at(problem, t),
                                                            path.problem_at(problem, t1), u, ga, la)
        problem = path.problem_at(problem, t1)
        res = self.newton.solve(problem, start, ga, gb, la, lb, linear, max_iter=path.max_iter)
        v, st, it, rn_v, linear = res[:5]
        ok = (st == Status.CONVERGED) | (st == Status.STABILITY_UNKNOWN)
        branch, crit, lost = s.branch, s.critical, jnp.array(False)
        if self.switches:
            v, st, it, rn_v, ok, branch, crit, lost = self._switched(problem, path, s, t1, gb, lb, v, st, it, rn_v,
                                                                     ok)
        grow = jnp.where(it <= self.easy, self.growth, 1.0)
        dt_next = jnp.where(ok, jnp.minimum(dt * grow, path.dt0), dt / 2)
        wasted = s.wasted + jnp.where(ok, 0, it)
        # with the branch switch: the critical point is bracketed and no stable state of that
        # load was found (``lost``): smaller steps would only bracket it again
        give_up = (~ok) & ((dt / 2 < path.dt_min * (1 - 1e-9)) | self._spent(path, s.iterations + it, wasted) | lost)
        return PathState(jnp.where(ok, t1, t), dt_next, jnp.where(ok, v, u), jnp.where(give_up, st, 0),
                         s.iterations + it, s.steps + ok, s.cuts + (~ok), jnp.where(ok, rn_v, s.residual_norm),
                         s.unknown | (st == Status.STABILITY_UNKNOWN), linear, branch, crit, wasted,
                         s.stats + work + res.stats)

    def _spent(self, path: Path, iterations, wasted):
        """Whether the failed attempts (``wasted`` of the ``iterations``) have spent their
        work budget."""
        budget = self.failed_work * jnp.maximum(iterations - wasted, path.nominal) + 2 * path.max_iter
        return wasted > budget

    def _stop(self, path: Path, s: PathState):
        """Why the path ended (a Stop code), read from its last state as ``step`` decided it:
        a failed step leaves the halved step in ``s.dt``."""
        smallest = s.dt < path.dt_min * (1 - 1e-9)
        cause = jnp.where(smallest, Stop.SMALLEST_STEP,
                          jnp.where(self._spent(path, s.iterations, s.wasted), Stop.WORK_BUDGET, Stop.NO_STABLE_STATE))
        return jnp.where(s.status > 0, cause, Stop.NONE).astype(jnp.int32)

    def _switched(self, problem, path: Path, s: PathState, t1, gb, lb, v, st, it, rn_v, ok):
        """The step's outcome after the branch switch (``switches``): where Newton ended on an
        unstable equilibrium at a step short enough to pin the critical point, the
        ``BranchSwitch`` goes on from it to a stable equilibrium of the same load, which the
        step then accepts (the critical point recorded). Returns (v, status, iterations, |r|,
        accepted, branch, critical, lost: no stable state was found)."""
        u, branch = s.u, s.branch
        switch = (st == Status.UNSTABLE_TANGENT) & (s.dt <= path.dt_locate * (1 + 1e-9))
        nan = jnp.full((Critical.n_eigenvalues,), jnp.nan, u.dtype)
        w, found, lam, mode, its = when(
            switch, lambda: self.branch.switch(problem, v, gb, lb, path.max_iter),
            (v, jnp.array(False), nan, jnp.zeros_like(u), jnp.array(0)))
        moved = switch & found
        critical = moved & (lam[0] < 0)
        crit = s.critical.record(branch, critical, s.t, t1, lam, mode)
        v = jnp.where(moved, w, v)
        # the residual of the state kept (the switch converged to the Newton tolerance)
        rn_v = jnp.where(moved, jnp.linalg.norm(problem.residual(v, gb, lb)), rn_v)
        return (v, jnp.where(moved, Status.CONVERGED, st), it + its, rn_v, ok | moved, branch + critical, crit,
                switch & ~found)

    def _parameter_predictor(self, problem_a, problem_b, u, g, load):
        """(u + du, K_ff's factorisation, LinearStats) with K_ff du = -(r + dr/dp (p_b - p_a))
        at u under problem_a (an equilibrium of it, or at a path's start near one): the
        linearised response to a step of the parameters (a frictional tool that moves drags
        the points that stick to it along), which Newton's first step, with the tangent at the
        new ones, does not see."""
        dp = jax.tree.map(lambda a, b: b - a if jnp.issubdtype(jnp.result_type(b), jnp.inexact)
                          else np.zeros(jnp.shape(b), jax.dtypes.float0), problem_a.params, problem_b.params)
        r, dr = jax.jvp(lambda p: problem_a.replace(params=p).residual(u, g, load), (problem_a.params,), (dp,))
        state = self.linear.state_at(problem_a, u, g, load)
        du = self.linear.solve(state, r + dr)
        return (jnp.where(jnp.all(jnp.isfinite(du)), u - du, u), state,
                self.linear.work(state) + LinearStats.of(solves=1))

    def solve(self, problem, lim: Limits, u0, g0, g1, l0, l1, state0=None, params0=None) -> Solution:
        """The equilibrium at (g1, l1) reached from (u0, g0, l0): a Solution (the last
        converged state and the failing status where the path stopped). ``state0``: the
        linear solver's state at the start; ``params0``: the problem's parameters at the
        start, ramped to its own along the path."""
        path = self.path(lim, g0, g1, l0, l1)._replace(p0=params0, state0=state0)
        return run(self, problem, path, u0)
