"""Several push-only tools on the 2D needle phantom: placement, preload and closed-loop
control through the differentiable contact solve.

Each tool is a rigid ``jaxrkpm.Contact`` (a rounded ``Box`` paddle or a concave ``Arc`` cup)
on one edge of the phantom's free skin (``SKIN_2D``: every edge but the held one), named
"tool1", "tool2", ...; its control is (s, depth): the face centre at arc length s along the
edge, pressed ``depth`` in along the inward normal from the rest boundary. Bounds: the face
stays on its edge and clear of its corners and of the needle's entry, and a tool is pressed
at most ``MAX_DEPTH`` particle spacings in and never past its own reach (a buried tool lets the tissue
close over its back, and then it pulls).

An insertion presses the tools in (frictionless: they arrive) with the needle out, then
inserts the needle increment by increment, each step's friction lag settled
(``jaxrkpm.control.friction.solve_frictional``) with the anchors at the step's start. Every
step checks each tool's every contact force compressive and inside the friction cone.

Derivatives (``final_gradient``): the final target deviation's derivative with respect to
every tool's control is the forward-mode derivative through every increment's solve (each by
implicit differentiation), the anchors carried from step to step and each step's settled
pressures and normals held fixed, or (``lag_sweeps``) the lag's relaxed fixed point replayed so
that their derivatives are carried too; frictionless, the final solve's alone (the equilibrium
does not depend on the path). A tool that lets go has no influence on the deviation, so the
objective (``objective``) adds the continuation term w sum_i ((g_i - ghat) / h)_+^2 on each
tool's smallest gap g_i: zero while every tool touches, and a gradient that presses a lost
tool back in.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ..base.outcome import Outcome
from ..control.friction import RELAXATION, LagStatus, solve_frictional
from ..mechanics.contact import Arc, Box, Contact
from ..model.model import Model, SolveError
from ..solvers.results import Status
from .contact_paddle import ContactPaddle, check_contact, tool_rotation

# the free skin of the Figure 6.1 phantom, counter-clockwise (outward normal on the right of
# each edge's direction): the bottom edge right of the needle is held
SKIN_2D = {"right": ((1.0, 0.0), (1.0, 1.0)), "top": ((1.0, 1.0), (0.0, 1.0)),
           "left": ((0.0, 1.0), (0.0, 0.5)), "cut": ((0.0, 0.5), (0.5, 0.0)),
           # the right edge's halves: two tools there whose faces cannot overlap
           "right_low": ((1.0, 0.0), (1.0, 0.5)), "right_high": ((1.0, 0.5), (1.0, 1.0))}
SHAPE_NAMES = ("box", "cup")
CONTINUATION = 1.0      # the continuation term's weight w
MAX_DEPTH = 1.0         # the deepest press, in particle spacings


@dataclass(frozen=True)
class Tool:
    """A push-only tool on the skin edge ``site`` (a key of ``SKIN_2D``): a ``"box"`` paddle
    (its edges rounded by ``rounding`` particle spacings: a sharp edge pressed a spacing into
    the coarse phantom inverts the tissue at its corners) or a ``"cup"`` (a concave ``Arc``
    probe spanning +-45 degrees, its rim ``rounding`` spacings thick) whose face reaches
    ``half_length`` either side of its centre."""

    site: str = "right"
    shape: str = "box"
    half_length: float = 0.1
    rounding: float = 0.5

    def __post_init__(self):
        if self.site not in SKIN_2D:
            raise ValueError(f"unknown skin site {self.site!r}: choose one of {list(SKIN_2D)}")
        if self.shape not in SHAPE_NAMES:
            raise ValueError(f"unknown tool shape {self.shape!r}: choose one of {list(SHAPE_NAMES)}")
        if not (isinstance(self.half_length, (int, float)) and 0 < self.half_length < 0.5):
            raise ValueError(f"half_length must be in (0, 0.5), got {self.half_length!r}")
        if not (isinstance(self.rounding, (int, float)) and 0 < self.rounding <= 1):
            raise ValueError(f"rounding must be in (0, 1] particle spacings, got {self.rounding!r}")


# --tools N of the CLI: a paddle beside the target on the far side from the corner cut (it
# pushes the target back towards the needle line); two: one on each half of that edge; three:
# and one on the left edge (the side the target moves away from)
DEFAULT_TOOLS = {1: (Tool("right"),), 2: (Tool("right_low"), Tool("right_high")),
                 3: (Tool("right_low"), Tool("right_high"), Tool("left"))}


def default_tools(n: int) -> tuple:
    if n not in DEFAULT_TOOLS:
        raise ValueError(f"tools must be one of {sorted(DEFAULT_TOOLS)}, got {n!r}")
    return DEFAULT_TOOLS[n]


def check_tools(tools) -> tuple:
    tools = tuple(tools)
    if not tools or not all(isinstance(t, Tool) for t in tools):
        raise ValueError(f"tools must be a non-empty sequence of Tool, got {tools!r}")
    return tools


def names(tools) -> list:
    return [f"tool{i + 1}" for i in range(len(tools))]


def edge(tool: Tool):
    """(start a (2,), unit tangent t (2,), outward normal n (2,), length L) of the tool's edge."""
    a, b = (np.asarray(p, float) for p in SKIN_2D[tool.site])
    L = float(np.linalg.norm(b - a))
    t = (b - a) / L
    return a, t, np.array([t[1], -t[0]]), L


