"""Needle studies with a contact (push-only) paddle: a rigid tool pressed against the
phantom instead of a set of particles glued to the tool.

The glued paddle of chapter 6 (an essential set, or stiff springs) holds its particles at
prescribed positions, so it pulls as readily as it pushes. A contact paddle is a rigid box
with rounded edges (``jaxrkpm.Contact(Box)``) placed against the phantom's boundary where the
glued paddle holds it (``phantom.contact_face(p)``: the face centre, the outward normal, the
tangents and the face's half extents), pressed in along the inward normal by an
``indentation`` and shifted along the boundary by a tangential ``shift``: its pose
(indentation, shift) is a solve parameter, so the paddle can only push (the barrier) and
drag (friction, at most mu times the normal pressure).

The path of one configuration: press the paddle in with the needle out (the tool moves with
the load scale from clear of the body to its pose), then insert the needle increment by
increment, each warm-started from the last with the paddle held. Friction is lagged
(``contact_forces(...).lag``) and the lagged normal pressure iterated within each step (the
anchors, from which each point's slip is measured, stay at the step's start) until it
changes by less than ``lag_tol`` of the largest one, so that the friction
of an increment is bounded by that increment's pressure (without the iteration a point that
left the tool would still carry the previous increment's friction). Every step is checked:
each contact point's force compressive (along the tool's outward normal) and within the
friction cone |f_t| <= mu f_n (``ContactCheck``).

The studies (``contact_sweep``, ``dynamic_contact_paddle``, ``optimize_contact_paddle``) take
any phantom with the ``NeedleTrack`` interface, ``sets(None)``, ``material(inclusion)`` and
``contact_face`` (the 2D ``Phantom`` and the 3D ``Phantom3D``); the glued studies of
``jaxrkpm.thesis.needle`` are unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..base.progress import progress_bar
from ..mechanics.contact import Box, Contact, contact_forces
from ..model.model import Model
from ..solvers.results import Status
from .needle import HoldStatus, OptimizeStatus, fung_shear_modulus

PADDLE_MODELS = ("glued", "contact")
NAME = "paddle"
MAX_ITER = 50   # Newton iterations per load step: contact with friction converges slower than the glued paddle


@dataclass(frozen=True)
class ContactPaddle:
    """The contact paddle's tool and contact settings (None: from the phantom).

    mu              Coulomb friction coefficient (lagged, see the module docstring)
    half_thickness  the box's half thickness behind its face (default two particle spacings:
                    the tool reaches out of the tissue at the deepest indentation the
                    controls allow, so no tissue closes over its back and the paddle can
                    only push; a thinner tool pressed deeper than its thickness is buried,
                    and the tissue around its back edges lets it pull)
    radius          the rounding of its edges (default a tenth of the particle spacing)
    gap             the barrier's range ghat (default a hundredth of the spacing): a touching
                    point stands off the face by less than this
    pressure        the barrier's pressure p0 at ghat / 2 (default the tissue's small-strain
                    shear modulus: the scale of the contact pressures of an indentation of the
                    order of the paddle's size)
    slip            the friction's slip tolerance eps (default a hundredth of the spacing): a
                    sticking point slips elastically by up to this
    press_steps     load steps of the press (the tool moves less than a step's share of the
                    indentation per Newton solve)
    lag_iterations  re-solves per step with the friction lag updated (at most); ``lag_tol``
                    their tolerance on each point's lagged pressure (relative) and normal
    """

    mu: float = 0.3
    half_thickness: float | None = None
    radius: float | None = None
    gap: float | None = None
    pressure: float | None = None
    slip: float | None = None
    press_steps: int = 8
    lag_iterations: int = 30
    lag_tol: float = 1e-2

    def __post_init__(self):
        if isinstance(self.mu, bool) or not isinstance(self.mu, (int, float, np.number)) \
                or not (np.isfinite(self.mu) and self.mu >= 0):
            raise ValueError(f"ContactPaddle.mu must be a friction coefficient >= 0, got {self.mu!r}")
        for k in ("half_thickness", "radius", "gap", "pressure", "slip", "lag_tol"):
            v = getattr(self, k)
            if v is not None and not (isinstance(v, (int, float, np.number)) and np.isfinite(v) and v > 0):
                raise ValueError(f"ContactPaddle.{k} must be a positive number (or None for the phantom's "
                                 f"default), got {v!r}")
        for k in ("press_steps", "lag_iterations"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"ContactPaddle.{k} must be a whole number >= 1, got {v!r}")

    def resolved(self, phantom) -> dict:
        """The tool's sizes and barrier constants for ``phantom`` (its defaults filled in)."""
        h = float(phantom.spacing)
        return {"half_thickness": self.half_thickness or 2.0 * h, "radius": self.radius or 0.1 * h,
                "gap": self.gap or 0.01 * h, "slip": self.slip or 0.01 * h, "pressure": self.pressure or tissue_shear_modulus(phantom)}


