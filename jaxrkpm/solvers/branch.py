"""Past a critical point: the switch to a stable branch (``BranchSwitch``) and the energy
descent that reaches it (``StableDescent``, an ``IterativeSolver``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..base.checks import count, positive
from .iterate import IterativeSolver, run
from .linalg.dense import lowest_modes
from .newton import Tolerance
from .results import Critical, Status


class DescentState(NamedTuple):
    iteration: jax.Array  # () steps done
    u: jax.Array          # (Nf, d) the iterate (every accepted one has det F > 0)
    energy: jax.Array     # () Pi at u
    residual: jax.Array   # (Nf, d) r at u
    shift: jax.Array      # () tau of the last step
    min_shift: jax.Array  # () the smallest tau the next step may try (Levenberg-Marquardt damping)
    done: jax.Array       # () the descent is over
    status: jax.Array     # () its Status: CONVERGED (to a stable equilibrium), INVERTED (running
    #                       into det F = 0), NONFINITE (no shift factorised K_ff), MAX_ITERATIONS
    #                       (also while running)


class Fixed(NamedTuple):
    """The descent's constants: the prescribed values and load it minimises at."""

    g: jax.Array
    load: jax.Array
    max_iter: jax.Array


@dataclass(frozen=True)
class StableDescent(IterativeSolver):
    """Minimise the energy at a fixed load (g, load) by Newton steps on a shifted tangent.

    Each step solves (K_ff + tau I) p = -r with the smallest tau of the trial sequence 0,
    max(beta, tau_prev / 2), doubling, for which the Cholesky factorisation exists (Nocedal &
    Wright, Algorithm 3.3, "Cholesky with added multiple of the identity"; beta = ``shift_floor``
    x the largest diagonal entry, near round-off: the shift must come out comparable to the
    negative eigenvalue, which near a bifurcation is many orders below the diagonal, or the
    step along the critical mode, |lambda| / (lambda + tau) of its residual, would crawl; with
    doubling, tau < 2 |lambda| and the step along the mode at least doubles the amplitude).
    So p is always a descent direction, and the Armijo energy line search can only go
    downhill: it cannot end on a saddle (the unstable branch), which is why this and not
    Newton on the residual follows a critical point. Where K_ff is positive definite tau = 0
    and the step is Newton's (quadratic convergence at the end). Converged: |r| below the
    tolerance, with K_ff positive definite (tau = 0) at the last step and by a Cholesky
    factorisation at the state returned (every accepted state is stable). A step that finds
    no energy decrease in the line search is retried with a shift at least 4x larger (a
    shorter, more gradient-like step: Levenberg-Marquardt damping), which relaxes again by 4x
    after each good step.

    It fails at its iteration cap, or at once where an accepted iterate has det F below
    ``collapse_det`` at an integration point: the energy then falls toward det F = 0 (a
    material collapse). Past their last stable state the compressed Fung and Quadratic
    squares have no energy minimum with det F > 0 near the path: an exact trust-region
    minimisation from there (``jaxrkpm.internal.stable_beyond``) drives the smallest det F to
    ~1e-14 at a corner while |r| stays O(1) and the energy keeps falling (the energies of eqs
    5.1-5.2 stay bounded as det F -> 0, so nothing stops a corner from folding flat); without
    this stop a branch switch spent its whole iteration cap finding nothing."""

    tolerance: Tolerance = Tolerance()
    line_search: int = 8
    armijo: float = 1e-4
    shift_floor: float = 1e-10   # smallest tangent shift, relative to K_ff's largest diagonal entry
    collapse_det: float = 1e-3   # an iterate with det F below this is running into det F = 0

    def __post_init__(self):
        count("line_search", self.line_search)
        for name in ("armijo", "shift_floor", "collapse_det"):
            positive(name, getattr(self, name))

    def _evaluate(self, problem, fixed: Fixed, v):
        (Pi, detmin), r = jax.value_and_grad(lambda x: problem.energy(x, fixed.g, fixed.load), has_aux=True)(v)
        return Pi, detmin, r

    def _tol(self, problem, fixed: Fixed, v):
        scale, stiffness = problem.force_scales(v, fixed.g)
        return self.tolerance.of(scale, self.tolerance.floor(stiffness))

    def _shifted_cholesky(self, K, tau_prev, tau_min):
        n = K.shape[0]
        beta = self.shift_floor * jnp.max(jnp.abs(jnp.diagonal(K)))

        def trial(tau):
            L = jnp.linalg.cholesky(K + tau * jnp.eye(n, dtype=K.dtype))
            return L, jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diagonal(L) > 0)

        def body(c):
            k, tau, _, _ = c
            tau = jnp.where(k == 0, tau_min,
                            jnp.where(k == 1, jnp.maximum(jnp.maximum(beta, tau_prev / 2), 2 * tau_min), 2 * tau))
            L, ok = trial(tau)
            return k + 1, tau, L, ok

        init = (jnp.array(0), jnp.asarray(0.0, K.dtype), jnp.zeros_like(K), jnp.array(False))
        # 64 doublings of beta cover any finite spectrum
        _, tau, L, ok = jax.lax.while_loop(lambda c: (~c[3]) & (c[0] < 66), body, init)
        return L, tau, ok, beta

    def init(self, problem, fixed: Fixed, u) -> DescentState:
        Pi0, _, r0 = self._evaluate(problem, fixed, u)
        zero = jnp.asarray(0.0, u.dtype)
        return DescentState(jnp.array(0), u, Pi0, r0, zero, zero, jnp.array(False), jnp.array(Status.MAX_ITERATIONS))

    def terminate(self, s: DescentState):
        return s.done, s.status

    def postprocess(self, problem, fixed: Fixed, s: DescentState, status):
        """(u, converged to a stable equilibrium, energy, iterations): stable by a Cholesky
        factorisation of K_ff at the state returned."""
        L = jnp.linalg.cholesky(problem.tangent(s.u, fixed.g, fixed.load))
        stable = jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diagonal(L) > 0)
        return s.u, (status == Status.CONVERGED) & stable, s.energy, s.iteration

    def step(self, problem, fixed: Fixed, s: DescentState) -> DescentState:
        v, Pi, r = s.u, s.energy, s.residual
        K = problem.tangent(v, fixed.g, fixed.load)
        L, tau, chol_ok, beta = self._shifted_cholesky(K, s.shift, s.min_shift)
        p = -jax.scipy.linalg.cho_solve((L, True), r.reshape(-1)).reshape(r.shape)
        slope = jnp.sum(p * r)
        rn = jnp.linalg.norm(r)

        def ls_body(c2):
            k = c2[0]
            alpha = 0.5 ** k
            w = v + alpha * p
            Pi_w, det_w, r_w = self._evaluate(problem, fixed, w)
            # where K_ff is positive definite (tau = 0) a residual decrease also counts: near
            # the minimum the energy change drowns in round-off, and a convex neighbourhood
            # holds no saddle to converge to
            ok = jnp.isfinite(Pi_w) & jnp.all(jnp.isfinite(r_w)) & (det_w > 0) & \
                ((Pi_w <= Pi + self.armijo * alpha * slope) | ((tau == 0) & (jnp.linalg.norm(r_w) < rn)))
            return k + 1, ok, w, Pi_w, r_w, det_w

        _, ls_ok, w, Pi_w, r_w, det_w = jax.lax.while_loop(
            lambda c2: (~c2[1]) & (c2[0] <= self.line_search), ls_body,
            (jnp.array(0), jnp.array(False), v, Pi, r, jnp.asarray(1.0, v.dtype)))
        ok = chol_ok & ls_ok
        done = ok & (tau == 0) & (jnp.linalg.norm(r_w) <= self._tol(problem, fixed, w))
        collapsing = ok & ~done & (det_w < self.collapse_det)
        # no decrease along p: the next step is shorter, by a larger shift (Levenberg-Marquardt
        # damping) instead of giving up; after a good step the damping relaxes
        tau_min = s.min_shift
        tau_min = jnp.where(ls_ok, jnp.where(tau_min / 4 < beta, 0.0, tau_min / 4), jnp.maximum(4 * tau, beta))
        status = jnp.where(done, Status.CONVERGED,
                           jnp.where(~chol_ok, Status.NONFINITE,
                                     jnp.where(collapsing, Status.INVERTED, Status.MAX_ITERATIONS)))
        over = done | ~chol_ok | collapsing | (s.iteration + 1 >= fixed.max_iter)
        return DescentState(s.iteration + 1, jnp.where(ok, w, v), jnp.where(ok, Pi_w, Pi), jnp.where(ok, r_w, r),
                            tau, tau_min, over, status)

    def solve(self, problem, u, g, load, max_iter):
        """(u, converged to a stable equilibrium, energy, iterations)."""
        return run(self, problem, Fixed(g, load, max_iter), u)