def geometry(phantom, tool: Tool, spec: ContactPaddle):
    """(shape, reach): the tool's sdf shape and the distance from its origin to its face's
    lowest point along -normal (pressed ``depth`` in, the origin stands ``reach - depth``
    out of the rest boundary)."""
    c = spec.resolved(phantom)
    r = tool.rounding * float(phantom.spacing)
    if tool.shape == "box":
        if tool.half_length <= r:
            raise ValueError(f"a box of half length {tool.half_length} is all rounding ({r:g})")
        return Box((tool.half_length - r, c["half_thickness"]), r), c["half_thickness"] + r
    a = np.pi / 4
    arc = Arc((tool.half_length - r) / np.sin(a), a, r)
    return arc, arc.sag + arc.thickness


def bounds(phantom, tools, spec: ContactPaddle = ContactPaddle()):
    """(lower, upper) (T, 2) of the controls (s, depth): the face on its edge, clear of its
    corners (and of the needle entry) by a particle spacing; depth 0 .. ``MAX_DEPTH``
    spacings (deeper presses invert the coarse phantom's tissue), less than the tool's
    reach."""
    h = float(phantom.spacing)
    lo, hi = [], []
    for tool in check_tools(tools):
        L = edge(tool)[3]
        reach = geometry(phantom, tool, spec)[1]
        s0, s1 = tool.half_length + h, L - tool.half_length - h
        if s0 > s1:
            raise ValueError(f"a tool of half length {tool.half_length} does not fit on the {tool.site!r} edge")
        lo.append([s0, 0.0])
        hi.append([s1, min(MAX_DEPTH * h, reach - 0.1 * h)])
    return np.array(lo), np.array(hi)


def tools_model(phantom, tools, inclusion: str = "none", spec: ContactPaddle = ContactPaddle()) -> Model:
    """The phantom (immobile edge and needle essential) with one ``Contact`` term per tool,
    each clear of the body at load scale 0 over its edge's middle."""
    tools = check_tools(tools)
    key = ("tools_model", inclusion, tools, spec)
    if key not in phantom._cache:
        c = spec.resolved(phantom)
        terms = []
        for name, tool in zip(names(tools), tools):
            a, t, n, L = edge(tool)
            shape, reach = geometry(phantom, tool, spec)
            rest = a + 0.5 * L * t + n * (reach + 2 * c["gap"])
            terms.append(Contact(shape, position=tuple(rest), rotation=tool_rotation(n, t[None]), gap=c["gap"],
                                 pressure=c["pressure"], mu=float(spec.mu), slip=c["slip"], name=name))
        phantom._cache[key] = Model(phantom.body, phantom.material(inclusion), phantom.integration,
                                    essential=phantom.sets(None), support=phantom.support, terms=terms)
    return phantom._cache[key]


def tool_params(phantom, tools, control, spec: ContactPaddle = ContactPaddle()) -> dict:
    """{tool name: {"position"}} at control (T, 2) = (s, depth) per tool (JAX, differentiable)."""
    control = jnp.asarray(control, jnp.float64).reshape(len(tools), 2)
    out = {}
    for i, (name, tool) in enumerate(zip(names(tools), tools)):
        a, t, n, _ = edge(tool)
        reach = geometry(phantom, tool, spec)[1]
        out[name] = {"position": jnp.asarray(a) + control[i, 0] * jnp.asarray(t)
                     + (reach - control[i, 1]) * jnp.asarray(n)}
    return out