def tissue_shear_modulus(phantom) -> float:
    """The phantom tissue's small-strain shear modulus (outside inclusions)."""
    law = phantom.material_law
    if law in ("neo-hookean", "neohookean") and hasattr(phantom, "mu"):   # the 3D phantom's own constant
        return float(phantom.mu)
    return fung_shear_modulus(phantom.alpha, phantom.beta)


def tool_rotation(normal, tangents):
    """The tool frame's rotation: its last axis along the outward ``normal``, the others along
    ``tangents``; an angle (2D) or a rotation vector (3D)."""
    normal = np.asarray(normal, float)
    if normal.size == 2:
        return float(np.arctan2(-normal[0], normal[1]))
    from scipy.spatial.transform import Rotation
    M = np.column_stack([*np.asarray(tangents, float), normal])
    return Rotation.from_matrix(M).as_rotvec()


def contact_model(phantom, inclusion: str = "none", paddle: int = 1, spec: ContactPaddle = ContactPaddle()) -> Model:
    """The phantom with its immobile edge and needle as essential sets and a contact paddle
    ("paddle", a rounded ``Box``) at glued paddle position ``paddle``, clear of the body at
    load scale 0 (its pose at load 1 is the solve parameter ``pose``)."""
    c = spec.resolved(phantom)
    key = ("contact_model", inclusion, paddle, spec)
    if key not in phantom._cache:
        centre, normal, tangents, half = phantom.contact_face(paddle)
        box = Box((*half, c["half_thickness"]), c["radius"])
        rest = centre + normal * (c["half_thickness"] + c["radius"] + 2 * c["gap"])
        tool = Contact(box, position=tuple(rest), rotation=tool_rotation(normal, tangents), gap=c["gap"],
                       pressure=c["pressure"], mu=float(spec.mu), slip=c["slip"], name=NAME)
        phantom._cache[key] = Model(phantom.body, phantom.material(inclusion), phantom.integration,
                                    essential=phantom.sets(None), support=phantom.support,
                                    **({"order": phantom.order} if hasattr(phantom, "order") else {}),
                                    terms=[tool])
    return phantom._cache[key]


def pose(phantom, paddle: int, spec: ContactPaddle, control) -> dict:
    """The paddle's parameters at control = (indentation, shift...) (JAX, differentiable):
    its face pressed ``indentation`` in along the inward normal from the rest boundary, its
    centre moved by ``shift`` (d - 1 tangential components) along the boundary."""
    c = spec.resolved(phantom)
    centre, normal, tangents, _ = phantom.contact_face(paddle)
    control = jnp.asarray(control, jnp.float64)
    position = (jnp.asarray(centre) + jnp.asarray(normal) * (c["half_thickness"] + c["radius"] - control[0])
                + control[1:] @ jnp.asarray(tangents))
    return {"position": position}


# ------------------------------------------------------------------ checks
@dataclass
class ContactCheck:
    """The contact's state at one step: resultant force (d,) of the paddle on the body, its
    component along the inward normal, the active points, the smallest point normal force
    (over active points), the largest |f_t| / (mu f_n) over active points, the largest
    tangential force at an inactive point, the smallest gap, and the active points behind
    the tool's mid-plane (they passed through it: the tool's back then pushes them out of
    the body, which pulls the tissue)."""

    force: np.ndarray
    push: float
    active: int
    min_normal: float
    cone: float
    loose_friction: float
    min_gap: float
    behind: int = 0

    def ok(self, tol: float = 1e-6, cone_tol: float = 1e-2) -> bool:
        """Every contact force compressive and within the friction cone (``tol``: relative,
        against the largest point force; ``cone_tol``: the cone's, the lag's tolerance, since
        friction is bounded by the lagged pressure)."""
        return bool(self.min_normal >= -tol * max(abs(self.push), 1.0) and self.cone <= 1.0 + cone_tol
                    and self.loose_friction <= tol * max(abs(self.push), 1.0) and self.min_gap > 0
                    and self.behind == 0)


