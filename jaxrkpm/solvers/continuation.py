"""Arc-length (Riks / Crisfield) continuation: equilibrium paths through limit points.

Load control (``model.solve``) cannot pass a limit point: past the largest load the
structure carries, no equilibrium exists at a higher load, so the solve fails or jumps
(snap-through). Arc-length continuation makes the load factor lambda an unknown and adds
one constraint per step, Crisfield's

    |Delta u|^2 + psi^2 Delta lambda^2 |q|^2 = Delta s^2

(``psi=0``: the cylindrical constraint, the default; ``psi=1``: the spherical Riks
constraint), so the path is followed by its length and turns at limit points like any other
point. ``q = -dr/dlambda`` is the load the path parameter drives: the model's dead loads
(tractions, body force; or a ``load_pattern``, e.g. ``point_load``) scaled by lambda, plus,
optionally, a prescribed displacement direction ``g = g0 + lambda dg``.

Every accepted point records the load factor, the state, |r|, the step's arc length, and
the stability of K_ff there: Stability (positive definite or not) and the number of
negative eigenvalues (the sparse factorisation's inertia; for the dense solver 0 where the
Cholesky factorisation succeeds, else counted from the eigenvalues of K_ff).

Design choices (and why):

- **Predictor direction: the previous increment**, not the sign of det K_ff. The tangent
  direction u_t = K_ff^-1 q is followed with the sign that makes a positive angle with the
  last accepted increment (Delta u, Delta lambda). The determinant's sign also flips at
  bifurcation points, where the path does not turn back, and the sparse factorisation cannot
  always tell the inertia (UNKNOWN); the angle criterion needs nothing from the
  factorisation and turns exactly where the path turns. The first step goes in the
  direction of ``direction`` (+1: increasing load).
- **Corrector**: full Newton (a new factorisation of K_ff at every iterate), with
  Crisfield's quadratic for the load-factor correction; of its two roots the one whose
  increment makes the smaller angle with the current one is taken (no doubling back).
  Complex roots (NO_ROOT), NaN (NONFINITE), det F <= 0 (INVERTED) or the iteration cap cut
  the arc length in half and retry from the last accepted point.
- **Adaptive arc length**: after a step that took I corrector iterations,
  Delta s <- Delta s sqrt(target / I), clipped to [1/2, 2] times the last and to ``ds_max``.
- **Two solvers, one contract**: the corrector (``ArcLength``) runs inside jit, one compiled
  function per step attempt (``arc_step``: predictor, corrector loop and the factorisation
  at the new point); the path (``ArcLengthPath``) runs on the host, through the same
  ``iterate`` with a Python loop, one step attempt (accepted, or the arc length cut) per
  iteration. A lax loop over all steps would compile the same step body, so it saves no
  compile time; it would need (steps, Nf, d) buffers preallocated for the longest path, and
  its points would reach the host only when the whole loop returns. Here every accepted
  point is copied to the host as it is accepted, so a failure (or Ctrl-C) loses none, the
  path stops at once on its target or a failure, and the one dispatch per step costs far
  less than the step's factorisations.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.outcome import Outcome
from .iterate import IterativeSolver, python_loop, run
from .linalg.base import LinearSolver, LinearStats, Stability
from .linalg.dense import DenseSolver
from .newton import Tolerance
from .results import Solution, Status


class PathStatus(Outcome):
    """How an arc-length path ended (``path.outcome``); every accepted point is kept."""

    COMPLETED = 0, "the path reached its end: the target load factor, or all the steps asked for"
    MAX_ITERATIONS = 1, ("the corrector reached its iteration cap even on the smallest arc length "
                         "allowed (max_cuts halvings)")
    NONFINITE = 2, "non-finite residual (NaN/inf) even on the smallest arc length allowed"
    INVERTED = 3, ("a corrector step would invert the material (det F <= 0 at an integration "
                   "point) even on the smallest arc length allowed")
    NO_ROOT = 4, ("the arc-length constraint had no real load-factor correction (complex roots of "
                  "Crisfield's quadratic) even on the smallest arc length allowed")
    INTERRUPTED = 5, "interrupted (KeyboardInterrupt); the points accepted until then are kept"


@dataclass(frozen=True)
class EquilibriumPath:
    """An equilibrium path from ``arc_length`` (NumPy arrays, one row per accepted point;
    row 0 is the start).

    load (n,) load factor lambda; u (n, Nf, d) free RK coefficients; g (n, Nb, d) prescribed
    values; displacement (n, P, d) at the ``points`` asked for (None if none); residual_norm
    (n,) |r|; stability (n,) jaxrkpm.solvers.linalg.base.Stability codes of K_ff; negative (n,) its number
    of negative eigenvalues (-1 where the factorisation could not tell); arc (n,) the arc
    length of the step that reached each point (0 at the start); iterations (n,) corrector
    iterations; cuts: arc-length halvings in all; status: a PathStatus code; start: the
    Solution the path started from; stats: the linear algebra of the whole path
    (``LinearStats``, every attempt)."""

    load: np.ndarray
    u: np.ndarray
    g: np.ndarray
    displacement: np.ndarray | None
    residual_norm: np.ndarray
    stability: np.ndarray
    negative: np.ndarray
    arc: np.ndarray
    iterations: np.ndarray
    cuts: int
    status: PathStatus
    start: Solution
    stats: LinearStats | None = None

    def __len__(self) -> int:
        return len(self.load)

    @property
    def outcome(self) -> PathStatus:
        return PathStatus.of(self.status)

    @property
    def completed(self) -> bool:
        return self.outcome == PathStatus.COMPLETED

    @property
    def limit_points(self) -> np.ndarray:
        """Indices of the points where the load factor has a local maximum or minimum along
        the path (the increment of lambda changes sign after them): the sampled limit points."""
        dl = np.diff(self.load)
        return np.flatnonzero(dl[:-1] * dl[1:] < 0) + 1

    def limit_loads(self) -> np.ndarray:
        """The load factor at each of ``limit_points``, located between the samples: the
        vertex of the parabola through the three points around it, in the path's arc length
        (the sampled extremum misses the true one by O(Delta s^2))."""
        s = np.cumsum(self.arc)
        out = []
        for k in self.limit_points:
            c2, c1, c0 = np.polyfit(s[k - 1:k + 2] - s[k], self.load[k - 1:k + 2], 2)
            out.append(c0 - c1 * c1 / (4 * c2))
        return np.asarray(out)

    @property
    def critical_points(self) -> np.ndarray:
        """Indices of the first point after each change of the number of negative
        eigenvalues of K_ff (a limit or bifurcation point lies between it and the one before)."""
        return np.flatnonzero(np.diff(self.negative) != 0) + 1

    @property
    def message(self) -> str:
        s = self.outcome
        where = (f"{len(self) - 1} steps, load factor {self.load[0]:.4g} -> {self.load[-1]:.4g} "
                 f"(largest {self.load.max():.4g}), {len(self.limit_points)} limit point(s), "
                 f"{self.cuts} step cuts")
        if s == PathStatus.COMPLETED:
            return f"completed: {where}"
        return f"{s.name}: {s.message}; stopped after {where}; every accepted point is kept"

    def solution(self, k: int) -> Solution:
        """Point ``k`` as a Solution (for ``model.displacement``, ``reaction``, ``stress``,
        output). Its status is CONVERGED (or STABILITY_UNKNOWN) whatever the stability: that
        is in ``stability[k]``, as with ``model.solve(..., check_stability=False)``."""
        n = len(self)
        if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)):
            raise TypeError(f"a path point is a whole index, got {k!r} ({type(k).__name__}); "
                            f"the path has points 0..{n - 1}")
        if not -n <= k < n:
            raise IndexError(f"point {k} of a path of {n} points")
        status = Status.STABILITY_UNKNOWN if self.stability[k] == Stability.UNKNOWN else Status.CONVERGED
        i32, f64 = partial(jnp.asarray, dtype=jnp.int32), partial(jnp.asarray, dtype=jnp.float64)
        return self.start._replace(u=f64(self.u[k]), g=f64(self.g[k]), load=f64(self.load[k]),
                                   status=i32(int(status)), t=f64(1.0), iterations=i32(int(self.iterations[k])),
                                   steps=i32(k), cuts=i32(self.cuts), residual_norm=f64(self.residual_norm[k]))


# ----------------------------------------------------------------------- inside jit
class ArcStep(NamedTuple):
    """One step's constants: from the equilibrium (u0, g0, lam0) by the arc length ``ds``."""

    u0: jax.Array        # (Nf, d)
    g0: jax.Array        # (Nb, d)
    dg: jax.Array        # (Nb, d) prescribed-value direction per unit lambda
    lam0: jax.Array      # ()
    ds: jax.Array        # () the arc length
    psi2: jax.Array      # () the load term's weight in the constraint (``predict``: psi^2 |q|^2)
    r_ref: jax.Array     # () the out-of-balance load the step puts on (``predict``)
    max_iter: jax.Array  # () corrector iterations
    linear0: Any         # the factorisation of K_ff at (u0, g0, lam0)