def check_control(phantom, tools, control, spec) -> np.ndarray:
    control = np.asarray(control, float)
    if control.shape != (len(tools), 2) or not np.all(np.isfinite(control)):
        raise ValueError(f"control must be ({len(tools)}, 2) finite numbers (s, depth per tool), "
                         f"got {control.tolist()}")
    lo, hi = bounds(phantom, tools, spec)
    if np.any(control < lo - 1e-12) or np.any(control > hi + 1e-12):
        raise ValueError(f"control {control.tolist()} outside the bounds {lo.tolist()} .. {hi.tolist()} "
                         "(the face off its edge, or a tool buried)")
    return control


def rest_control(phantom, tools, spec: ContactPaddle = ContactPaddle(), depth=None, at=None) -> np.ndarray:
    """(T, 2): each tool at the target's height (``at``: arc length, default the edge point
    nearest the target, within the bounds), pressed ``depth`` in (default one spacing)."""
    lo, hi = bounds(phantom, tools, spec)
    out = []
    for i, tool in enumerate(tools):
        a, t, _, _ = edge(tool)
        s = float((np.asarray(phantom.target) - a) @ t) if at is None else float(at)
        out.append([s, float(phantom.spacing) if depth is None else float(depth)])
    return np.clip(np.array(out), lo, hi)


# ------------------------------------------------------------------ one insertion
@dataclass
class ToolsRun:
    """One insertion with the tools held at ``control``.

    depths (n,), deviation (n,)   needle depth and lateral target deviation per increment
    force (n, T, 2)               each tool's resultant force on the body per increment
    checks                        per increment, a ContactCheck per tool
    lag_status                    per increment, the friction lag's LagStatus
    status                        the first failed solve's Status, else CONVERGED
    steps                         [(Solution, held lag)] of the press and of every increment"""

    control: np.ndarray
    depths: np.ndarray
    deviation: np.ndarray
    force: np.ndarray
    checks: list
    lag_status: list
    status: Status
    steps: list = field(default_factory=list, repr=False)

    @property
    def final(self) -> float:
        return float(self.deviation[-1]) if len(self.deviation) and self.converged else np.nan

    @property
    def converged(self) -> bool:
        return self.status == Status.CONVERGED

    @property
    def contact_ok(self) -> bool:
        """Every contact force of every tool compressive and in the cone at every increment."""
        return all(c.ok() for row in self.checks for c in row)

    @property
    def in_contact(self) -> list:
        """Per tool, whether it touches at full insertion."""
        return [c.active > 0 for c in self.checks[-1]] if self.checks else []


def _checks(phantom, tools, results, mu):
    return [check_contact(results[n], -edge(t)[2], mu) for n, t in zip(names(tools), tools)]


def insertion(phantom, tools, control, inclusion: str = "none", increments: int = 15,
              spec: ContactPaddle = ContactPaddle(), tol: float = 1e-6) -> ToolsRun:
    """Press the tools to ``control`` (T, 2) with the needle out, then insert the needle in
    ``increments``, the tools held; ``tol``: the friction lag's (``solve_frictional``)."""
    tools = check_tools(tools)
    control = check_control(phantom, tools, control, spec)
    model = tools_model(phantom, tools, inclusion, spec)
    params = tool_params(phantom, tools, control, spec)
    target = np.atleast_2d(phantom.target)
    frictionless = {n: {**p, "mu": 0.0} for n, p in params.items()}
    press = solve_frictional(model, {"needle": np.zeros(2)}, params=frictionless, steps=spec.press_steps, tol=tol)
    steps, depths, dev, force, checks, lags = [], [], [], [], [], []
    status = Status.CONVERGED if press.status != LagStatus.SOLVE_FAILED else press.solve_status
    if status == Status.CONVERGED:
        steps.append((press.solution, None))
        sol, lag = press.solution, press.lag
        for depth in phantom.depths(increments):
            fs = solve_frictional(model, {"needle": phantom.needle_at(depth)}, params=params, initial=sol,
                                  lag=lag, tol=tol)
            if fs.status == LagStatus.SOLVE_FAILED:
                status = fs.solve_status
                break
            sol, lag = fs.solution, fs.lag
            steps.append((sol, fs.held))
            depths.append(depth)
            dev.append(float(phantom.deviation_of(np.asarray(model.displacement(sol, target)[0]))))
            force.append([np.asarray(fs.results[n].force) for n in names(tools)])
            checks.append(_checks(phantom, tools, fs.results, spec.mu))
            lags.append(fs.status)
    return ToolsRun(control, np.array(depths), np.array(dev), np.array(force).reshape(-1, len(tools), 2), checks,
                    lags, status, steps)


