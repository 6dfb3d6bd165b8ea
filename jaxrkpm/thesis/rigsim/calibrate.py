"""Model calibration from rig data, and the online (Broyden) Jacobian correction.

Calibration (beyond the thesis, which tuned beta = 0.02 by hand).

A :class:`Recording` holds what the rig can measure: commanded paddle displacements, the
camera's control point displacements and the robot's force readings. :func:`calibrate`
fits the controller model's material parameters (Fung alpha, beta) to it by gradient
descent (optax) through the differentiable solve: each data point is an equilibrium
solve, and jax.grad goes through it by implicit differentiation (no Newton iteration is
differentiated). Parameters are fitted in log space (they must stay positive; a factor
of 2 is then the same distance up or down).

Why both kinds of data: under prescribed displacements a uniform scaling of W leaves the
displacements unchanged, so markers alone fix only the ratio of the stiffnesses; the
force fixes their level.
"""
from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ...base.progress import progress_bar
from ...model.model import Model
from ...solvers.results import Status

__all__ = ["Recording", "CalibrationResult", "predict", "calibrate", "region_index", "broyden_update"]


@dataclasses.dataclass(frozen=True)
class Recording:
    """Rig data, model units except forces: paddle (N, d) commanded paddle displacement,
    cp (N, d) measured control point displacement, force (N, d) force of the object on
    the paddle (newtons = model force x ``force_scale_n``), control_point (1, d)."""

    paddle: np.ndarray
    cp: np.ndarray
    force: np.ndarray
    control_point: np.ndarray
    force_scale_n: float = 1.0

    def __post_init__(self):
        p, c, f = (np.atleast_2d(np.asarray(a, float)) for a in (self.paddle, self.cp, self.force))
        if not (p.shape == c.shape == f.shape):
            raise ValueError(f"paddle, cp and force must have the same (N, d) shape; got "
                             f"{p.shape}, {c.shape}, {f.shape}")
        for name, a in (("paddle", p), ("cp", c), ("force", f)):
            if not np.all(np.isfinite(a)):
                raise ValueError(f"Recording.{name} has non-finite entries")
        object.__setattr__(self, "paddle", p)
        object.__setattr__(self, "cp", c)
        object.__setattr__(self, "force", f)
        object.__setattr__(self, "control_point", np.atleast_2d(np.asarray(self.control_point, float)))

    def __len__(self):
        return len(self.paddle)


@dataclasses.dataclass(frozen=True)
class CalibrationResult:
    """Fitted parameters (scalars, or (Q,) fields with a stiffness map), the start, the loss
    per optimiser step, the data misfit (RMS control point error in model units, RMS
    relative force error) before and after, and the fitted map (regions) or None."""

    params: dict
    initial: dict
    loss: np.ndarray
    cp_rms: tuple
    force_rel_rms: tuple
    converged_solves: bool
    stiffness_map: np.ndarray | None = None


def _predictor(model: Model, rec: Recording, steps: int):
    """(params dict) -> (cp (N, d), force (N, d) in newtons, worst solve status), traced."""
    sf = model.shape_functions(rec.control_point, gradients=False)
    idx, psi = jnp.asarray(sf.idx), jnp.asarray(sf.psi)
    G = model.directions("paddle")
    paddle = jnp.asarray(rec.paddle)
    base = model.initial()

    def one(params, mp):
        g = jnp.einsum("a,abi->bi", mp, G)
        s = model.solve_g(g, params=params, steps=steps, initial=base, throw=False)
        cp = model.constraint.point_values(idx, psi, s.u, s.g).ravel()
        f = -model.reaction(s, "paddle", params=params) * rec.force_scale_n
        return cp, f, s.status

    def predict_all(params):
        cp, f, st = jax.lax.map(partial(one, params), paddle)
        return cp, f, jnp.max(st)

    return predict_all


def predict(model: Model, rec: Recording, params: dict, steps: int = 2):
    """Model control point (N, d) and force (N, d) at the recording's paddle positions, and
    the worst solve :class:`~jaxrkpm.solvers.results.Status` among them."""
    cp, f, st = jax.jit(_predictor(model, rec, steps))({k: jnp.asarray(v, jnp.float64) for k, v in params.items()})
    return np.asarray(cp), np.asarray(f), Status(int(st))