class ArcState(NamedTuple):
    iteration: jax.Array      # () corrector iterations done
    du: jax.Array             # (Nf, d) the increment of the free coefficients
    dlam: jax.Array           # () the increment of the load factor
    done: jax.Array           # () the corrector is over
    status: jax.Array         # () its PathStatus (COMPLETED: converged; MAX_ITERATIONS while running)
    residual_norm: jax.Array  # () |r| at the last iterate
    linear: Any               # the factorisation of K_ff at the last iterate
    stats: LinearStats        # the linear work so far


class ArcPoint(NamedTuple):
    """A step attempt's outcome (``arc_step``): the new point, or the failure."""

    u: jax.Array              # (Nf, d)
    g: jax.Array              # (Nb, d)
    load: jax.Array           # () lambda
    status: jax.Array         # () PathStatus: COMPLETED (accepted), else why the attempt failed
    iterations: jax.Array     # () corrector iterations
    residual_norm: jax.Array  # () |r|
    linear: Any               # the factorisation of K_ff there
    stability: jax.Array      # () its Stability code
    negative: jax.Array       # () its negative eigenvalues (-1: unknown)
    stats: LinearStats        # the attempt's linear work


@dataclass(frozen=True)
class ArcLength(IterativeSolver):
    """The arc-length corrector (see the module docstring): full Newton on (u, lambda) with
    Crisfield's constraint, the tangent factorised at every iterate by ``linear``, converged
    by ``tolerance``. Its start is the predictor's increment (``predict``); ``arc_step`` takes
    one step."""

    linear: LinearSolver = DenseSolver()
    tolerance: Tolerance = Tolerance()

    def residual_and_load(self, problem, u, g0, dg, lam0, lam):
        """r(u, lambda) (Nf, d), q = -dr/dlambda (the load the path parameter drives) and the
        smallest det F, at g = g0 + (lambda - lambda0) dg and load scale lambda."""
        def r_of(l):
            (_, detmin), r = jax.value_and_grad(
                lambda v: problem.energy(v, g0 + (l - lam0) * dg, l), has_aux=True)(u)
            return r, detmin

        (r, detmin), (dr, _) = jax.jvp(r_of, (lam,), (jnp.ones_like(lam),))
        return r, -dr, detmin

    def start(self, problem, u, g, load):
        """The path's first point: (factorisation of K_ff, stability, negative eigenvalues, |r|,
        LinearStats)."""
        state = self.linear.state_at(problem, u, g, load)
        rn = jnp.linalg.norm(problem.residual(u, g, load))
        return (state, self.linear.stability(state), self.linear.negative_eigenvalues(state), rn,
                self.linear.work(state))

    def predict(self, problem, step: ArcStep, du_prev, dlam_prev) -> tuple:
        """The predictor: the tangent u_t = K^-1 q scaled to the arc length, signed by the
        angle with the last increment (see the module docstring). Returns (the step's
        constants completed, the corrector's start (du, dlam))."""
        _, q0, _ = self.residual_and_load(problem, step.u0, step.g0, step.dg, step.lam0, step.lam0)
        qq = jnp.sum(q0 * q0)
        psi2 = step.psi2 * qq     # the load term's weight in the constraint
        ut = self.linear.solve(step.linear0, q0)
        angle = jnp.sum(ut * du_prev) + psi2 * dlam_prev
        sign = jnp.where(angle != 0, jnp.sign(angle), jnp.where(dlam_prev < 0, -1.0, 1.0))
        dlam = sign * step.ds / jnp.sqrt(jnp.sum(ut * ut) + psi2)
        return step._replace(psi2=psi2, r_ref=jnp.abs(dlam) * jnp.sqrt(qq)), (dlam * ut, dlam)

    def init(self, problem, step: ArcStep, start) -> ArcState:
        """From the predicted increment ``start`` = (du, dlam) (the predictor's solve counted)."""
        du, dlam = start
        return ArcState(jnp.array(0), du, dlam, jnp.array(False), jnp.array(PathStatus.MAX_ITERATIONS),
                        jnp.array(jnp.inf), step.linear0, LinearStats.of(solves=1))

    def terminate(self, s: ArcState):
        return s.done, s.status

    def step(self, problem, step: ArcStep, s: ArcState) -> ArcState:
        du, dlam, it = s.du, s.dlam, s.iteration
        u, g, lam = step.u0 + du, step.g0 + dlam * step.dg, step.lam0 + dlam
        r, q, detmin = self.residual_and_load(problem, u, step.g0, step.dg, step.lam0, lam)
        rn = jnp.linalg.norm(r)
        finite = jnp.all(jnp.isfinite(r)) & jnp.all(jnp.isfinite(q))
        scale, stiffness = problem.force_scales(u, g)
        converged = rn <= self.tolerance.of(scale, self.tolerance.floor(stiffness), step.r_ref)
        state = self.linear.state_at(problem, u, g, lam)
        # K [dr, dt] = [-r, q]: the residual correction and the tangent at this iterate
        x = self.linear.solve(state, jnp.stack([-r, q], axis=-1))
        w, d_t = du + x[..., 0], x[..., 1]
        dl, disc = self._load_correction(step, s, w, d_t)
        failed = ~finite | (detmin <= 0)
        status = jnp.where(~finite, PathStatus.NONFINITE,
                           jnp.where(detmin <= 0, PathStatus.INVERTED,
                                     jnp.where(converged, PathStatus.COMPLETED,
                                               jnp.where(disc < 0, PathStatus.NO_ROOT, PathStatus.MAX_ITERATIONS))))
        done = failed | converged | (disc < 0) | (it + 1 >= step.max_iter)
        return ArcState(it + 1, jnp.where(done, du, w + dl * d_t), jnp.where(done, dlam, dlam + dl), done, status,
                        rn, state, s.stats + self.linear.work(state) + LinearStats.of(solves=1))

    def _load_correction(self, step: ArcStep, s: ArcState, w, d_t):
        """Crisfield's quadratic for the load-factor correction dl of the iterate w + dl d_t:
        (dl, its discriminant); of the two roots, the one whose increment makes the smaller
        angle with the current one (no doubling back)."""
        psi2, ds, du, dlam = step.psi2, step.ds, s.du, s.dlam
        a = jnp.sum(d_t * d_t) + psi2
        b = 2.0 * (jnp.sum(d_t * w) + psi2 * dlam)
        cc = jnp.sum(w * w) + psi2 * dlam * dlam - ds * ds
        disc = b * b - 4.0 * a * cc
        root = jnp.sqrt(jnp.maximum(disc, 0.0))
        dl1, dl2 = (-b + root) / (2.0 * a), (-b - root) / (2.0 * a)

        def angle(dl):   # with the current increment
            return jnp.sum((w + dl * d_t) * du) + psi2 * (dlam + dl) * dlam

        return jnp.where(angle(dl1) >= angle(dl2), dl1, dl2), disc

    def postprocess(self, problem, step: ArcStep, s: ArcState, status) -> ArcPoint:
        u, g, lam = step.u0 + s.du, step.g0 + s.dlam * step.dg, step.lam0 + s.dlam
        return ArcPoint(u, g, lam, status, s.iteration - 1, s.residual_norm, s.linear,
                        self.linear.stability(s.linear), self.linear.negative_eigenvalues(s.linear), s.stats)