def check_contact(res, inward, mu: float) -> ContactCheck:
    """A ``ContactCheck`` of a ``ContactResult``: point forces split along the tool's outward
    normal at each point (f_n > 0: the paddle pushes) and across it."""
    f, n = np.asarray(res.point_force), np.asarray(res.normals)
    fn = np.sum(f * n, 1)
    ft = np.linalg.norm(f - fn[:, None] * n, axis=1)
    act = np.asarray(res.active)
    big = max(float(np.max(np.abs(f))) if f.size else 0.0, 1e-300)
    cone = 0.0
    if act.any() and mu > 0:
        cone = float(np.max(ft[act] / np.maximum(mu * fn[act], 1e-12 * big)))
    elif act.any():
        cone = float(np.max(ft[act]) / big) if np.max(ft[act]) > 1e-9 * big else 0.0
    F = np.asarray(res.force)
    return ContactCheck(F, float(F @ np.asarray(inward, float)), int(act.sum()),
                        float(np.min(fn[act])) if act.any() else 0.0, cone,
                        float(np.max(ft[~act])) if (~act).any() else 0.0, float(res.min_gap),
                        int(np.sum(act & (np.asarray(res.lag["anchor"])[:, -1] > 0))))


# ------------------------------------------------------------------ one configuration
class ContactHistory:
    """What an insertion with a contact paddle reports per increment (``deviation``,
    ``checks``): its final deviation and whether every contact check held."""

    @property
    def final(self) -> float:
        return float(self.deviation[-1]) if len(self.deviation) else np.nan

    @property
    def contact_ok(self) -> bool:
        return all(c.ok() for c in self.checks)


@dataclass
class ContactRun(ContactHistory):
    """One insertion with a contact paddle at glued paddle position ``paddle``."""

    paddle: int
    control: np.ndarray          # (d,) indentation and shift
    depths: np.ndarray           # (n,) needle depth of each converged increment
    deviation: np.ndarray        # (n,) lateral target deviation
    checks: list                 # ContactCheck per converged increment
    status: Status               # the first failed solve's, else CONVERGED
    solution: object = None      # the last converged Solution
    lag: dict | None = None      # the friction lag at it

    @property
    def converged(self) -> bool:
        return self.status == Status.CONVERGED

    @property
    def in_contact(self) -> bool:
        """Whether the paddle touches the body at full insertion."""
        return bool(self.checks and self.checks[-1].active > 0)


LAG_RELAXATION = 0.5
LAG_FLOOR = 1e-6     # as ContactCheck's tolerance on point forces


def lag_settled(held, now, tol: float) -> bool:
    """Whether the friction lag a solve held agrees with the state it reached: each point's
    pressure within ``tol`` of its own (the friction cone is a bound per point; pressures below
    ``LAG_FLOOR`` of the largest are not told apart), normals within ``tol`` (radians, about)."""
    p = np.asarray(now["pressure"])
    floor = LAG_FLOOR * max(float(np.max(p, initial=0.0)), 1e-300)
    return bool(np.all(np.abs(p - held["pressure"]) <= tol * np.maximum(p, floor))
                and np.max(np.abs(now["normal"] - held["normal"]), initial=0.0) <= tol)


