"""Adaptive load stepping from one equilibrium to another (the driver of every solve).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from ..mechanics.assembly import Ops, Params, residual
from .branch import switch_branch, switches_branch
from .config import Config
from .loops import when
from .newton import newton
from .results import CRITICAL_EIGS, Critical, Limits, Solution, Status


FAILED_WORK = 2    # Newton iterations of failed attempts allowed per iteration of useful work (solve_path)


def solve_path(ops: Ops, params: Params, cfg: Config, lim: Limits, u0, g0, g1, l0, l1, state0=None) -> Solution:
    """Adaptive load stepping from the equilibrium (u0, g0, l0) to (g1, l1).

    Halves the step on failure (up to lim.max_cuts times below the initial step), grows it
    by ``cfg.growth`` after easy steps (never above the initial step). On failure the last
    converged state is returned with the failing status. The linear solver's state runs
    through every step (a sparse factorisation keeps preconditioning later steps).
    ``state0``: a factorisation of K_ff at the start (u0, g0, l0), e.g. the one an implicit
    Jacobian at that equilibrium made: the first step starts from it where the solver keeps
    states (modified Newton's predictor, ``Config.reuse``; the sparse path's preconditioner),
    so the same matrix is not factorised twice; full Newton ignores it.

    Past a critical point (``switches_branch(cfg)``): a step whose equilibrium has a K_ff that
    is not positive definite is cut (as any failure) until it is at most dt0 / 2**cfg.locate
    long, which pins the critical point between the last stable state and that step's end;
    then ``switch_branch`` goes on from that unstable equilibrium to a stable equilibrium of
    the same load, and the step is accepted there; if none is found the solve stops there
    with UNSTABLE_TANGENT (the last stable state kept). (A step whose Newton fails is cut as
    before: measured on the Fung squares, a descent from where Newton stalled did not reach a
    stable state within max_iter, and it costs several times a Newton attempt.) Where K_ff had a negative eigenvalue there, the critical point is recorded in
    ``Solution.critical`` and counted in ``Solution.branch``.

    Failure in bounded time: the Newton iterations spent in failed attempts (cut steps and
    failed switches) may not exceed FAILED_WORK x max(iterations of the accepted steps,
    steps x cfg.easy) + 2 x max_iter; the solve gives up (with the failing attempt's status)
    once they would. So a solve that cannot proceed costs at most (1 + FAILED_WORK) x the
    larger of the work it did and a converging solve's nominal work (steps x easy), plus two
    attempts, whatever lim.max_cuts allows. Without the budget, a solve stuck at a limit point
    spends up to max_cuts attempts of max_iter iterations each, and more where successes and
    failures alternate (tens of times a converging solve's work)."""
    dt0 = 1.0 / lim.steps
    dt_min = dt0 * 0.5 ** lim.max_cuts
    dt_locate = jnp.maximum(dt0 * 0.5 ** cfg.locate, dt_min)
    branching = switches_branch(cfg)
    nominal = lim.steps * max(int(cfg.easy), 1)

    def at(t):
        # exactly g0 before the first converged step (a NaN in g1 must not leak into the
        # kept state: 0 * NaN is NaN) and exactly g1 at the end
        def lerp(a, b):
            return jnp.where(t >= 1.0, b, jnp.where(t > 0.0, a + t * (b - a), a))
        return lerp(g0, g1), lerp(l0, l1)

    def cond(c):
        t, dt, u, status, *_ = c
        return (t < 1.0) & (status <= 0)

    def body(c):
        t, dt, u, status, iters, steps, cuts, rn, unknown, state, branch, crit, wasted = c
        t1 = jnp.minimum(t + dt, 1.0)
        t1 = jnp.where(1.0 - t1 < 1e-12, 1.0, t1)
        ga, la = at(t)
        gb, lb = at(t1)
        v, st, it, rn_v, state = newton(ops, params, cfg, lim.max_iter, u, ga, gb, la, lb, state)
        ok = (st == Status.CONVERGED) | (st == Status.STABILITY_UNKNOWN)
        if branching:
            switch = (st == Status.UNSTABLE_TANGENT) & (dt <= dt_locate * (1 + 1e-9))
            nan = jnp.full((CRITICAL_EIGS,), jnp.nan, u.dtype)
            w, found, lam, mode, its = when(
                switch, lambda: switch_branch(ops, params, cfg, lim.max_iter, v, gb, lb),
                (v, jnp.array(False), nan, jnp.zeros_like(u), jnp.array(0)))
            moved = switch & found
            lost = switch & ~found
            critical = moved & (lam[0] < 0)
            crit = crit.record(branch, critical, t, t1, lam, mode)
            branch = branch + critical
            v = jnp.where(moved, w, v)
            it = it + its
            ok = ok | moved
            st = jnp.where(moved, Status.CONVERGED, st)
            # the residual of the state kept (the switch converged to the Newton tolerance)
            rn_v = jnp.where(moved, jnp.linalg.norm(residual(ops, params, cfg.W, v, gb, lb)), rn_v)
        grow = jnp.where(it <= cfg.easy, cfg.growth, 1.0)
        dt_next = jnp.where(ok, jnp.minimum(dt * grow, dt0), dt / 2)
        wasted = wasted + jnp.where(ok, 0, it)
        budget = FAILED_WORK * jnp.maximum(iters + it - wasted, nominal) + 2 * lim.max_iter
        give_up = (~ok) & ((dt / 2 < dt_min * (1 - 1e-9)) | (wasted > budget))
        if branching:
            # the critical point is bracketed and no stable state of that load was found:
            # smaller steps would only bracket it again
            give_up = give_up | lost
        return (jnp.where(ok, t1, t), dt_next, jnp.where(ok, v, u),
                jnp.where(give_up, st, 0), iters + it, steps + ok, cuts + (~ok), jnp.where(ok, rn_v, rn),
                unknown | (st == Status.STABILITY_UNKNOWN), state, branch, crit, wasted)

    zero = jnp.array(0)
    init = (jnp.array(0.0), jnp.array(dt0), u0, zero, zero, zero, zero, jnp.array(0.0), jnp.array(False),
            cfg.linear.empty(ops, u0.dtype) if state0 is None else state0, zero, Critical.empty(u0), zero)
    t, _, u, status, iters, steps, cuts, rn, unknown, _, branch, crit, _ = jax.lax.while_loop(cond, body, init)
    status = jnp.where((status == 0) & unknown, Status.STABILITY_UNKNOWN, status)
    g, load = at(t)
    return Solution(u, g, load, status, t, iters, steps, cuts, rn, branch, crit)