@partial(jax.jit, static_argnames=("arc",))
def start_point(arc: ArcLength, problem, u, g, load):
    """``ArcLength.start``, compiled."""
    return arc.start(problem, u, g, load)


@partial(jax.jit, static_argnames=("arc",))
def arc_step(arc: ArcLength, problem, max_iter, u0, g0, dg, lam0, state0, du_prev, dlam_prev, ds, psi) -> ArcPoint:
    """One arc-length step of length ``ds`` from the equilibrium (u0, g0, lam0), whose
    factorisation is ``state0``; (du_prev, dlam_prev) is the last accepted increment (zeros
    and the wanted sign of the first load increment on the first step). Returns the
    ``ArcPoint`` (status COMPLETED: accepted, else the PathStatus of the failure: the caller
    cuts ``ds``)."""
    step = ArcStep(u0, g0, dg, lam0, ds, psi * psi, jnp.zeros((), u0.dtype), max_iter, state0)
    step, start = arc.predict(problem, step, du_prev, dlam_prev)
    return run(arc, problem, step, start)


# ----------------------------------------------------------------------- on the host
class ArcPath(NamedTuple):
    """The path's constants (``ArcLengthPath``; host values, but ``dg``, ``psi``, ``max_iter``
    as the arrays ``arc_step`` takes)."""

    dg: jax.Array             # (Nb, d) prescribed-value direction per unit lambda
    psi: jax.Array            # () the constraint's load weight
    max_iter: jax.Array       # () corrector iterations per attempt
    direction: int            # +1: the load factor increases first; -1: it decreases
    ds: float                 # the first arc length
    ds_max: float             # the largest
    steps: int                # accepted steps at most
    max_cuts: int             # halvings of the arc length in a row before the path stops
    target_iterations: int    # corrector iterations a step should take (the arc length adapts)
    load_max: float | None    # the path stops once lambda reaches it
    probes: Any = None        # (idx, psi) of the points whose displacement is recorded, or None