class Stepper:
    """Solves of one contact model with lagged friction iterated per step (see the module
    docstring); ``step`` returns (Solution, lag, ContactResult) or the failed Solution."""

    def __init__(self, phantom, model: Model, paddle: int, spec: ContactPaddle):
        self.phantom, self.model, self.paddle, self.spec = phantom, model, paddle, spec

    def params(self, control, lag):
        p = pose(self.phantom, self.paddle, self.spec, control)
        return {NAME: p if lag is None else {**p, **lag}}

    def step(self, prescribed, control, start, lag, steps: int = 1):
        """Solve for ``prescribed`` at ``control`` from ``start`` with the friction ``lag``,
        then re-solve with the lag updated until its pressure settles (a failed re-solve
        keeps the last converged one: its check then reports the cone it meets)."""
        m, spec = self.model, self.spec
        sol = m.solve(prescribed, params=self.params(control, lag), initial=start, steps=steps,
                      max_iter=MAX_ITER, throw=False)
        if int(sol.status) != Status.CONVERGED:
            return sol, lag, None
        res = contact_forces(m, sol, NAME, self.params(control, lag))
        # The anchors stay the step's start (each point's slip of this step is measured from
        # there); the pressure and the tangent planes are iterated, the pressure half-way to
        # the new one each time (the plain update swings between the points sharing the load),
        # a point that left the tool at once (it carries no friction).
        # A first step (no lag) anchors at its own frictionless end.
        anchor = np.asarray(res.lag["anchor"] if lag is None else lag["anchor"])
        held = None if lag is None else {k: np.asarray(v) for k, v in lag.items()}
        for _ in range(spec.lag_iterations if spec.mu > 0 else 0):
            now = {k: np.asarray(v) for k, v in res.lag.items()}
            if held is not None and lag_settled(held, now, spec.lag_tol):
                break
            relaxed = now["pressure"] if held is None else np.where(
                now["pressure"] > 0, held["pressure"] + LAG_RELAXATION * (now["pressure"] - held["pressure"]), 0.0)
            new = {"pressure": relaxed, "normal": now["normal"], "anchor": anchor}
            # a lag update is a fixed-point iteration at one pose, not a path: the re-solve starts
            # from the converged state without ramping the lagged quantities (params=None)
            again = m.solve(prescribed, params=self.params(control, new), initial=sol._replace(params=None),
                            max_iter=MAX_ITER, throw=False)
            if int(again.status) != Status.CONVERGED:
                break
            sol, held = again, new
            res = contact_forces(m, sol, NAME, self.params(control, held))
        return sol, {k: np.asarray(v) for k, v in res.lag.items()}, res


def check_not_buried(phantom, spec: ContactPaddle, control):
    """A paddle pressed deeper than its own thickness would be buried in the tissue (which
    then closes over its back and lets it pull): refuse it."""
    c = spec.resolved(phantom)
    reach = 2 * (c["half_thickness"] + c["radius"])
    if float(control[0]) >= reach:
        raise ValueError(f"indentation {float(control[0]):.4g} buries the paddle (it is {reach:.4g} thick): "
                         "press it in less, or give ContactPaddle(half_thickness=...) a thicker tool")


def contact_insertion(phantom, paddle: int, control, inclusion: str = "none", increments: int = 15,
                      spec: ContactPaddle = ContactPaddle(), progress: bool = True) -> ContactRun:
    """Press the contact paddle at position ``paddle`` to ``control`` = (indentation, shift...)
    with the needle out, then insert the needle in ``increments`` (the paddle held there).
    ``progress``: a bar of the increments on a terminal."""
    model = contact_model(phantom, inclusion, paddle, spec)
    st = Stepper(phantom, model, paddle, spec)
    d = model.dim
    control = np.asarray(control, float)
    if control.shape != (d,) or not np.all(np.isfinite(control)):
        raise ValueError(f"control must be {d} finite numbers (indentation, then {d - 1} tangential "
                         f"shift(s)), got {control.tolist()}")
    check_not_buried(phantom, spec, control)
    inward = -phantom.contact_face(paddle)[1]
    target = np.atleast_2d(phantom.target)
    sol, lag, res = st.step({"needle": np.zeros(d)}, control, None, None, steps=spec.press_steps)
    depths, dev, checks = [], [], []
    status = Status.of(sol.status) if res is None else Status.CONVERGED
    bar = progress_bar(increments, desc=f"contact paddle {paddle} ({inclusion})", unit="increment",
                       progress=progress and res is not None)
    if res is not None:
        for depth in phantom.depths(increments):
            bar.update()
            new, new_lag, r = st.step({"needle": phantom.needle_at(depth)}, control, sol, lag)
            if r is None:
                status = Status.of(new.status)
                break
            sol, lag = new, new_lag
            depths.append(depth)
            dev.append(float(phantom.deviation_of(np.asarray(model.displacement(sol, target)[0]))))
            checks.append(check_contact(r, inward, spec.mu))
    bar.close()
    return ContactRun(paddle, control, np.array(depths), np.array(dev), checks, status, sol, lag)