# ------------------------------------------------------------------ derivatives
def _final_state(phantom, model, tools, spec, run: ToolsRun, frictional: bool, sweeps: int = 0):
    """control (T*2,) -> (lateral (L,), smallest gap per tool (T,)) at full insertion, the
    path replayed from ``run``'s converged states (see the module docstring)."""
    nm = names(tools)
    sf = model.shape_functions(np.atleast_2d(phantom.target), gradients=False)
    idx, psi = jnp.asarray(sf.idx), jnp.asarray(sf.psi)
    B = jnp.asarray(phantom.lateral, jnp.float64)
    depths = phantom.depths(len(run.depths))

    def gaps_of(sol, params):
        problem = model.problem(params)
        d = model.constraint.coefficients(sol.u, sol.g)
        return [problem.term(n).gaps(problem.term(n).points(d), 1.0) for n in nm]

    def f(c):
        params = tool_params(phantom, tools, c, spec)
        if not frictional:
            p = params
            sol = model.solve({"needle": phantom.needle_at(depths[-1])}, params=p, initial=run.steps[-1][0],
                              max_iter=50)
        else:
            p = {n: {**params[n], "mu": 0.0} for n in nm}
            sol = model.solve({"needle": np.zeros(2)}, params=p, initial=run.steps[0][0], max_iter=50)
            for depth, (start, held) in zip(depths, run.steps[1:]):
                prev = model.problem(p)
                d = model.constraint.coefficients(sol.u, sol.g)
                anchors = {n: prev.term(n).local(prev.term(n).points(d), 1.0) for n in nm}
                p = {n: {**params[n], "pressure": jnp.asarray(held[n]["pressure"]),
                         "normal": jnp.asarray(held[n]["normal"]), "anchor": anchors[n]} for n in nm}
                g = {"needle": phantom.needle_at(depth)}
                sol = model.solve(g, params=p, initial=start, max_iter=50)
                for _ in range(sweeps):
                    # the lag's own fixed point, replayed: its tangent converges with it
                    problem = model.problem(p)
                    d = model.constraint.coefficients(sol.u, sol.g)
                    now = {n: problem.term(n).results(d, jnp.asarray(1.0)).lag for n in nm}
                    p = {n: {**p[n], "normal": now[n]["normal"], "pressure": jnp.where(
                        now[n]["pressure"] > 0, p[n]["pressure"] + RELAXATION * (now[n]["pressure"] - p[n]["pressure"]),
                        0.0)} for n in nm}
                    sol = model.solve(g, params=p, initial=start, max_iter=50)
        lateral = B @ model.constraint.point_values(idx, psi, sol.u, sol.g)[0]
        return lateral, jnp.stack([jnp.min(g) for g in gaps_of(sol, p)])
    return f


def final_gradient(phantom, tools, run: ToolsRun, inclusion: str = "none", spec: ContactPaddle = ContactPaddle(),
                   lag_sweeps: int = 0):
    """(lateral (L,), its Jacobian (L, T*2), smallest gaps (T,), their Jacobian (T, T*2)) at
    full insertion with respect to the controls, through every increment (see the module
    docstring: the anchors carried; the settled pressures and normals held, or, with
    ``lag_sweeps`` > 0, that many sweeps of the lag's relaxed fixed point replayed per
    increment, so that their derivatives converge with them)."""
    tools = check_tools(tools)
    if not run.converged:
        raise ValueError(f"the insertion did not reach full depth ({run.status.name}): no derivative")
    model = tools_model(phantom, tools, inclusion, spec)
    f = _final_state(phantom, model, tools, spec, run, spec.mu > 0, lag_sweeps)
    c = jnp.asarray(run.control, jnp.float64).reshape(-1)
    lat, gaps = f(c)
    J, Jg = jax.jacfwd(f)(c)
    return np.asarray(lat), np.asarray(J), np.asarray(gaps), np.asarray(Jg)


