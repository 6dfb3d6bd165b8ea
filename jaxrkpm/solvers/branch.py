"""Past a critical point: the switch to a stable branch and the energy descent that reaches it.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from ..mechanics.assembly import coefficients, dense_tangent, energy, force_scales, pair_blocks
from .config import Config
from .linalg.dense import DenseSolver, lowest_modes
from .results import CRITICAL_EIGS


# ------------------------------------------------------------------ the stable branch
SWITCH_AMPLITUDE = 0.05   # the kick along the critical mode: its largest entry, in particle spacings

SHIFT_FLOOR = 1e-10       # smallest tangent shift, relative to the largest diagonal entry of K_ff

COLLAPSE_DET = 1e-3       # a descent whose iterate has det F below this at an integration point is


def switches_branch(cfg: Config) -> bool:
    """Whether solves with ``cfg`` go on past a critical point (static): the stable-branch
    option needs the stability check and the dense tangent (its eigenpairs); the sparse path
    stops with UNSTABLE_TANGENT as before."""
    return bool(cfg.stable_branch and cfg.check_stability and isinstance(cfg.linear, DenseSolver))


def descend(ops, params, cfg: Config, max_iter, u, g, load):
    """Minimise the energy at the fixed load (g, load) from u by Newton steps on a shifted
    tangent: returns (u, converged to a stable equilibrium, energy, iterations).

    Each step solves (K_ff + tau I) p = -r with the smallest tau of the trial sequence 0,
    max(beta, tau_prev / 2), doubling, for which the Cholesky factorisation exists (Nocedal &
    Wright, Algorithm 3.3, "Cholesky with added multiple of the identity"; beta = SHIFT_FLOOR x
    the largest diagonal entry, near round-off: the shift must come out comparable to the
    negative eigenvalue, which near a bifurcation is many orders below the diagonal, or the
    step along the critical mode, |lambda| / (lambda + tau) of its residual, would crawl; with
    doubling, tau < 2 |lambda| and the step along the mode at least doubles the amplitude).
    So p is always a descent direction, and the Armijo energy line
    search can only go downhill: it cannot end on a saddle (the unstable branch), which is why
    this and not Newton on the residual follows a critical point. Where K_ff is positive
    definite tau = 0 and the step is Newton's (quadratic convergence at the end). Converged:
    |r| below the Newton tolerance, with K_ff positive definite (tau = 0) at the last step and
    by a Cholesky factorisation at the state returned (every accepted state is stable). A step
    that finds no energy decrease in the line search is retried with a shift at least 4x larger
    (a shorter, more gradient-like step: Levenberg-Marquardt damping), which relaxes again by 4x
    after each good step.

    It fails at its iteration cap (``max_iter``), or at once where an accepted iterate has
    det F < COLLAPSE_DET at an integration point: the energy then falls toward det F = 0 (a
    material collapse). Measured on the compressed Fung and Quadratic squares (issue 19), past
    their last stable state the energy has no minimum with det F > 0 near the path: an exact
    trust-region minimisation from there (``jaxrkpm.solvers.minimise.stable_beyond``) drives the
    smallest det F to ~1e-14 at a corner while |r| stays O(1) and the energy keeps falling
    (the energies of eqs 5.1-5.2 stay bounded as det F -> 0, so nothing stops a corner from
    folding flat). Without this stop the switch spent its iteration cap finding nothing
    (9x9 Fung square, 60% compression: 82 Newton iterations against 63 with it)."""
    W = cfg.W
    n = u.size

    def evaluate(v):
        (Pi, detmin), r = jax.value_and_grad(lambda x: energy(ops, params, W, x, g, load), has_aux=True)(v)
        return Pi, detmin, r

    def tol(v):
        scale, floor = force_scales(ops, params, W, coefficients(ops, v, g))
        return jnp.maximum(cfg.rtol * scale, floor)

    def shifted_cholesky(K, tau_prev, tau_min):
        beta = SHIFT_FLOOR * jnp.max(jnp.abs(jnp.diagonal(K)))

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

    def cond(c):
        return c[6] < 0

    def body(c):
        it, v, Pi, r, tau_prev, tau_min, _ = c
        K = dense_tangent(ops, pair_blocks(ops, params, W, coefficients(ops, v, g)))
        L, tau, chol_ok, beta = shifted_cholesky(K, tau_prev, tau_min)
        p = -jax.scipy.linalg.cho_solve((L, True), r.reshape(-1)).reshape(r.shape)
        slope = jnp.sum(p * r)
        rn = jnp.linalg.norm(r)

        def ls_body(c2):
            k = c2[0]
            alpha = 0.5 ** k
            w = v + alpha * p
            Pi_w, det_w, r_w = evaluate(w)
            # where K_ff is positive definite (tau = 0) a residual decrease also counts: near
            # the minimum the energy change drowns in round-off, and a convex neighbourhood
            # holds no saddle to converge to
            ok = jnp.isfinite(Pi_w) & jnp.all(jnp.isfinite(r_w)) & (det_w > 0) & \
                ((Pi_w <= Pi + cfg.armijo * alpha * slope) | ((tau == 0) & (jnp.linalg.norm(r_w) < rn)))
            return k + 1, ok, w, Pi_w, r_w, det_w

        _, ls_ok, w, Pi_w, r_w, det_w = jax.lax.while_loop(
            lambda c2: (~c2[1]) & (c2[0] <= cfg.line_search), ls_body,
            (jnp.array(0), jnp.array(False), v, Pi, r, jnp.asarray(1.0, u.dtype)))
        ok = chol_ok & ls_ok
        done = ok & (tau == 0) & (jnp.linalg.norm(r_w) <= tol(w))
        collapsing = ok & ~done & (det_w < COLLAPSE_DET)
        # no decrease along p: the next step is shorter, by a larger shift (Levenberg-Marquardt
        # damping) instead of giving up; after a good step the damping relaxes
        tau_min = jnp.where(ls_ok, jnp.where(tau_min / 4 < beta, 0.0, tau_min / 4), jnp.maximum(4 * tau, beta))
        status = jnp.where(done, 1, jnp.where(~chol_ok | collapsing | (it + 1 >= max_iter), 0, -1))
        return (it + 1, jnp.where(ok, w, v), jnp.where(ok, Pi_w, Pi), jnp.where(ok, r_w, r), tau, tau_min, status)

    Pi0, _, r0 = evaluate(u)
    zero = jnp.asarray(0.0, u.dtype)
    it, v, Pi, _, _, _, status = jax.lax.while_loop(cond, body, (jnp.array(0), u, Pi0, r0, zero, zero, jnp.array(-1)))
    K = dense_tangent(ops, pair_blocks(ops, params, W, coefficients(ops, v, g)))
    L = jnp.linalg.cholesky(K)
    stable = jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diagonal(L) > 0)
    return v, (status == 1) & stable, Pi, it


KICK_DOUBLINGS = 40       # the kick along the critical mode grows by doubling at most this often


def along_mode(ops, params, W, u, kick, g, load):
    """u + 2**k kick for the k (0 <= k <= KICK_DOUBLINGS) of least energy, found by doubling
    while the energy falls (and det F > 0). Near a bifurcation the energy is flat along the
    critical mode (Pi ~ lambda s^2 / 2 + c s^4 / 4 with a tiny lambda < 0): a shifted Newton
    step from a small kick crawls, while this 1D search lands within a factor 2 of the
    buckled amplitude sqrt(-lambda / c) in a few energy evaluations."""
    def Pi(v):
        e, det = energy(ops, params, W, v, g, load)
        return jnp.where(jnp.isfinite(e) & (det > 0), e, jnp.inf)

    def body(c):
        k, best, Pi_best, _ = c
        v = u + 2.0 ** k * kick
        Pi_v = Pi(v)
        lower = Pi_v < Pi_best
        return k + 1, jnp.where(lower, v, best), jnp.where(lower, Pi_v, Pi_best), lower

    _, best, _, _ = jax.lax.while_loop(lambda c: c[3] & (c[0] <= KICK_DOUBLINGS), body,
                                       (jnp.array(0), u, Pi(u), jnp.array(True)))
    return best


def switch_branch(ops, params, cfg: Config, max_iter, u, g, load):
    """From the equilibrium u at (g, load) whose K_ff is not positive definite, to a stable
    equilibrium of the same load: returns (u, found, lowest eigenvalues (CRITICAL_EIGS,),
    critical mode (Nf, d) of unit norm, iterations).

    The state is kicked along the critical mode (the eigenvector of the lowest eigenvalue; its
    largest entry SWITCH_AMPLITUDE particle spacings, then doubled while the energy falls:
    ``along_mode``) to either side; ``descend`` minimises the energy from the kick of lower
    energy (at a symmetric bifurcation the two sides are mirror images of equal energy: the +
    side is taken; at an asymmetric one, the side on which the energy falls further). A
    perturbation along the mode, not a shift alone, because at the unstable equilibrium r = 0:
    every shifted Newton step would be zero."""
    lam, vecs = lowest_modes(dense_tangent(ops, pair_blocks(ops, params, cfg.W, coefficients(ops, u, g))),
                             min(CRITICAL_EIGS, u.size))
    lam = jnp.concatenate([lam, jnp.full((CRITICAL_EIGS - lam.shape[0],), jnp.nan, lam.dtype)])
    mode = vecs[:, 0].reshape(u.shape)
    kick = SWITCH_AMPLITUDE * ops.spacing / jnp.max(jnp.abs(mode)) * mode

    plus = along_mode(ops, params, cfg.W, u, kick, g, load)
    minus = along_mode(ops, params, cfg.W, u, -kick, g, load)
    lower = energy(ops, params, cfg.W, minus, g, load)[0] < energy(ops, params, cfg.W, plus, g, load)[0]
    v, found, _, its = descend(ops, params, cfg, max_iter, jnp.where(lower, minus, plus), g, load)
    return v, found, lam, mode, its