# ------------------------------------------------------------------ static sweep
@dataclass
class ContactSweep:
    """Static contact paddles at every glued paddle position, pressed to ``control``, beside
    the glued sweep and the no-paddle insertion of the same phantom and increments."""

    inclusion: str
    mu: float
    control: np.ndarray        # (d,) indentation and shift of every paddle
    runs: list                 # ContactRun per paddle
    glued: np.ndarray          # (P,) final deviation with the glued paddle (NaN: it failed)
    no_paddle: float           # final deviation without a paddle

    @property
    def final(self) -> np.ndarray:
        return np.array([r.final if r.converged else np.nan for r in self.runs])

    @property
    def contact_ok(self) -> bool:
        return all(r.contact_ok for r in self.runs)

    def glued_only(self, factor: float = 2.0) -> list:
        """The paddle positions (1-based) where the glued paddle reduces |deviation| more than
        ``factor`` x what the contact paddle keeps (or the contact paddle's insertion fails):
        placements only a paddle that pulls achieves."""
        out = []
        for p, (g, c) in enumerate(zip(self.glued, self.final), 1):
            if np.isfinite(g) and (not np.isfinite(c) or abs(c) > factor * abs(g)):
                out.append(p)
        return out

    def rows(self) -> list:
        """One dict per paddle: the table of the closing note."""
        out = []
        for p, (r, g) in enumerate(zip(self.runs, self.glued), 1):
            chk = r.checks
            out.append({"paddle": p, "inclusion": self.inclusion, "mu": self.mu,
                        "indentation": float(self.control[0]), "shift": self.control[1:].tolist(),
                        "no_paddle": self.no_paddle, "glued": float(g),
                        "contact": r.final if r.converged else np.nan,
                        "depth_reached": float(r.depths[-1]) if len(r.depths) else 0.0,
                        "contact_per_increment": r.deviation.tolist(),
                        "contact_status": r.status.name,
                        "increments_converged": len(r.deviation),
                        "in_contact_at_end": r.in_contact,
                        "last_increment_in_contact": int(max([i + 1 for i, c in enumerate(chk) if c.active] or [0])),
                        "contact_ok": r.contact_ok,
                        "max_cone_ratio": max([c.cone for c in chk] or [0.0]),
                        "min_point_normal_force": min([c.min_normal for c in chk] or [0.0]),
                        "min_gap": min([c.min_gap for c in chk] or [np.inf]),
                        "most_points_behind": max([c.behind for c in chk] or [0])})
        return out


def glued_finals(phantom, inclusion: str, increments: int, paddles: Sequence[int], progress: bool = True):
    """(P,) final deviations of the glued paddles (NaN where an increment failed) and the
    no-paddle final deviation, each by ``jaxrkpm.thesis.needle.static_state`` (warm-started
    increments, as the contact paddle's insertion). ``progress``: a bar of the insertions
    on a terminal."""
    from .needle import static_state
    target = np.atleast_2d(phantom.target)

    def final(p):
        model, sol = static_state(phantom, inclusion, p, increments, progress=False)
        full = model.prescribed({"needle": phantom.needle_at(phantom.insertion)})
        if not np.allclose(np.asarray(sol.g), np.asarray(full)):
            return np.nan                 # an increment failed: it stopped short of full depth
        return float(phantom.deviation_of(np.asarray(model.displacement(sol, target)[0])))
    finals = []
    with progress_bar(len(paddles) + 1, desc=f"glued paddles ({inclusion})", unit="insertion", progress=progress) as bar:
        for p in [*paddles, None]:          # None: the no-paddle insertion
            finals.append(final(p))
            bar.update()
    return np.array(finals[:-1]), finals[-1]