def objective(phantom, tools, control, inclusion: str = "none", increments: int = 15,
              spec: ContactPaddle = ContactPaddle(), scale: float = 1.0, weight: float = CONTINUATION,
              tol: float = 1e-6, lag_sweeps: int = 0):
    """(value, gradient (T, 2), ToolsRun): (deviation / scale)^2 plus the continuation term
    w sum_i ((g_i - ghat) / h)_+^2 (module docstring); an insertion that fails gives (inf,
    NaN), as does one whose derivative replay fails."""
    tools = check_tools(tools)
    run = insertion(phantom, tools, control, inclusion, increments, spec, tol)
    if not run.converged:
        return np.inf, np.full((len(tools), 2), np.nan), run
    try:
        lat, J, gaps, Jg = final_gradient(phantom, tools, run, inclusion, spec, lag_sweeps)
    except SolveError:
        # a replayed step that does not converge again from its own equilibrium (a tangent
        # near singular there) has no derivative to give: the point counts as failed
        return np.inf, np.full((len(tools), 2), np.nan), run
    h = float(phantom.spacing)
    ghat = spec.resolved(phantom)["gap"]
    e = lat / scale
    lost = np.maximum(gaps - ghat, 0.0) / h
    value = float(e @ e + weight * np.sum(lost ** 2))
    grad = 2 * (J.T @ e) / scale + weight * 2 * (Jg.T @ lost) / h
    return value, grad.reshape(len(tools), 2), run


# ------------------------------------------------------------------ placement optimisation
class PlacementStatus(Outcome):
    """Outcome of ``optimize_placement``."""

    CONVERGED = 0, "converged: projected gradient norm below gtol, or relative change of the objective below ftol"
    MAX_ITERATIONS = 1, "the iteration budget ran out before the criterion held; the best iterate is returned"
    START_FAILED = 2, "the insertion fails at the start pose"
    LINE_SEARCH = 3, "the line search failed (an objective that is not smooth there); the best iterate is returned"


@dataclass
class Placement:
    """The optimised controls (T, 2) of the tools (``optimize_placement``)."""

    tools: tuple
    control: np.ndarray
    deviation: float
    value: float
    projected_gradient: float
    iterations: int
    evaluations: int
    status: PlacementStatus
    message: str
    history: list
    run: ToolsRun


def projected_gradient(x, g, lo, hi) -> float:
    """The infinity norm of the gradient projected on the bounds (0 at a bound it pushes on)."""
    pg = np.where((x <= lo + 1e-12) & (g > 0), 0.0, np.where((x >= hi - 1e-12) & (g < 0), 0.0, g))
    return float(np.max(np.abs(pg)))


def optimize_placement(phantom, tools, inclusion: str = "none", increments: int = 15,
                       spec: ContactPaddle = ContactPaddle(), start=None, free: str = "all",
                       gtol: float = 1e-6, ftol: float = 1e-9, max_iterations: int = 40,
                       tol: float = 1e-6, lag_sweeps: int = 0, grid: int = 0) -> Placement:
    """Bounded L-BFGS (scipy's L-BFGS-B) on the tools' controls minimising ``objective``
    (the squared final deviation relative to the no-tool one, with the continuation term),
    gradients through every increment. Converged when the projected gradient's largest
    component is below ``gtol`` or the objective changes by less than ``ftol`` (relative) in
    an iteration. ``free``: "all" (positions and depths) or "depth" (each tool pressed at its
    start position: the preload). The default start: each tool at the target's height half a
    spacing in (half as deep again, up to three times, where that insertion fails).
    ``lag_sweeps``: ``final_gradient``'s (0: the friction's settled pressures and normals held
    in the gradient). ``grid`` > 0: first ``grid_search`` with that many points per free
    control, and start from its best point (so the optimum is no worse than the grid's)."""
    from scipy.optimize import minimize
    tools = check_tools(tools)
    if free not in ("all", "depth"):
        raise ValueError(f"free must be 'all' or 'depth', got {free!r}")
    lo, hi = bounds(phantom, tools, spec)
    x0 = (rest_control(phantom, tools, spec, depth=0.5 * phantom.spacing) if start is None
          else np.clip(np.asarray(start, float), lo, hi))
    mask = np.ones_like(lo, bool) if free == "all" else np.array([[False, True]] * len(tools))
    if grid and start is None:
        gx = grid_search(phantom, tools, inclusion, increments, spec, points=grid, free=free, start=x0, tol=tol)[0]
        if gx is not None:
            x0 = gx
            start = gx
    scale = abs(no_tool_deviation(phantom, inclusion, increments)) or 1.0
    hist, best, seen = [], {}, {}

    def full(z):
        x = x0.copy()
        x[mask] = z
        return x

    def fun(z):
        key = tuple(np.round(z, 15))
        if key not in seen:
            v, g, run = objective(phantom, tools, full(z), inclusion, increments, spec, scale, tol=tol,
                                  lag_sweeps=lag_sweeps)
            seen[key] = (v, g, run)
            hist.append({"control": full(z).tolist(), "value": v, "deviation": run.final})
            if np.isfinite(v) and (not best or v < best["value"]):
                best.update(value=v, control=full(z), run=run, grad=g)
        v, g, _ = seen[key]
        if not np.isfinite(v):
            return 1e6, np.zeros(int(mask.sum()))
        return v, g[mask]

    v0, _ = fun(x0[mask])
    for _ in range(3 if start is None else 0):
        if v0 < 1e6:
            break
        # the default start presses too deep for this insertion: half as deep
        x0[:, 1] *= 0.5
        v0, _ = fun(x0[mask])
    if v0 >= 1e6:
        return Placement(tools, x0, np.nan, np.inf, np.nan, 0, 1, PlacementStatus.START_FAILED,
                         "the insertion fails at the start pose", hist, seen[tuple(np.round(x0[mask], 15))][2])
    r = minimize(fun, x0[mask], jac=True, method="L-BFGS-B", bounds=list(zip(lo[mask], hi[mask])),
                 options={"maxiter": max_iterations, "gtol": gtol, "ftol": ftol, "maxls": 20})
    pg = projected_gradient(best["control"][mask], best["grad"][mask], lo[mask], hi[mask])
    if r.status == 0:
        status = PlacementStatus.CONVERGED
    elif r.status == 1:
        status = PlacementStatus.MAX_ITERATIONS
    else:
        status = PlacementStatus.LINE_SEARCH
    return Placement(tools, best["control"], best["run"].final, best["value"], pg, int(r.nit), int(r.nfev), status,
                     str(r.message), hist, best["run"])