def region_index(points, regions) -> np.ndarray:
    """Cell of a (rx, ry, ...) grid over the unit square/cube holding each point: (Q,) ints."""
    P = np.atleast_2d(np.asarray(points, float))
    r = np.asarray(regions, int)
    if r.shape != (P.shape[1],) or np.any(r < 1):
        raise ValueError(f"regions must be {P.shape[1]} positive counts, got {regions}")
    cell = np.clip(np.floor(P * r).astype(int), 0, r - 1)
    return np.ravel_multi_index(tuple(cell.T), tuple(r))


def calibrate(model: Model, rec: Recording, initial: dict, *, fit=("alpha", "beta"),
              regions=None, region_reg: float = 1.0, steps: int = 40, gtol: float = 1e-6,
              max_halvings: int = 30, cp_sigma: float = 5e-4, force_rel_sigma: float = 0.01,
              solve_steps: int = 2, progress: bool = True) -> CalibrationResult:
    """Fit the material parameters named in ``fit`` (starting at ``initial``, which also
    holds any fixed ones) to the recording by L-BFGS (optax) on log-parameters: at most ``steps`` iterations,
    stopping when the gradient norm falls below ``gtol`` or no step lowers the loss.

    Loss = mean((cp_model - cp)^2) / cp_sigma^2 + mean((f_model - f)^2) / (force_rel_sigma
    * rms(f))^2: each residual in units of its expected noise (camera: ``cp_sigma`` model
    units; force sensor: a fraction of the force level).

    ``regions`` (e.g. (3, 3)): also fit a stiffness multiplier exp(m_r) per cell of that grid
    over the unit square, applied to alpha and beta alike (the fitted parameters become
    (Q,) fields). A uniform alpha, beta barely changes the kinematics (the control point
    moves almost the same whatever the level of the stiffness), so only a stiffness *map*
    can absorb an unmodelled inclusion; ``region_reg`` * mean(m_r^2) keeps the map
    near uniform where the data say nothing. ``progress``: a bar of the iterations on a
    terminal."""
    fit = _checked_fit(rec, initial, fit, steps)
    fixed = {k: jnp.asarray(float(v)) for k, v in initial.items() if k not in fit}
    predict_all = _predictor(model, rec, solve_steps)
    cp_data, f_data = jnp.asarray(rec.cp), jnp.asarray(rec.force)
    f_sigma = force_rel_sigma * float(np.sqrt(np.mean(rec.force ** 2)) or 1.0)
    cell = None if regions is None else jnp.asarray(region_index(model.volume.points, regions))

    def params_of(theta):
        p = {**fixed, **{k: jnp.exp(v) for k, v in theta.items() if k != "_map"}}
        if regions is not None:   # the map multiplies every material parameter alike
            m = jnp.exp(theta["_map"])[cell]
            p = {k: v * m for k, v in p.items()}
        return p

    def loss_fn(theta):
        cp, f, status = predict_all(params_of(theta))
        value = jnp.mean((cp - cp_data) ** 2) / cp_sigma ** 2 + jnp.mean((f - f_data) ** 2) / f_sigma ** 2
        if regions is not None:
            value = value + region_reg * jnp.mean(theta["_map"] ** 2)
        return value, (cp, f, status)

    value_and_grad = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))
    theta = {k: jnp.log(jnp.asarray(float(initial[k]))) for k in fit}
    if regions is not None:
        theta["_map"] = jnp.zeros(int(np.prod(regions)))
    bar = progress_bar(int(steps), desc="calibrate", unit="iteration", progress=progress)
    theta, first, aux, losses = _descend(value_and_grad, theta, steps, gtol, max_halvings, bar)
    bar.close()
    final = {k: (float(v) if jnp.ndim(v) == 0 else np.asarray(v)) for k, v in params_of(theta).items()}
    stiffness_map = None if regions is None else np.exp(np.asarray(theta["_map"])).reshape(tuple(regions))
    misfit = [_misfit(rec, first), _misfit(rec, aux)]
    ok = int(first[2]) == Status.CONVERGED and int(aux[2]) == Status.CONVERGED
    return CalibrationResult(final, {k: float(v) for k, v in initial.items()}, np.asarray(losses),
                             (misfit[0][0], misfit[1][0]), (misfit[0][1], misfit[1][1]), bool(ok),
                             stiffness_map)