class ArcPathState(NamedTuple):
    """The path between step attempts (host values; the last point's arrays as returned)."""

    u: Any                 # (Nf, d) the last accepted point
    g: Any                 # (Nb, d)
    lam: Any               # ()
    linear: Any            # the factorisation of K_ff there
    du_prev: Any           # (Nf, d) the last accepted increment
    dlam_prev: Any         # ()
    ds: float              # the next attempt's arc length
    tries: int             # cuts in a row at this step
    cuts: int              # cuts in all
    rows: tuple            # the accepted points' host records (``ArcLengthPath.row``)
    done: bool
    status: PathStatus     # COMPLETED while running
    stats: LinearStats     # the linear work of every attempt
    origin: Solution       # the Solution the path started from


@dataclass(frozen=True)
class ArcLengthPath(IterativeSolver):
    """The equilibrium path by arc-length steps (see the module docstring), on the host: each
    ``step`` is one attempt by the compiled ``attempt`` (``arc_step``), accepted, or cut in
    half and retried (``max_cuts`` times in a row, then the path stops with the attempt's
    status); the arc length then adapts to about ``target_iterations`` corrector iterations
    a step, never above ``ds_max``. ``first`` (``start_point``) factorises the start. An
    interrupt (KeyboardInterrupt) during an attempt ends the path with INTERRUPTED, every
    accepted point kept. ``run`` through ``iterate`` with a Python loop (``solve``)."""

    corrector: ArcLength = ArcLength()
    attempt: Callable = arc_step
    first: Callable = start_point

    @staticmethod
    def row(u, g, lam, rn, stab, neg, ds, its) -> tuple:
        """A point's host record: (u, g, lambda, |r|, stability, negative eigenvalues, the arc
        length that reached it, corrector iterations)."""
        return np.asarray(u), np.asarray(g), float(lam), float(rn), int(stab), int(neg), float(ds), int(its)

    def init(self, problem, args: ArcPath, start: Solution) -> ArcPathState:
        f64 = partial(jnp.asarray, dtype=jnp.float64)
        u, g, lam = f64(start.u), f64(start.g), f64(start.load)
        state, stab, neg, rn0, work = self.first(self.corrector, problem, u, g, lam)
        return ArcPathState(u, g, lam, state, jnp.zeros_like(u), f64(args.direction), float(args.ds), 0, 0,
                            (self.row(u, g, lam, rn0, stab, neg, 0.0, 0),), False, PathStatus.COMPLETED, work,
                            start)

    def terminate(self, s: ArcPathState):
        return s.done, s.status

    def step(self, problem, args: ArcPath, s: ArcPathState) -> ArcPathState:
        try:
            out = self.attempt(self.corrector, problem, args.max_iter, s.u, s.g, args.dg, s.lam, s.linear,
                               s.du_prev, s.dlam_prev, jnp.asarray(s.ds, jnp.float64), args.psi)
            code = PathStatus.of(int(out.status))
        except KeyboardInterrupt:
            return s._replace(done=True, status=PathStatus.INTERRUPTED)
        s = s._replace(stats=s.stats + out.stats)
        if code == PathStatus.COMPLETED:
            return self._accepted(args, s, out)
        if s.tries == args.max_cuts:
            return s._replace(done=True, status=code)
        return s._replace(tries=s.tries + 1, cuts=s.cuts + 1, ds=s.ds / 2)

    def _accepted(self, args: ArcPath, s: ArcPathState, out: ArcPoint) -> ArcPathState:
        """The path after the accepted attempt ``out``, and the next arc length."""
        its = int(out.iterations)
        rows = s.rows + (self.row(out.u, out.g, out.load, out.residual_norm, out.stability, out.negative, s.ds,
                                  its),)
        ds = min(s.ds * min(2.0, max(0.5, math.sqrt(args.target_iterations / max(its, 1)))), args.ds_max)
        done = len(rows) > args.steps or (args.load_max is not None and float(out.load) >= args.load_max)
        return s._replace(u=out.u, g=out.g, lam=out.load, linear=out.linear, du_prev=out.u - s.u,
                          dlam_prev=out.load - s.lam, ds=ds, tries=0, rows=rows, done=done)

    def postprocess(self, problem, args: ArcPath, s: ArcPathState, status) -> EquilibriumPath:
        """The EquilibriumPath of the accepted points (the probes' displacements at each)."""
        U, G, L, R, ST, NEG, A, IT = (np.asarray(c) for c in zip(*s.rows))
        disp = None
        if args.probes is not None:
            idx, psi_p = args.probes
            # one point at a time: a compiled function of the path's length would recompile per length
            disp = np.stack([np.asarray(_point_values(problem, idx, psi_p, u_k, g_k)) for u_k, g_k in zip(U, G)])
        stats = LinearStats(*(np.asarray(v) for v in s.stats))
        return EquilibriumPath(L, U, G, disp, R, ST, NEG, A, IT, s.cuts, PathStatus.of(status), s.origin, stats)

    def solve(self, problem, args: ArcPath, start: Solution) -> EquilibriumPath:
        """The path from the equilibrium ``start``: ``run`` on the host (a Python loop)."""
        return run(self, problem, args, start, loop=python_loop)


_point_values = jax.jit(lambda problem, idx, psi, u, g: problem.point_values(idx, psi, u, g))