@dataclass(frozen=True)
class BranchSwitch:
    """From an equilibrium whose K_ff is not positive definite to a stable equilibrium of the
    same load.

    The state is kicked along the critical mode (the eigenvector of the lowest eigenvalue; its
    largest entry ``amplitude`` particle spacings, then doubled while the energy falls, at
    most ``kick_doublings`` times: ``along_mode``) to either side; ``descent`` minimises the
    energy from the kick of lower energy (at a symmetric bifurcation the two sides are mirror
    images of equal energy: the + side is taken; at an asymmetric one, the side on which the
    energy falls further). A perturbation along the mode, not a shift alone, because at the
    unstable equilibrium r = 0: every shifted Newton step would be zero. Needs the dense
    tangent (its eigenpairs)."""

    descent: StableDescent = field(default_factory=StableDescent)
    amplitude: float = 0.05
    kick_doublings: int = 40

    def __post_init__(self):
        if not isinstance(self.descent, StableDescent):
            raise ValueError(f"descent must be a StableDescent, got {self.descent!r}")
        positive("amplitude", self.amplitude)
        count("kick_doublings", self.kick_doublings)

    def along_mode(self, problem, u, kick, g, load):
        """u + 2**k kick for the k (0 <= k <= kick_doublings) of least energy, found by
        doubling while the energy falls (and det F > 0). Near a bifurcation the energy is flat
        along the critical mode (Pi ~ lambda s^2 / 2 + c s^4 / 4 with a tiny lambda < 0): a
        shifted Newton step from a small kick crawls, while this 1D search lands within a
        factor 2 of the buckled amplitude sqrt(-lambda / c) in a few energy evaluations."""
        def Pi(v):
            e, det = problem.energy(v, g, load)
            return jnp.where(jnp.isfinite(e) & (det > 0), e, jnp.inf)

        def body(c):
            k, best, Pi_best, _ = c
            v = u + 2.0 ** k * kick
            Pi_v = Pi(v)
            lower = Pi_v < Pi_best
            return k + 1, jnp.where(lower, v, best), jnp.where(lower, Pi_v, Pi_best), lower

        _, best, _, _ = jax.lax.while_loop(lambda c: c[3] & (c[0] <= self.kick_doublings), body,
                                           (jnp.array(0), u, Pi(u), jnp.array(True)))
        return best

    def switch(self, problem, u, g, load, max_iter):
        """(u, found, lowest eigenvalues (Critical.n_eigenvalues,), critical mode (Nf, d) of
        unit norm, iterations) from the unstable equilibrium u at (g, load)."""
        k = Critical.n_eigenvalues
        lam, vecs = lowest_modes(problem.tangent(u, g, load), min(k, u.size))
        lam = jnp.concatenate([lam, jnp.full((k - lam.shape[0],), jnp.nan, lam.dtype)])
        mode = vecs[:, 0].reshape(u.shape)
        kick = self.amplitude * problem.spacing / jnp.max(jnp.abs(mode)) * mode

        plus = self.along_mode(problem, u, kick, g, load)
        minus = self.along_mode(problem, u, -kick, g, load)
        lower = problem.energy(minus, g, load)[0] < problem.energy(plus, g, load)[0]
        v, found, _, its = self.descent.solve(problem, jnp.where(lower, minus, plus), g, load, max_iter)
        return v, found, lam, mode, its
