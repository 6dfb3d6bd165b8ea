"""Newton's method on the free RK coefficients (full, modified, chord and quasi-Newton chord).
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from ..mechanics.assembly import (coefficients, energy_residual_stress, force_scales, pair_blocks, residual,
                                  stress_force_scale, zero_stress)
from .config import Config
from .linalg.base import Stability
from .loops import when
from .results import Status


def tangent(ops, params, cfg: Config, u, g):
    """The tangent as the linear solver takes it: dense K_ff, or (P, d, d) pair blocks."""
    return cfg.linear.matrix(ops, pair_blocks(ops, params, cfg.W, coefficients(ops, u, g)))


def linear_state(ops, params, cfg: Config, u, g):
    """The linear solver's factorisation of K_ff at (u, g) (see jaxrkpm.solvers.linalg)."""
    return cfg.linear.init(ops, pair_blocks(ops, params, cfg.W, coefficients(ops, u, g)))


# ---------------------------------------------------------------------------- Newton
# relative residual of an iterative solver's predictor solve: the predictor is a linearised
# step, off by O(increment^2) whatever its solve's accuracy
PREDICTOR_RTOL = 1e-4


def newton(ops, params, cfg: Config, max_iter, u, g0, g1, l0, l1, state, chord: bool = False, floor=None):
    """Newton from the equilibrium at (g0, l0) to (g1, l1); returns (u, status, iterations,
    |r|, linear state).

    The first linear solve is the predictor: it carries the prescribed increment,
    K_ff(u, g0) du = -(r(u, g0, l1) + K_fg (g1 - g0)); later ones are Newton steps at g1.
    ``g0`` None: u is an iterate at g1 (e.g. a state predicted by the caller) and the first
    solve a Newton step there (a residual pass instead of the predictor's linearisation).
    Converged when |r| <= max(rtol max(|r + K_fg dg|, internal force scale), round-off
    floor) (the force scale at the iterate after the last step that assembled the tangent,
    or after the predictor: chord steps reuse it; the floor there, after the predictor, unless
    ``floor`` gives it: e.g. one that the caller computed at a nearby state and keeps, as the
    control loop does, since the floor's own pass through the material cost as much as a
    chord correction). The force scale comes from the stress that each residual evaluation
    computes (``energy_residual_stress``): no pass of its own.

    ``chord=False``: every iteration assembles the tangent and solves through
    ``cfg.linear.newton_solve`` (which may reuse ``state``, e.g. as a preconditioner), then a
    backtracking line search (energy decrease or residual decrease).
    ``chord=True``: every solve uses the factorisation ``state`` as it is (no assembly: the
    chord, or modified Newton, iteration of a kept tangent; a solver with an ``update``, such
    as ``linear.QuasiNewton``, adds each correction's secant pair to the state it returns:
    quasi-Newton corrections); no line search, each correction
    must lower |r|; a ``state`` that is not stable gives UNSTABLE_TANGENT at once. With
    ``cfg.reuse`` > 0 a correction must cut |r| by at least that factor, else the chord
    stops at once with MAX_ITERATIONS (it contracts too slowly: the caller refactorises).
    ``cfg.reuse`` > 0 (with ``chord=False``): an iteration solves with the kept, stable
    ``state`` (no assembly) where the previous step cut |r| by at least ``cfg.reuse`` (the
    predictor: where ``state``, the previous load step's last, is stable), else assembles and
    factorises; the line search stays. Once |r| is small enough that one Newton step meets
    the tolerance, the tangent there is factorised (once per load step, where the chord has
    not already made one) and serves the rest of the step. Convergence is declared only
    after a tangent of this load step was factorised (its stability is the one reported)."""
    W = cfg.W
    res = partial(residual, ops, params, W)
    if g0 is None:   # no increment: the residual at (u, g1), not a linearisation along g1 - g0 = 0
        g0, rhs0 = g1, res(u, g1, l1)
    else:
        r_pred, kfg_dg = jax.jvp(lambda g: res(u, g, l1), (g0,), (g1 - g0,))
        rhs0 = r_pred + kfg_dg
    r_ref = jnp.linalg.norm(rhs0)
    halvings = 0 if chord else cfg.line_search

    def evaluate(v):
        return energy_residual_stress(ops, params, W, v, g1, l1)

    def line_search(u, Pi, r, du, first):
        slope = jnp.sum(du * r)
        rn = jnp.linalg.norm(r)
        start_ok = jnp.isfinite(Pi) & jnp.all(jnp.isfinite(r))

        def cond(c):
            return (~c[1]) & (c[0] <= halvings)

        def body(c):
            k, _, _, _, _, _, any_finite, _ = c
            alpha = 0.5 ** k
            v = u + alpha * du
            Pi_v, det_v, r_v, wP_v = evaluate(v)
            finite = jnp.isfinite(Pi_v) & jnp.all(jnp.isfinite(r_v))
            valid = finite & (det_v > 0)
            lower_r = jnp.linalg.norm(r_v) < rn
            if chord:   # the predictor need only be admissible; corrections must lower |r|
                decrease = first | lower_r
            else:
                decrease = (Pi_v <= Pi + cfg.armijo * alpha * slope) | lower_r | ~start_ok
            return (k + 1, valid & decrease, v, Pi_v, r_v, wP_v, any_finite | finite, det_v > 0)

        init = (jnp.array(0), jnp.array(False), u, Pi, r, wP0, jnp.array(False), jnp.array(True))
        # no halvings (chord): the one trial step, without a loop around it
        search = body if halvings == 0 else partial(jax.lax.while_loop, cond, body)
        _, accepted, v, Pi_v, r_v, wP_v, any_finite, det_ok = search(init)
        why = jnp.where(~any_finite, Status.NONFINITE,
                        jnp.where(~det_ok, Status.INVERTED, Status.LINE_SEARCH))
        return accepted, v, Pi_v, r_v, wP_v, why

    def cond(c):
        return c[4] < 0

    # dense only: the sparse solver's newton_solve already reuses its factorisation (as a CG
    # preconditioner), and its kept state may factorise an older tangent than the last step's
    reusing = (not chord) and cfg.reuse > 0 and cfg.linear.name == "dense"

    def body(c):
        it, u, Pi, r, _, state, keep, scales, step_factorised = c
        first = it == 0
        rhs = jnp.where(first, rhs0, r)
        made = True
        if chord:
            dx, stab = cfg.linear.solve(state, rhs), cfg.linear.stability(state)
            made = False
        elif reusing:
            dx, state, stab, made = jax.lax.cond(
                keep, lambda: (cfg.linear.solve(state, rhs), state, cfg.linear.stability(state), False),
                lambda: (*assemble_and_solve(u, first, rhs, state), True))
        else:
            dx, state, stab = assemble_and_solve(u, first, rhs, state)
        ok, v, Pi_v, r_v, wP_v, why = line_search(u, Pi, r, -dx, first)
        if chord and hasattr(cfg.linear, "update"):
            # a quasi-Newton solver learns from each correction (the predictor's step also
            # changes the load: not a secant pair of one residual)
            state = cfg.linear.update(state, v - u, r_v - r, ok & ~first)
        rn = jnp.linalg.norm(r_v)
        # the force scale of the tolerance: at the iterate after each assembled step, kept
        # through the chord steps that follow it (they move the state by less than the step
        # before them, so the scale by a relative O(|du|));
        # the round-off floor once a call after the predictor, where not given
        scale = when(first | made, lambda: stress_force_scale(ops, wP_v), scales[0])
        if floor is None:
            floor_now = when(first, lambda: force_scales(ops, params, W, coefficients(ops, v, g1))[1], scales[1])
        else:
            floor_now = jnp.asarray(floor, u.dtype)
        tol = jnp.maximum(cfg.rtol * jnp.maximum(r_ref, scale), floor_now)
        converged = ok & (rn <= tol)
        cap = max_iter
        if chord and cfg.reuse > 0:
            # a kept factorisation that no longer contracts fast is not worth more corrections
            slow = ~first & ~converged & (rn > cfg.reuse * jnp.linalg.norm(r))
            cap = jnp.where(slow, it + 1, max_iter)
        if reusing:
            # the equilibrium is declared only once a tangent of this step (at g1: not the
            # predictor's) has been factorised, so the stability reported is, as in full
            # Newton, that of an iterate of this step's Newton sequence (measured: with one
            # of the previous step only, a solve passed a critical point); a chord step that
            # meets the tolerance before that is followed by one. That factorisation is made
            # where it does most: once |r| is low enough that a Newton step from there meets
            # the tolerance (quadratic convergence, |r|^2 <= tol r_ref), so the chord steps
            # after it contract at once (10^3 cube, 30% in 10 steps: 76 -> 40 iterations, the
            # same 10 factorisations, 5.37 -> 4.08 s, quiet machine, runs minutes apart)
            step_factorised = step_factorised | (made & ~first)
            met = converged
            converged = converged & (step_factorised | (not cfg.check_stability))
            # (without the stability check no factorisation is owed: chords while they contract)
            owed = cfg.check_stability & ~step_factorised & (rn * rn <= tol * r_ref)
            keep = ok & ~met & (rn <= cfg.reuse * jnp.linalg.norm(r)) & \
                (cfg.linear.stability(state) == Stability.STABLE) & ~owed
        # stability from the last factorised tangent (at the iterate before the converged one)
        if cfg.check_stability:
            done = jnp.where(stab == Stability.STABLE, Status.CONVERGED,
                             jnp.where(stab == Stability.UNSTABLE, Status.UNSTABLE_TANGENT,
                                       Status.STABILITY_UNKNOWN))
        else:
            done = Status.CONVERGED
        status = jnp.where(~ok, why, jnp.where(converged, done,
                                               jnp.where(it + 1 >= cap, Status.MAX_ITERATIONS, -1)))
        # a linear solve that did not converge (krylov) gives an untrusted step: unless the
        # residual met the tolerance anyway, the attempt ends
        status = jnp.where((stab == Stability.FAILED) & ~converged, Status.LINEAR_SOLVE, status)
        return (it + 1, jnp.where(ok, v, u), jnp.where(ok, Pi_v, Pi), jnp.where(ok, r_v, r), status, state, keep,
                (scale, floor_now), step_factorised)

    def assemble_and_solve(u, first, rhs, state):
        """A Newton step with the tangent at u (at g0 for the predictor): (dx, state, stability)."""
        blocks = pair_blocks(ops, params, W, coefficients(ops, u, jnp.where(first, g0, g1)))
        # inexact Newton (iterative linear solvers): far from equilibrium the linear solve
        # need only be as accurate as the step is good (a forcing term proportional to the
        # residual keeps the convergence quadratic), near it solves are tight. With the
        # stability check only the predictor's solve may stop early: an iterative solver
        # finds negative curvature only in a rich Krylov space (measured: with loose early
        # corrections a buckling column's CG path, SuperLU-preconditioned, passed the
        # critical point and reported the state beyond it, lowest eigenvalue -2.5e-5, as
        # stable), and the predictor's tangent is the previous equilibrium's, which that
        # equilibrium's own tight solves checked (measured only together with the sparse
        # path's refactorisation when CG slows: 20^3 cube, 412 -> 213 CG iterations)
        forcing = None
        if not cfg.check_stability:
            rel = jnp.linalg.norm(rhs) / jnp.maximum(r_ref, 1e-300)
            forcing = jnp.where(rel > 1e-4, jnp.minimum(1e-2 * rel, 1e-4), 1e-11)
        elif cfg.linear.tight_rtol is not None:
            forcing = jnp.where(first, PREDICTOR_RTOL, cfg.linear.tight_rtol)
        return cfg.linear.newton_solve(state, ops, blocks, rhs, forcing)

    if chord:
        # the chord's first solve is the predictor (right-hand side rhs0, accepted whenever
        # admissible): the energy and residual at (u, g1) would go unused, so they are not
        # evaluated (one energy-gradient pass per settle saved)
        Pi0, r0 = jnp.array(jnp.inf, u.dtype), rhs0
        wP0 = zero_stress(ops, u)
    else:
        Pi0, _, r0, wP0 = evaluate(u)
    status0 = jnp.array(-1)
    if chord:
        status0 = jnp.where(cfg.linear.stability(state) == Stability.STABLE, -1, Status.UNSTABLE_TANGENT)
    keep0 = jnp.asarray(reusing) & (cfg.linear.stability(state) == Stability.STABLE)
    it, u_new, _, r, status, state, _, _, _ = jax.lax.while_loop(
        cond, body, (jnp.array(0), u, Pi0, r0, status0, state, keep0, (jnp.zeros((), u.dtype),) * 2,
                     jnp.array(False)))
    return u_new, status, it, jnp.linalg.norm(r), state
