"""Frictional contact solved to its own fixed point: the lagged friction (each tool's normal
pressure, tangent planes and anchors, ``jaxrkpm.Contact``) iterated within a load step until
it agrees with the state it produces, for any number of tools at once.

A lagged solve bounds each point's friction by the pressure of the state it was handed, so a
point whose pressure falls in the step can leave the Coulomb cone. ``solve_frictional``
re-solves the step with every tool's pressure relaxed towards the one it reached and its
normals updated, the anchors held at the step's start (each point's slip in the step is
measured from there), until each point's pressure changes by less than ``tol`` of its own
(normals by ``tol`` radians): at that fixed point the friction is bounded by the step's own
pressure in its own tangent plane. A first step (no lag given) is solved frictionless and
anchored at its own end, as the thesis ``Stepper`` does.

Derivatives: a solve with the settled lag given as parameters is differentiable in the poses
with the pressures and normals held at their settled values (the anchors are parameters too,
so a path's derivative can carry them from step to step).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..base.outcome import Outcome
from ..mechanics.contact import ContactTerm, contact_forces
from ..solvers.results import Status

RELAXATION = 0.5
PRESSURE_FLOOR = 1e-6    # pressures below this share of a tool's largest (held or reached) are not told apart


class LagStatus(Outcome):
    """Outcome of a frictional solve (``solve_frictional``)."""

    SETTLED = 0, "the friction lag settled: every point's pressure and normal within tol of the state reached"
    NOT_SETTLED = 1, "max_lag re-solves did not settle the lag; the last converged state is kept"
    SOLVE_FAILED = 2, "a solve failed (see solve_status)"


@dataclass
class FrictionalSolve:
    """A load step with its friction lag settled (or not: ``status``).

    solution      the Solution (the last converged one)
    lag           tool name -> {"pressure", "anchor", "normal"}: the solution's own state,
                  the lag of the next step (pass it as ``lag``)
    held          the lag this solution was solved with (its derivatives hold it; None: a
                  frictionless first step)
    results       tool name -> ContactResult at ``solution``
    status        LagStatus; ``solve_status`` the failed solve's Status (CONVERGED otherwise)
    iterations    re-solves with the lag updated
    change        the largest relative pressure change of the last update"""

    solution: object
    lag: dict
    held: dict | None
    results: dict
    status: LagStatus
    iterations: int
    change: float
    solve_status: Status = Status.CONVERGED

    @property
    def ok(self) -> bool:
        return self.status == LagStatus.SETTLED


def contact_names(model, params=None) -> tuple:
    """The names of the model's contact tools (``jaxrkpm.Contact`` terms)."""
    return tuple(t.name for t in model.problem(params).terms if isinstance(t, ContactTerm))


def _lag_change(held, now, tol):
    """The largest relative pressure change and whether the normals moved by more than tol."""
    p = np.asarray(now["pressure"])
    floor = PRESSURE_FLOOR * max(float(np.max(p, initial=0.0)), float(np.max(held["pressure"], initial=0.0)), 1e-300)
    dp = np.max(np.abs(p - held["pressure"]) / np.maximum(p, floor), initial=0.0)
    dn = np.max(np.abs(np.asarray(now["normal"]) - held["normal"]), initial=0.0)
    return float(dp), bool(dn <= tol)


def solve_frictional(model, prescribed=None, *, params=None, initial=None, lag=None, steps: int = 1,
                     tol: float = 1e-6, max_lag: int = 60, relaxation: float = RELAXATION,
                     max_iter: int = 50) -> FrictionalSolve:
    """``model.solve(prescribed, params=..., initial=..., steps=...)`` with every contact tool's
    friction lag iterated to its fixed point (see the module docstring).

    ``params``: the solve's parameters (the tools' poses, ``mu``); ``lag``: tool name ->
    the previous step's ``FrictionalSolve.lag`` (None: a first step, anchored at its own
    frictionless end). ``tol``: on each point's lagged pressure (relative) and normal.
    Frictionless tools (mu = 0) need no iteration. Never raises on a failed solve: see
    ``status``."""
    if not (isinstance(tol, (int, float)) and tol > 0):
        raise ValueError(f"tol must be a positive number, got {tol!r}")
    if not (isinstance(max_lag, (int, np.integer)) and max_lag >= 0):
        raise ValueError(f"max_lag must be a whole number >= 0, got {max_lag!r}")
    if not 0 < relaxation <= 1:
        raise ValueError(f"relaxation must be in (0, 1], got {relaxation!r}")
    params = dict(params or {})
    names = contact_names(model, params)
    if not names:
        raise ValueError("the model has no contact tool (jaxrkpm.Contact in its terms)")
    if lag is not None and set(lag) != set(names):
        raise ValueError(f"lag must name every tool {list(names)}, got {list(lag)}")
    problem = model.problem(params)
    frictional = any(float(problem.term(n).mu) > 0 for n in names)

    def with_lag(held):
        if held is None:
            return params
        return {**params, **{n: {**params.get(n, {}), **held[n]} for n in names}}

    def own(res):
        return {n: {k_: np.asarray(v) for k_, v in res[n].lag.items()} for n in names}

    def results(sol, held):
        p = with_lag(held)
        return {n: contact_forces(model, sol, n, p) for n in names}

    sol = model.solve(prescribed, params=with_lag(lag), initial=initial, steps=steps, max_iter=max_iter, throw=False)
    if int(sol.status) != Status.CONVERGED:
        return FrictionalSolve(sol, lag, lag, {}, LagStatus.SOLVE_FAILED, 0, np.inf, Status.of(sol.status))
    held = None if lag is None else {n: {k: np.asarray(v) for k, v in lag[n].items()} for n in names}
    res = results(sol, held)
    anchor = {n: np.asarray((res[n].lag if lag is None else lag[n])["anchor"]) for n in names}
    if not frictional:
        return FrictionalSolve(sol, own(res), held, res, LagStatus.SETTLED, 0, 0.0)
    change, k = np.inf, 0
    while True:
        now = own(res)
        if held is not None:
            moves = [_lag_change(held[n], now[n], tol) for n in names]
            change = max(m[0] for m in moves)
            if change <= tol and all(m[1] for m in moves):
                return FrictionalSolve(sol, own(res), held, res, LagStatus.SETTLED, k, change)
        if k >= max_lag:
            return FrictionalSolve(sol, own(res), held, res, LagStatus.NOT_SETTLED, k, change)
        # the pressure half-way to the one reached (the plain update swings between points that
        # share the load), a point that left the tool at once (it carries no friction)
        new = {}
        for n in names:
            p = now[n]["pressure"] if held is None else np.where(
                now[n]["pressure"] > 0,
                held[n]["pressure"] + relaxation * (now[n]["pressure"] - held[n]["pressure"]), 0.0)
            new[n] = {"pressure": p, "normal": now[n]["normal"], "anchor": anchor[n]}
        # a lag update is a fixed point at one pose, not a path: no ramp of the lagged quantities
        again = model.solve(prescribed, params=with_lag(new), initial=sol._replace(params=None), max_iter=max_iter,
                            throw=False)
        k += 1
        if int(again.status) != Status.CONVERGED:
            return FrictionalSolve(sol, own(res), held, res, LagStatus.SOLVE_FAILED, k, change, Status.of(again.status))
        sol, held = again, new
        res = results(sol, held)