def grid_search(phantom, tools, inclusion: str = "none", increments: int = 15,
                spec: ContactPaddle = ContactPaddle(), points: int = 3, free: str = "all", start=None,
                tol: float = 1e-6):
    """The grid of the same space as ``optimize_placement``: ``points`` values per free
    control between its bounds (every combination). Returns (best control (T, 2), its
    |deviation|, [(control, deviation)])."""
    tools = check_tools(tools)
    lo, hi = bounds(phantom, tools, spec)
    x0 = rest_control(phantom, tools, spec, depth=0.5 * phantom.spacing) if start is None else np.asarray(start, float)
    mask = np.ones_like(lo, bool) if free == "all" else np.array([[False, True]] * len(tools))
    axes = [np.linspace(a, b, points) for a, b in zip(lo[mask], hi[mask])]
    rows = []
    for z in itertools.product(*axes):
        x = x0.copy()
        x[mask] = z
        run = insertion(phantom, tools, x, inclusion, increments, spec, tol)
        rows.append((x, run.final))
    ok = [(x, d) for x, d in rows if np.isfinite(d)]
    bx, bd = min(ok, key=lambda r: abs(r[1])) if ok else (None, np.nan)
    return bx, abs(bd), rows


def no_tool_deviation(phantom, inclusion: str = "none", increments: int = 15) -> float:
    """The final deviation without a tool (warm-started increments, as the tools' runs)."""
    from .needle import static_state
    model, sol = static_state(phantom, inclusion, None, increments)
    return float(phantom.deviation_of(np.asarray(model.displacement(sol, np.atleast_2d(phantom.target))[0])))


# ------------------------------------------------------------------ closed loop
class QPStatus(Outcome):
    """Outcome of one closed-loop correction's QP."""

    OPTIMAL = 0, "the QP was solved"
    INFEASIBLE = 1, "no move keeps every touching tool's force above the minimum and in the cone within the bounds"
    FAILED = 2, "the QP solver failed"


class LoopStatus(Outcome):
    """Outcome of ``closed_loop``."""

    HELD = 0, "the target held within tol at every increment"
    NOT_HELD = 1, "at some increment no push-only move brought the deviation below tol"
    SOLVE_FAILED = 2, "a solve failed; the increments before it are kept"


