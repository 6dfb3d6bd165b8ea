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
- **A jitted step called from Python**: each step attempt (predictor, corrector loop and
  the factorisation at the new point) is one compiled function; the loop over steps (and
  the cuts) is Python. A lax loop over all steps would compile the same step body, so it
  saves no compile time; it would need (steps, Nf, d) buffers preallocated for the longest
  path, and its points would reach the host only when the whole loop returns. Here every
  accepted point is copied to the host as it is accepted, so a failure (or Ctrl-C) loses
  none, the path stops at once on its target or a failure, and the one dispatch per step
  costs far less than the step's factorisations.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.outcome import Outcome
from .iterate import iterate
from .linalg.base import LinearSolver, Stability
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


_RUNNING = -1


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
    Solution the path started from."""

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
    psi2: jax.Array      # () the load term's weight in the constraint, psi^2 |q|^2
    r_ref: jax.Array     # () the out-of-balance load the step puts on
    max_iter: jax.Array  # () corrector iterations


class ArcState(NamedTuple):
    iteration: jax.Array      # () corrector iterations done
    du: jax.Array             # (Nf, d) the increment of the free coefficients
    dlam: jax.Array           # () the increment of the load factor
    status: jax.Array         # () _RUNNING, else a PathStatus code
    residual_norm: jax.Array  # () |r| at the last iterate
    linear: Any               # the factorisation of K_ff at the last iterate


@dataclass(frozen=True)
class ArcLength:
    """The arc-length corrector (see the module docstring): full Newton on (u, lambda) with
    Crisfield's constraint, the tangent factorised at every iterate by ``linear``, converged
    by ``tolerance``. A solver with init / step / terminate; ``step_from`` takes one step."""

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
        """The path's first point: (factorisation of K_ff, stability, negative eigenvalues, |r|)."""
        state = self.linear.state_at(problem, u, g, load)
        rn = jnp.linalg.norm(problem.residual(u, g, load))
        return state, self.linear.stability(state), self.linear.negative_eigenvalues(state), rn

    def init(self, problem, step: ArcStep, state0, du_prev, dlam_prev) -> tuple:
        """The predictor: the tangent u_t = K^-1 q scaled to the arc length, signed by the
        angle with the last increment (see the module docstring). Returns (the step's
        constants completed, the corrector's first state)."""
        _, q0, _ = self.residual_and_load(problem, step.u0, step.g0, step.dg, step.lam0, step.lam0)
        qq = jnp.sum(q0 * q0)
        psi2 = step.psi2 * qq     # the load term's weight in the constraint
        ut = self.linear.solve(state0, q0)
        angle = jnp.sum(ut * du_prev) + psi2 * dlam_prev
        sign = jnp.where(angle != 0, jnp.sign(angle), jnp.where(dlam_prev < 0, -1.0, 1.0))
        dlam = sign * step.ds / jnp.sqrt(jnp.sum(ut * ut) + psi2)
        du = dlam * ut
        step = step._replace(psi2=psi2, r_ref=jnp.abs(dlam) * jnp.sqrt(qq))
        return step, ArcState(jnp.array(0), du, dlam, jnp.array(_RUNNING), jnp.array(jnp.inf), state0)

    def terminate(self, s: ArcState):
        return s.status != _RUNNING

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
        d_r, d_t = x[..., 0], x[..., 1]
        w = du + d_r
        psi2, ds = step.psi2, step.ds
        a = jnp.sum(d_t * d_t) + psi2
        b = 2.0 * (jnp.sum(d_t * w) + psi2 * dlam)
        cc = jnp.sum(w * w) + psi2 * dlam * dlam - ds * ds
        disc = b * b - 4.0 * a * cc
        root = jnp.sqrt(jnp.maximum(disc, 0.0))
        dl1, dl2 = (-b + root) / (2.0 * a), (-b - root) / (2.0 * a)

        def angle(dl):   # with the current increment: the root that does not double back
            return jnp.sum((w + dl * d_t) * du) + psi2 * (dlam + dl) * dlam

        dl = jnp.where(angle(dl1) >= angle(dl2), dl1, dl2)
        status = jnp.where(~finite, PathStatus.NONFINITE,
                           jnp.where(detmin <= 0, PathStatus.INVERTED,
                                     jnp.where(converged, PathStatus.COMPLETED,
                                               jnp.where(disc < 0, PathStatus.NO_ROOT,
                                                         jnp.where(it + 1 >= step.max_iter, PathStatus.MAX_ITERATIONS,
                                                                   _RUNNING)))))
        keep = converged | (status != _RUNNING)
        return ArcState(it + 1, jnp.where(keep, du, w + dl * d_t), jnp.where(keep, dlam, dlam + dl), status, rn,
                        state)


@partial(jax.jit, static_argnames=("arc",))
def start_point(arc: ArcLength, problem, u, g, load):
    """``ArcLength.start``, compiled."""
    return arc.start(problem, u, g, load)


@partial(jax.jit, static_argnames=("arc",))
def arc_step(arc: ArcLength, problem, max_iter, u0, g0, dg, lam0, state0, du_prev, dlam_prev, ds, psi):
    """One arc-length step of length ``ds`` from the equilibrium (u0, g0, lam0), whose
    factorisation is ``state0``; (du_prev, dlam_prev) is the last accepted increment (zeros
    and the wanted sign of the first load increment on the first step).

    Returns (u, g, lam, status, iterations, |r|, state, stability, negative eigenvalues) at
    the new point; status 0 accepted, else the PathStatus of the failure (the caller cuts
    ``ds``)."""
    step = ArcStep(u0, g0, dg, lam0, ds, psi * psi, jnp.zeros((), u0.dtype), max_iter)
    step, s = arc.init(problem, step, state0, du_prev, dlam_prev)
    s = iterate(arc, problem, step, s)
    u, g, lam = u0 + s.du, g0 + s.dlam * dg, lam0 + s.dlam
    return (u, g, lam, s.status, s.iteration - 1, s.residual_norm, s.linear, arc.linear.stability(s.linear),
            arc.linear.negative_eigenvalues(s.linear))