def _checked_fit(rec: Recording, initial: dict, fit, steps) -> tuple:
    """The names to fit, each with a positive initial value (so are the fixed ones)."""
    if len(rec) < 1:
        raise ValueError("the recording is empty")
    fit = tuple(fit)
    for k in fit:
        if k not in initial:
            raise ValueError(f"parameter {k!r} to fit has no initial value in {sorted(initial)}")
    for k, v in initial.items():
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"initial {k} must be positive (log-parameters), got {v}")
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    return fit


def _descend(value_and_grad, theta: dict, steps: int, gtol: float, max_halvings: int, bar):
    """Minimise by L-BFGS directions (optax) with a monotone backtracking step; returns the
    last parameters, the first and last (cp, force, status) and the loss per step (``bar``:
    advanced once per iteration).

    Why: the force misfit is a long curved valley in (log alpha, log beta) (both stiffen the
    same small-strain response), where plain gradient steps crawl. The line search is done
    here, with the one compiled value-and-grad, rather than inside optax's jitted zoom line
    search, which would trace (and compile) the N equilibrium solves several times over."""
    opt = optax.chain(optax.scale_by_lbfgs(), optax.scale(-1.0))
    state = opt.init(theta)
    update = jax.jit(opt.update)   # run eagerly, optax's L-BFGS is hundreds of tiny dispatches
    (value, aux), grad = value_and_grad(theta)
    first = aux
    losses = [float(value)]
    for _ in range(int(steps)):
        if float(optax.tree_utils.tree_norm(grad)) < gtol:
            break
        direction, new_state = update(grad, state, theta)
        step = _backtrack(value_and_grad, theta, direction, value, max_halvings)
        if step is None:
            break   # no descent along the L-BFGS direction: at the minimum to rounding
        theta, value, aux, grad = step
        state = new_state
        losses.append(float(value))
        bar.update()
        bar.set_postfix(loss=f"{float(value):.3g}")
    return theta, first, aux, losses


def _backtrack(value_and_grad, theta: dict, direction: dict, value, max_halvings: int):
    """The first of theta + t direction, t = 1, 1/2, 1/4, ..., whose solves converge and
    whose loss is no higher than ``value``: (theta, loss, aux, gradient); None if none is."""
    t = 1.0
    for _ in range(max_halvings):
        trial = optax.apply_updates(theta, jax.tree.map(lambda d: t * d, direction))
        (v, a), g = value_and_grad(trial)
        if int(a[2]) == Status.CONVERGED and np.isfinite(float(v)) and float(v) <= float(value):
            return trial, v, a, g
        t *= 0.5
    return None


def _misfit(rec: Recording, aux) -> tuple[float, float]:
    """(RMS control point error, RMS force error relative to the force's RMS) of a prediction."""
    cp, f = np.asarray(aux[0]), np.asarray(aux[1])
    return (float(np.sqrt(np.mean((cp - rec.cp) ** 2))),
            float(np.sqrt(np.mean((f - rec.force) ** 2)) / np.sqrt(np.mean(rec.force ** 2))))


def broyden_update(J: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Good Broyden rank-one update: the J' nearest J (Frobenius norm) with J' dx = dy, i.e.
    J + (dy - J dx) dx^T / (dx^T dx). ``dx``: the manipulation step taken, ``dy``: the
    control point change the camera saw."""
    J = np.asarray(J, float)
    dx, dy = np.asarray(dx, float).ravel(), np.asarray(dy, float).ravel()
    if J.shape != (dy.size, dx.size):
        raise ValueError(f"J must be ({dy.size}, {dx.size}) for dy {dy.shape} and dx {dx.shape}, got {J.shape}")
    nx = float(dx @ dx)
    if not nx > 0:
        raise ValueError("broyden_update needs a non-zero step dx")
    return J + np.outer(dy - J @ dx, dx) / nx