def step_jacobians(phantom, tools, model, spec, prescribed, control, sol, held):
    """At the equilibrium ``sol`` (solved with the lag ``held``): lateral e (L,), per tool
    the normal (inward) and tangential resultant forces n, t (T,), and their Jacobians with
    respect to the controls (T*2,), by implicit differentiation (the lag held)."""
    nm = names(tools)
    sf = model.shape_functions(np.atleast_2d(phantom.target), gradients=False)
    idx, psi = jnp.asarray(sf.idx), jnp.asarray(sf.psi)
    B = jnp.asarray(phantom.lateral, jnp.float64)
    frames = [edge(t) for t in tools]

    def f(c):
        params = tool_params(phantom, tools, c, spec)
        p = params if held is None else {n: {**params[n], **{k: jnp.asarray(v) for k, v in held[n].items()}}
                                         for n in nm}
        s = model.solve(prescribed, params=p, initial=sol, max_iter=50)
        problem = model.problem(p)
        d = model.constraint.coefficients(s.u, s.g)
        F = [problem.term(n).results(d, jnp.asarray(1.0)).force for n in nm]
        nrm = jnp.stack([-F[i] @ jnp.asarray(fr[2]) for i, fr in enumerate(frames)])
        tan = jnp.stack([F[i] @ jnp.asarray(fr[1]) for i, fr in enumerate(frames)])
        return B @ model.constraint.point_values(idx, psi, s.u, s.g)[0], nrm, tan
    c = jnp.asarray(control, jnp.float64).reshape(-1)
    vals = f(c)
    jacs = jax.jacfwd(f)(c)
    return tuple(np.asarray(v) for v in vals), tuple(np.asarray(j) for j in jacs)


def qp_move(e, Je, n, Jn, t, Jt, mu, x, lo, hi, max_move, min_force, regular=1e-6):
    """The QP of one correction: min |e + Je dx|^2 + regular |dx / max_move|^2 subject to,
    for each touching tool (n > 0), n + Jn dx >= min_force and, where its resultant is inside
    the cone now, |t + Jt dx| <= mu (n + Jn dx);
    lo <= x + dx <= hi, |dx| <= max_move. Returns (dx, QPStatus): INFEASIBLE where a linear
    program finds no dx that meets the constraints."""
    from scipy.optimize import linprog, minimize
    k = len(x)
    lb, ub = np.maximum(lo - x, -max_move), np.minimum(hi - x, max_move)
    # the constraints as G dx <= h: minimum force, then the cone's two sides
    G, h = [], []
    for i in np.flatnonzero(n > 0):
        G.append(-Jn[i])
        h.append(n[i] - min_force)
        # the cone on the resultant only where it holds now: on a rounded edge each point's
        # force stays in its own cone (the friction law) while their sum may lean further
        if mu > 0 and abs(t[i]) <= mu * n[i]:
            G += [Jt[i] - mu * Jn[i], -Jt[i] - mu * Jn[i]]
            h += [mu * n[i] - t[i], mu * n[i] + t[i]]
    G, h = np.reshape(G, (-1, k)), np.asarray(h, float)
    if len(h) and linprog(np.zeros(k), A_ub=G, b_ub=h, bounds=list(zip(lb, ub)), method="highs").status == 2:
        return np.zeros(k), QPStatus.INFEASIBLE
    cons = [{"type": "ineq", "fun": lambda d: h - G @ d, "jac": lambda d: -G}] if len(h) else []
    w = regular / max_move ** 2

    def fun(d):
        r = e + Je @ d
        return float(r @ r + w * d @ d), 2 * Je.T @ r + 2 * w * d
    r = minimize(fun, np.zeros(k), jac=True, method="SLSQP", bounds=list(zip(lb, ub)), constraints=cons,
                 options={"maxiter": 200, "ftol": 1e-16})
    if r.status == 0:
        return r.x, QPStatus.OPTIMAL
    return np.zeros(k), QPStatus.FAILED


@dataclass
class LoopRun:
    """Closed-loop push-only control (``closed_loop``): per increment the deviation after the
    corrections (and before them), the controls, each tool's force, the QP statuses, the
    contact checks per tool."""

    depths: np.ndarray
    deviation: np.ndarray
    uncorrected: np.ndarray
    control: np.ndarray       # (n, T, 2)
    force: np.ndarray         # (n, T, 2)
    corrections: list
    qp_status: list           # per increment, the QPStatus of each correction
    checks: list
    status: LoopStatus
    message: str

    @property
    def final(self) -> float:
        return float(self.deviation[-1]) if len(self.deviation) else np.nan

    @property
    def contact_ok(self) -> bool:
        return all(c.ok() for row in self.checks for c in row)