def contact_sweep(phantom, inclusion: str = "none", increments: int = 15, control=None,
                  spec: ContactPaddle = ContactPaddle(), paddles: Sequence[int] | None = None,
                  progress: bool = True) -> ContactSweep:
    """The static sweep with contact paddles: each paddle position's contact paddle pressed
    to ``control`` (default: indented by one particle spacing, no shift), then the needle
    inserted; with the glued sweep and the no-paddle run to compare. ``progress``: a bar of
    the paddles on a terminal."""
    paddles = list(range(1, len(phantom.paddles) + 1)) if paddles is None else list(paddles)
    d = phantom.body.dim
    control = np.r_[phantom.spacing, np.zeros(d - 1)] if control is None else np.asarray(control, float)
    runs = []
    with progress_bar(len(paddles) + 1, desc=f"contact sweep ({inclusion})", unit="paddle", progress=progress) as bar:
        for p in paddles:
            runs.append(contact_insertion(phantom, p, control, inclusion, increments, spec, progress=progress))
            bar.update()
        bar.set_postfix_str("glued paddles and no paddle")
        glued, free = glued_finals(phantom, inclusion, increments, paddles, progress=progress)
        bar.update()
    return ContactSweep(inclusion, float(spec.mu), control, runs, glued, free)


# ------------------------------------------------------------------ dynamic paddle
@dataclass
class DynamicContactRun(ContactHistory):
    """Closed loop with a contact paddle: its pose (indentation, shift) moves during the
    insertion to hold the target on the needle line, as far as pushing and friction can."""

    paddle: int
    depths: np.ndarray          # (n,)
    deviation: np.ndarray       # (n,) after the corrections
    uncorrected: np.ndarray     # (n,) before them (the pose of the previous increment)
    control: np.ndarray         # (n, d) indentation and shift
    iterations: np.ndarray      # (n,) corrections per increment
    checks: list                # ContactCheck per increment
    status: HoldStatus
    message: str
    solution: object = None     # the last converged Solution (None: the press failed)
    lag: dict | None = None     # the friction lag at it


def max_indentation(phantom) -> float:
    """The deepest indentation the pose takes (``control_bounds``, the CLI's --indentation):
    two particle spacings."""
    return 2.0 * float(phantom.spacing)


def control_bounds(phantom, paddle: int):
    """(lower, upper) (d,) of the pose: indentation 0..``max_indentation``, each shift within
    the face's half extent (the face stays over the glued paddle's boundary piece)."""
    half = np.asarray(phantom.contact_face(paddle)[3], float)
    return np.r_[0.0, -half], np.r_[max_indentation(phantom), half]


def lateral_jacobian(stepper: Stepper, prescribed, control, sol, lag):
    """(L, d) d(lateral target displacement)/d(control) at the equilibrium ``sol`` (implicit
    differentiation of the solve, the friction lag held)."""
    phantom, model = stepper.phantom, stepper.model
    B = jnp.asarray(phantom.lateral, jnp.float64)
    sf = model.shape_functions(np.atleast_2d(phantom.target), gradients=False)
    idx, psi = jnp.asarray(sf.idx), jnp.asarray(sf.psi)

    def lateral(c):
        s = model.solve(prescribed, params=stepper.params(c, lag), initial=sol, max_iter=MAX_ITER, throw=False)
        return B @ model.constraint.point_values(idx, psi, s.u, s.g)[0]
    return np.asarray(jax.jacfwd(lateral)(jnp.asarray(control, jnp.float64)))


def dynamic_contact_paddle(phantom, paddle: int, inclusion: str = "none", increments: int = 15,
                           spec: ContactPaddle = ContactPaddle(), tol: float = 1e-4,
                           max_corrections: int = 6, start=None, max_move: float = 0.25,
                           progress: bool = True) -> DynamicContactRun:
    """Move the contact paddle's pose during insertion to hold the target on the needle line.

    The paddle is pressed to ``start`` (default: touching, no shift); each increment the
    needle advances with the pose held, then corrections: the minimum-norm pose change that
    cancels the lateral deviation by the implicit Jacobian d(lateral)/d(pose), clipped to the
    bounds (``control_bounds``); where the paddle has lost contact (a zero Jacobian) it moves
    in through the gap and presses. A pose is kept only where it brings the target nearer.
    The paddle cannot pull: where pushing and friction cannot reach the
    needle line the loop ends NOT_HELD at that increment and goes on. A correction moves the
    pose by at most ``max_move`` spacings and is halved until it brings the target nearer the
    line (the contact set changes along it: the linearisation holds only nearby).
    ``progress``: a bar of the increments on a terminal."""
    model = contact_model(phantom, inclusion, paddle, spec)
    st = Stepper(phantom, model, paddle, spec)
    lo, hi = control_bounds(phantom, paddle)
    d = model.dim
    B = np.asarray(phantom.lateral, float)
    target = np.atleast_2d(phantom.target)
    inward = -phantom.contact_face(paddle)[1]
    c = np.zeros(d) if start is None else np.clip(np.asarray(start, float), lo, hi)
    sol, lag, res = st.step({"needle": np.zeros(d)}, c, None, None, steps=spec.press_steps)
    out = {"dev": [], "pre": [], "ctl": [], "its": [], "chk": []}
    status, message = HoldStatus.CONVERGED, HoldStatus.CONVERGED.message
    if res is None:
        return DynamicContactRun(paddle, np.zeros(0), *(np.zeros(0),) * 2, np.zeros((0, d)), np.zeros(0, int), [],
                                 HoldStatus.SOLVE_FAILED, f"the press failed ({Status.of(sol.status).name})")

    def lateral_error(s):
        return B @ np.asarray(model.displacement(s, target)[0])
    depths = phantom.depths(increments)
    bar = progress_bar(len(depths), desc=f"dynamic contact paddle {paddle} ({inclusion})", unit="increment",
                       progress=progress)
    for depth in depths:
        bar.update()
        g = {"needle": phantom.needle_at(depth)}
        new, new_lag, r = st.step(g, c, sol, lag)
        if r is None:
            status, message = HoldStatus.SOLVE_FAILED, f"the needle step to {depth:.4f} failed ({Status.of(new.status).name})"
            break
        sol, lag, res = new, new_lag, r
        e = lateral_error(sol)
        out["pre"].append(float(np.linalg.norm(e) if e.size > 1 else e[0]))
        k = 0
        while np.linalg.norm(e) >= tol and k < max_corrections:
            k += 1
            J = lateral_jacobian(st, g, c, sol, lag)
            if not np.all(np.isfinite(J)) or np.linalg.norm(J) < 1e-9:
                # contact lost: move in through the gap and press by the largest move
                dc = np.r_[float(res.min_gap) + max_move * phantom.spacing, np.zeros(d - 1)]
            else:
                dc = -J.T @ np.linalg.solve(J @ J.T, e)
                dc *= min(1.0, max_move * phantom.spacing / max(np.max(np.abs(dc)), 1e-300))
            better = False
            for _ in range(3):        # accept a pose that brings the target nearer the line, else halve
                c_new = np.clip(c + dc, lo, hi)
                if np.allclose(c_new, c, atol=1e-12):
                    break
                new, new_lag, r = st.step(g, c_new, sol, lag)
                if r is not None and np.linalg.norm(lateral_error(new)) < np.linalg.norm(e):
                    c, sol, lag, res, better = c_new, new, new_lag, r, True
                    e = lateral_error(sol)
                    break
                dc = 0.5 * dc
            if not better:
                break                 # no pose within the bounds does better: push-only limit
        out["dev"].append(float(np.linalg.norm(e) if e.size > 1 else e[0]))
        out["ctl"].append(c.copy())
        out["its"].append(k)
        out["chk"].append(check_contact(res, inward, spec.mu))
        if np.linalg.norm(e) >= tol and status == HoldStatus.CONVERGED:
            status = HoldStatus.NOT_HELD
            message = (f"|lateral deviation| {np.linalg.norm(e):.2e} >= {tol:g} from depth {depth:.4f} "
                       "(the push-only paddle cannot reach the needle line)")
    bar.close()
    n = len(out["dev"])
    return DynamicContactRun(paddle, depths[:n], np.array(out["dev"]), np.array(out["pre"][:n]),
                             np.array(out["ctl"]).reshape(n, d), np.array(out["its"], int), out["chk"],
                             status, message, sol, lag)


# ------------------------------------------------------------------ optimised placement
@dataclass
class ContactOptimum:
    """The contact paddle's pose (indentation, shift) at position ``paddle`` minimising the
    squared final lateral deviation (Adam through the final solve)."""

    paddle: int
    inclusion: str
    control: np.ndarray      # best pose
    deviation: float         # its final deviation
    history: np.ndarray      # (iterations, 2d + 1): pose (d), deviation, gradient (d)
    run: ContactRun          # the insertion at the best pose
    status: OptimizeStatus
    message: str