def closed_loop(phantom, tools, inclusion: str = "none", increments: int = 15,
                spec: ContactPaddle = ContactPaddle(), start=None, tol: float = 1e-3, max_corrections: int = 6,
                max_move: float = 0.25, min_force: float | None = None, lag_tol: float = 1e-6) -> LoopRun:
    """Move the tools during insertion to hold the target on the needle line: each increment
    the needle advances with the controls held, then corrections, each the QP ``qp_move`` on
    the implicit Jacobians of the target and of every tool's force (moves of at most
    ``max_move`` spacings; a touching tool keeps at least ``min_force``, default a
    thousandth of p0 times the spacing), halved until it brings the target nearer the line.
    The default start: each tool at the target's height half a spacing in (half as deep
    again, up to three times, where the press fails)."""
    tools = check_tools(tools)
    h = float(phantom.spacing)
    lo, hi = (b.reshape(-1) for b in bounds(phantom, tools, spec))
    x = (rest_control(phantom, tools, spec, depth=0.5 * h) if start is None
         else check_control(phantom, tools, start, spec)).reshape(-1)
    model = tools_model(phantom, tools, inclusion, spec)
    nm = names(tools)
    target = np.atleast_2d(phantom.target)
    fmin = 1e-3 * spec.resolved(phantom)["pressure"] * h if min_force is None else float(min_force)
    P = lambda x: tool_params(phantom, tools, x, spec)        # noqa: E731
    for attempt in range(4 if start is None else 1):
        if attempt:
            x = x.reshape(-1, 2)
            x[:, 1] *= 0.5            # the default start presses too deep for this phantom: half as deep
            x = x.reshape(-1)
        press = solve_frictional(model, {"needle": np.zeros(2)},
                                 params={n: {**p, "mu": 0.0} for n, p in P(x).items()}, steps=spec.press_steps,
                                 tol=lag_tol)
        if press.status != LagStatus.SOLVE_FAILED:
            break
    out = {k: [] for k in ("dev", "pre", "ctl", "frc", "its", "qp", "chk")}
    if press.status == LagStatus.SOLVE_FAILED:
        return LoopRun(np.zeros(0), *(np.zeros(0),) * 2, np.zeros((0, len(tools), 2)), np.zeros((0, len(tools), 2)),
                       [], [], [], LoopStatus.SOLVE_FAILED, f"the press failed ({press.solve_status.name})")
    sol, lag = press.solution, press.lag
    status, message = LoopStatus.HELD, LoopStatus.HELD.message

    def lateral(s):
        return np.asarray(phantom.lateral_components(np.asarray(model.displacement(s, target)[0])))
    depths = phantom.depths(increments)
    for depth in depths:
        g = {"needle": phantom.needle_at(depth)}
        fs = solve_frictional(model, g, params=P(x), initial=sol, lag=lag, tol=lag_tol)
        if fs.status == LagStatus.SOLVE_FAILED:
            status, message = LoopStatus.SOLVE_FAILED, f"the needle step to {depth:.4f} failed"
            break
        e = lateral(fs.solution)
        out["pre"].append(float(np.linalg.norm(e)))
        k, qps = 0, []
        while np.linalg.norm(e) >= tol and k < max_corrections:
            k += 1
            (e0, n, t), (Je, Jn, Jt) = step_jacobians(phantom, tools, model, spec, g, x, fs.solution, fs.held)
            dx, qs = qp_move(e0, Je, n, Jn, t, Jt, spec.mu, x, lo, hi, max_move * h, fmin)
            qps.append(qs)
            if qs != QPStatus.OPTIMAL or np.max(np.abs(dx)) < 1e-12:
                break
            better = False
            for _ in range(4):
                new = solve_frictional(model, g, params=P(x + dx), initial=fs.solution, lag=fs.lag, tol=lag_tol)
                if new.status != LagStatus.SOLVE_FAILED and np.linalg.norm(lateral(new.solution)) < np.linalg.norm(e):
                    x, fs, better = x + dx, new, True
                    e = lateral(fs.solution)
                    break
                dx = 0.5 * dx
            if not better:
                break
        sol, lag = fs.solution, fs.lag
        out["dev"].append(float(phantom.deviation_of(np.asarray(model.displacement(sol, target)[0]))))
        out["ctl"].append(x.reshape(-1, 2).copy())
        out["frc"].append([np.asarray(fs.results[n_].force) for n_ in nm])
        out["its"].append(k)
        out["qp"].append(qps)
        out["chk"].append(_checks(phantom, tools, fs.results, spec.mu))
        if np.linalg.norm(e) >= tol and status == LoopStatus.HELD:
            status = LoopStatus.NOT_HELD
            message = f"|deviation| {np.linalg.norm(e):.2e} >= {tol:g} from depth {depth:.4f}"
    m = len(out["dev"])
    return LoopRun(depths[:m], np.array(out["dev"]), np.array(out["pre"][:m]), np.array(out["ctl"]).reshape(m, -1, 2),
                   np.array(out["frc"]).reshape(m, -1, 2), out["its"], out["qp"], out["chk"], status, message)