def final_deviation_and_gradient(phantom, paddle, control, inclusion, increments, spec):
    """(final lateral deviation, its gradient in the pose (d,), ContactRun): the path to the
    last increment selects the equilibrium; the derivative is the implicit one of the last
    increment's solve with the friction lag held."""
    run = contact_insertion(phantom, paddle, control, inclusion, increments, spec, progress=False)
    d = len(control)
    if not run.converged:
        return np.nan, np.full(d, np.nan), run
    model = contact_model(phantom, inclusion, paddle, spec)
    st = Stepper(phantom, model, paddle, spec)
    g = {"needle": phantom.needle_at(run.depths[-1])}
    J = lateral_jacobian(st, g, control, run.solution, run.lag)          # (L, d)
    e = np.asarray(phantom.lateral_components(np.asarray(model.displacement(run.solution,
                                                                        np.atleast_2d(phantom.target))[0])))
    dev = run.final
    grad = (J.T @ e) / max(abs(dev), 1e-300) if e.size > 1 else J[0] * np.sign(dev)
    return dev, grad, run


def optimize_contact_paddle(phantom, paddle: int, inclusion: str = "none", increments: int = 15,
                            spec: ContactPaddle = ContactPaddle(), start=None, iterations: int = 10,
                            learning_rate: float = 0.02, decay: float = 0.9, tol: float = 1e-6,
                            step_tol: float = 1e-4, progress: bool = True) -> ContactOptimum:
    """Adam on the pose (indentation, shift) within ``control_bounds`` for min deviation^2 at
    full insertion, from ``start`` (default: 1.5 spacings in, no shift: deep enough that the
    paddle still touches at full insertion, where a shallower one lets go and the gradient is
    zero). A pose whose insertion fails is undone and the steps halved; a step that lets go of
    the tissue is kept in the history but not chosen (its deviation is the no-paddle one).
    ``progress``: a bar of the iterations on a terminal."""
    import optax
    lo, hi = control_bounds(phantom, paddle)
    d = len(lo)
    c = np.clip(np.r_[1.5 * phantom.spacing, np.zeros(d - 1)] if start is None else np.asarray(start, float), lo, hi)
    opt = optax.adam(optax.exponential_decay(learning_rate, transition_steps=1, decay_rate=decay))
    state = opt.init(jnp.asarray(c))
    dev, grad, run = final_deviation_and_gradient(phantom, paddle, c, inclusion, increments, spec)
    if not np.isfinite(dev):
        return ContactOptimum(paddle, inclusion, c, np.nan, np.zeros((0, 2 * d + 1)), run,
                              OptimizeStatus.START_FAILED, f"the insertion fails at the start pose {c.tolist()}")
    hist, runs, scale = [[*c, dev, *(2 * dev * grad)]], [run], 1.0
    status, message = OptimizeStatus.MAX_ITERATIONS, f"{iterations} iterations"
    bar = progress_bar(iterations, desc=f"optimize contact paddle {paddle}", unit="iteration", progress=progress)
    for _ in range(iterations):
        bar.update()
        bar.set_postfix(deviation=f"{dev:.2e}")
        if abs(dev) < tol:
            status, message = OptimizeStatus.CONVERGED, f"|deviation| < {tol:g}"
            break
        upd, new_state = opt.update(jnp.asarray(2 * dev * grad), state)
        c_new = np.clip(c + scale * np.asarray(upd), lo, hi)
        if np.max(np.abs(c_new - c)) < step_tol:
            status, message = OptimizeStatus.CONVERGED, f"step below {step_tol:g}"
            break
        dn, gn, rn = final_deviation_and_gradient(phantom, paddle, c_new, inclusion, increments, spec)
        if not np.isfinite(dn):
            scale *= 0.5
            continue
        c, dev, grad, state = c_new, dn, gn, new_state
        hist.append([*c, dev, *(2 * dev * grad)])
        runs.append(rn)
    bar.close()
    hist = np.array(hist)
    best = int(np.argmin(np.abs(hist[:, d])))
    return ContactOptimum(paddle, inclusion, hist[best, :d], float(hist[best, d]), hist, runs[best], status, message)
