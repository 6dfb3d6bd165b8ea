"""Contact with rigid tools: a smooth barrier (incremental potential contact) as a term.

A rigid tool is a shape given by its signed distance function ``sdf(y)`` in the tool's own
frame (``HalfSpace``, ``Box`` with rounded edges, ``Sphere`` (a disc in 2D), ``Capsule``, ``Arc`` (a concave
probe, 2D)),
placed by a pose: a position c and a rotation R (2D: an angle; 3D: a rotation vector), so
that a point x of space is at y = R^T (x - c) in the tool's frame and at the gap
g(x) = sdf(R^T (x - c)) from the tool. The pose is a parameter of the solve
(``Model.solve(params={name: {"position": c, "rotation": theta}})``), differentiable by the
model's implicit differentiation.

**The tool moves with the load scale.** The spec's ``position`` / ``rotation`` is the tool's
pose at load scale 0 (where the body is undeformed: it must not touch the tool there); the
parameters are its pose at load scale 1, and in between the pose is interpolated linearly
(c(l) = c_0 + l (c - c_0), likewise the angle or rotation vector). So the solver's load steps
(``solve(..., steps=n)``, halved on failure) move the tool in steps, as they scale a dead load.
A solve warm-started at load 1 (``initial=sol``) with a new pose moves the tool from its pose
in ``sol`` (``Solution.params``) to the new one along the solve's path, each step predicted
from the tangent of the converged state before it, so step cutting shrinks the move.

**Contact points: the boundary quadrature points of the model's own boundary rule**
(``Context.balanced``), each displaced by that rule's shape-function row and weighted by its
weight. Under SCNI these are the Gauss points on the smoothing cells' boundary facets with
the 'nodal' rule's interpolated shape functions, the very rule of SCNI's boundary integral
(``scni.Smoothing.boundary``), so that a uniform pressure gives exactly the nodal forces
that a uniform stress balances (the contact patch test passes to round-off); under Gauss
integration they are the boundary Gauss points of the tractions. Why quadrature points and
not the boundary particles: the particles' lumped (trapezoidal) weights differ from SCNI's
rule wherever a cell's boundary facet straddles its particle, and that difference alone
breaks the patch test. The price: the surface between two points may dip into a tool by
O(h^2 / radius of the tool).

**Normal contact** (Li et al. 2020, IPC): the energy sum_b w_b b(g_b) with the barrier

    b(g) = -kappa (g - ghat)^2 ln(g / ghat)   for 0 < g < ghat,   0 for g >= ghat,

C2 at ghat, so the contact pressure p = -b'(g) rises smoothly from 0 at g = ghat. ``pressure``
p0 sets kappa = p0 / (ghat (ln 2 + 1/2)): the pressure at g = ghat/2 is p0. Accuracy: a point
in contact stands off the tool by the gap at which the barrier carries its pressure, between
0 and ghat (ghat/2 at p = p0, about 0.6 ghat p0 / p for p >> p0): the solution is that of
exact contact with the tool offset by less than ghat. **No interpenetration**: below
g_min = ``floor`` x ghat the barrier is continued by its second-order Taylor expansion at
g_min (finite and convex, so that a load step that carries the tool past points starts from a
finite energy and Newton pushes them out: with +inf there, every load step that moves the tool
by more than the current gap, at most ghat, would fail, and the tool could not advance more
than ghat a step). So the energy is finite everywhere and the line search (which halves a
step whose energy does not decrease, ``jaxrkpm.solvers.newton``) keeps the body out of the
tool: at equilibrium every contact point has g > g_min > 0 while its pressure is below
p(g_min) (about 10 p0 at the default floor 0.1), and g > 0 while it is below about 20 p0;
``contact_forces`` reports the smallest gap, so a pressure far beyond p0 (g <= g_min: the
tolerance is not met) is visible. A floor nearer 0 allows higher pressures before g_min but
costs Newton iterations (from g_min a Newton step on the logarithm about doubles the gap). Choose p0 near
the expected contact pressure and ghat a small fraction of the indentation.

**Friction** (regularised Coulomb with lagged quantities, IPC's smoothed friction): the
dissipation potential sum_b w_b mu lambda_b f0(|P_b (y_b - yhat_b)|) with lambda_b the lagged
normal pressure, yhat_b the lagged anchor (the point's position in the tool's frame at the
previous step), P_b the lagged tangent projector (I - n n^T, n the lagged unit normal in the
tool's frame: by default the sdf's gradient at the anchor), and f0 the C1 smoothing of |s|
(f0 = -s^3/(3 eps^2) + s^2/eps + eps/3 below the slip tolerance eps = ``slip``, s above): the
friction force is mu lambda f0'(s), sticking (an elastic slip of up to eps) below mu lambda,
sliding at it. The lagged quantities are parameters
(``pressure``, ``anchor``, ``normal``; zero pressure: frictionless): a frictional load path is a
sequence of solves, each lagging the previous one (``contact_forces(...).lag``), as in IPC's
lagged iterations, so a solve's derivatives are those of one lagged step (the lagged quantities
held). Within a step the pressure and the normal may be iterated with the anchors held (the
step's start): at the fixed point the friction is bounded by the step's own pressure in its own
tangent plane, i.e. inside the Coulomb cone (on a rounded edge a point slides around the tool,
and the anchor's normal is no longer the point's).

Results: ``contact_forces(model, sol, name)`` (force per tool, normal and tangential parts,
pressure, gap and activity of each point). Derivatives are those of the equilibrium where the
contact set is stable: a point at g = ghat has a continuous second derivative (the barrier is
C2), so the implicit Jacobian is continuous there, but the Hessian of the tool's sdf jumps
between its face and edge regions (a box's rounded edges).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, ClassVar, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.checks import positive
from ..discretise.quadrature import Table
from .term import Context, Pairs, Term, TermSpec, boolean_mask, static, term

LN2_HALF = float(np.log(2.0) + 0.5)   # p(ghat / 2) = kappa ghat (ln 2 + 1/2)


# ------------------------------------------------------------------ tool shapes (sdf)
def _unit(v):
    """v (..., d) scaled to unit length over the last axis (0 stays 0)."""
    return v / jnp.maximum(jnp.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def _safe_norm(v):
    """|v| over the last axis with a zero (not NaN) gradient at v = 0."""
    s = jnp.sum(v * v, -1)
    pos = s > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, s, 1.0)), 0.0)


def _length(owner: str, name: str, v, zero: bool = False) -> float:
    """``v`` as a float, checked: a finite number > 0 (>= 0 with ``zero``)."""
    ok = not isinstance(v, (bool, np.bool_)) and isinstance(v, (int, float, np.integer, np.floating))
    if not ok or not np.isfinite(v) or not (v >= 0 if zero else v > 0):
        raise ValueError(f"{owner}.{name} must be a finite number {'>= 0' if zero else '> 0'}, got {v!r}")
    return float(v)


@dataclass(frozen=True)
class HalfSpace:
    """The half-space {n . y <= 0} of the tool's frame (a plate's face through its origin);
    ``normal`` the outward unit normal n in the tool's frame (default: the last axis)."""

    normal: tuple | None = None

    def __post_init__(self):
        if self.normal is not None:
            try:
                n = np.asarray(self.normal, float).reshape(-1)
            except (TypeError, ValueError):
                raise ValueError(f"HalfSpace.normal must be a vector of numbers, got {self.normal!r}") from None
            if not np.all(np.isfinite(n)) or not np.linalg.norm(n) > 0:
                raise ValueError(f"HalfSpace.normal must be a finite, non-zero vector (the outward normal), "
                                 f"got {self.normal!r}")
            object.__setattr__(self, "normal", tuple(float(v) for v in n))

    def sdf(self, y):
        n = np.zeros(y.shape[-1]) if self.normal is None else np.asarray(self.normal, float)
        if self.normal is None:
            n[-1] = 1.0
        if n.shape != (y.shape[-1],):
            raise ValueError(f"HalfSpace.normal must have {y.shape[-1]} components, got {self.normal}")
        return y @ jnp.asarray(n / np.linalg.norm(n))


@dataclass(frozen=True)
class Sphere:
    """A ball of ``radius`` about the tool's origin (a disc in 2D: a cylinder's section)."""

    radius: float

    def __post_init__(self):
        object.__setattr__(self, "radius", _length("Sphere", "radius", self.radius))

    def sdf(self, y):
        return _safe_norm(y) - self.radius


@dataclass(frozen=True)
class Capsule:
    """The points within ``radius`` of the segment from -half_length to +half_length along
    the tool's first axis (a stadium in 2D)."""

    half_length: float
    radius: float

    def __post_init__(self):
        object.__setattr__(self, "half_length", _length("Capsule", "half_length", self.half_length, zero=True))
        object.__setattr__(self, "radius", _length("Capsule", "radius", self.radius))

    def sdf(self, y):
        t = jnp.clip(y[..., 0], -self.half_length, self.half_length)
        return _safe_norm(y.at[..., 0].add(-t)) - self.radius


@dataclass(frozen=True)
class Box:
    """A box paddle with rounded edges: the points within ``radius`` of the box of half
    extents ``half`` (one per axis of the tool's frame) about its origin."""

    half: tuple
    radius: float = 0.0

    def __post_init__(self):
        try:
            half = np.atleast_1d(np.asarray(self.half, float))
        except (TypeError, ValueError):
            raise ValueError(f"Box.half must be the box's half extents (numbers), got {self.half!r}") from None
        if half.ndim != 1 or not np.all(np.isfinite(half)) or np.any(half < 0):
            raise ValueError(f"Box.half must be finite half extents >= 0, one per axis, got {self.half!r}")
        radius = _length("Box", "radius", self.radius, zero=True)
        if np.any(half + radius <= 0):
            raise ValueError(f"Box: a half extent of 0 needs radius > 0 (the box would have no thickness), "
                             f"got half={self.half!r}, radius={self.radius!r}")
        object.__setattr__(self, "half", tuple(float(v) for v in half))
        object.__setattr__(self, "radius", radius)

    def sdf(self, y):
        h = jnp.asarray(np.asarray(self.half, float))
        if h.shape != (y.shape[-1],):
            raise ValueError(f"Box.half must have {y.shape[-1]} components, got {self.half}")
        q = jnp.abs(y) - h
        return _safe_norm(jnp.maximum(q, 0.0)) + jnp.minimum(jnp.max(q, -1), 0.0) - self.radius


@dataclass(frozen=True)
class Arc:
    """A concave probe (a cup): the points within ``thickness`` of the circular arc of
    ``radius`` whose apex is the tool's origin and whose centre lies at -radius along the
    tool's last axis, spanning ``half_angle`` (radians) either side of that axis; its concave
    side faces -last axis (the body, for a tool placed as a paddle), so pressed in it wraps
    the tissue under it (2D)."""

    radius: float
    half_angle: float
    thickness: float

    def __post_init__(self):
        for k in ("radius", "half_angle", "thickness"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or not (np.isfinite(v) and v > 0):
                raise ValueError(f"Arc.{k} must be a positive number, got {v!r}")
        if self.half_angle >= np.pi / 2:
            raise ValueError(f"Arc.half_angle must be below pi/2 (a cup, not a ring), got {self.half_angle!r}")

    @property
    def sag(self) -> float:
        """How far the arc's ends stand below its apex along the last axis."""
        return float(self.radius * (1.0 - np.cos(self.half_angle)))

    def sdf(self, y):
        if y.shape[-1] != 2:
            raise ValueError(f"Arc is a 2D shape, got points of dimension {y.shape[-1]}")
        z = jnp.asarray(y).at[..., 1].add(self.radius)          # about the arc's centre
        phi = jnp.arctan2(z[..., 0], z[..., 1])     # from the last axis
        on_arc = jnp.abs(phi) <= self.half_angle
        ends = self.radius * jnp.array([[np.sin(self.half_angle), np.cos(self.half_angle)],
                                        [-np.sin(self.half_angle), np.cos(self.half_angle)]])
        to_end = jnp.minimum(_safe_norm(z - ends[0]), _safe_norm(z - ends[1]))
        return jnp.where(on_arc, jnp.abs(_safe_norm(z) - self.radius), to_end) - self.thickness


SHAPES = (HalfSpace, Sphere, Capsule, Box, Arc)


def rotation(theta, dim: int):
    """The rotation matrix of an angle (2D, ()) or a rotation vector (3D, (3,)); smooth at 0
    (Taylor series for small angles, so derivatives at the identity are exact)."""
    if dim == 2:
        c, s = jnp.cos(theta), jnp.sin(theta)
        return jnp.array([[c, -s], [s, c]])
    w = jnp.asarray(theta)
    t2 = jnp.sum(w * w)
    small = t2 < 1e-8
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    A = jnp.where(small, 1 - t2 / 6 + t2 * t2 / 120, jnp.sin(t) / t)
    B = jnp.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, (1 - jnp.cos(t)) / jnp.where(small, 1.0, t2))
    W = jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    return jnp.eye(3) + A * W + B * W @ W


def near_seam(shape, y, distance):
    """Whether the tool's curvature (its sdf's Hessian) jumps within ``distance`` of y (d,)
    in its frame: the Hessian at one of the 2d points ``distance`` away along the axes
    differs from y's by more than a tenth of its size (in a smooth region it changes by
    about distance / radius)."""
    H = jax.hessian(shape.sdf)
    shifts = distance * jnp.concatenate([jnp.eye(y.shape[-1]), -jnp.eye(y.shape[-1])])
    h0, hs = H(y), jax.vmap(lambda s: H(y + s))(shifts)
    size = jnp.maximum(jnp.max(jnp.abs(hs)), jnp.max(jnp.abs(h0)))
    # (a curvature that turns the normal by less than 1e-8 over ``distance`` is round-off)
    return (size * distance > 1e-8) & jnp.any(jnp.max(jnp.abs(hs - h0), axis=(1, 2)) > 0.1 * size)


def barrier(g, kappa, ghat, floor):
    """IPC's barrier b(g) (see the module docstring), continued below g_min = floor ghat by
    its second-order Taylor expansion there; 0 from ghat."""
    gm = floor * ghat

    def b(x):
        return -kappa * (x - ghat) ** 2 * jnp.log(x / ghat)

    db, d2b = jax.grad(b), jax.grad(jax.grad(b))
    inner = (g > gm) & (g < ghat)
    x = jnp.where(inner, g, 0.5 * (gm + ghat))        # a safe argument where b is not used
    below = b(gm) + db(gm) * (g - gm) + 0.5 * d2b(gm) * (g - gm) ** 2
    return jnp.where(inner, b(x), jnp.where(g <= gm, below, 0.0))


def _f0(s2, eps):
    """IPC's smoothed |s| from s^2 (C1 at s = eps, zero gradient at s = 0)."""
    pos = s2 > 0
    s = jnp.where(pos, jnp.sqrt(jnp.where(pos, s2, 1.0)), 0.0)
    return jnp.where(s < eps, -s * s2 / (3 * eps * eps) + s2 / eps + eps / 3, s)


@term
class ContactTerm(Term):
    """Barrier contact (and lagged friction) of the body's boundary points against one rigid
    tool (see the module docstring).

    idx, psi (S, K)      the contact points' neighbours and shape functions
    X (S, d)             the contact points (reference)
    w (S,)               their boundary quadrature weights
    kappa, ghat          the barrier's stiffness and range
    position0, rotation0 the tool's pose at load scale 0
    position, rotation   its pose at load scale 1: parameters
    mu                   () friction coefficient: a parameter
    pressure (S,)        lagged normal pressure: a parameter (0: frictionless)
    anchor (S, d)        lagged positions in the tool's frame: a parameter
    normal (S, d)        lagged unit normals in the tool's frame (the friction's tangent
                         planes): a parameter
    pair_id (S, K, K)    the pattern's index of each pair of a row (set by ``placed``)
    shape                the tool's shape (static)
    floor, slip          g_min / ghat and the friction's slip tolerance eps (static)
    """

    modified_newton: ClassVar[bool] = False   # the barrier's stiffness grows as a gap closes

    idx: jax.Array
    psi: jax.Array
    X: jax.Array
    w: jax.Array
    kappa: jax.Array
    ghat: jax.Array
    position0: jax.Array
    rotation0: jax.Array
    position: jax.Array
    rotation: jax.Array
    mu: jax.Array
    pressure: jax.Array
    anchor: jax.Array
    normal: jax.Array
    pair_id: jax.Array = None
    shape: object = static(None)
    floor: float = static(0.1)
    slip: float = static(1e-4)
    name: str = static("contact")

    # ---------------------------------------------------------------- geometry
    def pose(self, load):
        """(c, R) the tool's pose at load scale ``load``."""
        c = self.position0 + load * (self.position - self.position0)
        th = self.rotation0 + load * (self.rotation - self.rotation0)
        return c, rotation(th, self.X.shape[-1])

    def points(self, d):
        """The contact points' deformed positions (S, d)."""
        return self.X + jnp.einsum("sk,ski->si", self.psi, d[self.idx])

    def local(self, x, load):
        """Positions x (S, d) in the tool's frame at load scale ``load``."""
        c, R = self.pose(load)
        return (x - c) @ R

    def gaps(self, x, load):
        return self.shape.sdf(self.local(x, load))

    def _point_energy(self, x, load, pressure, anchor, n, w):
        """The energy of one contact point at x (d,)."""
        y = self.local(x[None], load)[0]
        e = w * barrier(self.shape.sdf(y), self.kappa, self.ghat, self.floor)
        v = y - anchor
        v = v - jnp.dot(n, v) * n
        return e + w * self.mu * pressure * _f0(jnp.sum(v * v), self.slip)

    def _energies(self, x, load):
        return jax.vmap(self._point_energy, in_axes=(0, None, 0, 0, 0, 0))(x, load, self.pressure, self.anchor,
                                                                           self.normal, self.w)

    def energy(self, d, load, aux=None):
        return jnp.sum(self._energies(self.points(d), load)), None

    def blocks(self, d, load, pairs: Pairs):
        x = self.points(d)
        H = jax.vmap(jax.hessian(self._point_energy), in_axes=(0, None, 0, 0, 0, 0))(
            x, load, self.pressure, self.anchor, self.normal, self.w)          # (S, d, d)
        dim = x.shape[-1]
        B = jnp.einsum("sk,sij,sm->skmij", self.psi, H, self.psi)
        return jax.ops.segment_sum(B.reshape(-1, dim, dim), self.pair_id.reshape(-1), num_segments=pairs.count)

    def results(self, d, load) -> "ContactResult":
        """The contact's forces and state at coefficients d (N, d), load scale ``load``."""
        return _compiled_results(self, d, load)

    def _results(self, d, load) -> "ContactResult":
        x = self.points(d)
        c, R = self.pose(load)
        y = (x - c) @ R
        g = self.shape.sdf(y)
        n_loc = jax.vmap(jax.grad(self.shape.sdf))(y)
        n = _unit(n_loc @ R.T)   # the tool's outward normal
        f = -jax.vmap(jax.grad(self._point_energy), in_axes=(0, None, 0, 0, 0, 0))(
            x, load, self.pressure, self.anchor, self.normal, self.w)   # force of the tool on each point
        fn = jnp.sum(f * n, 1)
        p = jnp.where(g < self.ghat, -jax.vmap(jax.grad(barrier), in_axes=(0, None, None, None))(
            g, self.kappa, self.ghat, self.floor), 0.0)
        total = jnp.sum(f, 0)
        normal = jnp.sum(fn[:, None] * n, 0)
        active = g < self.ghat
        return ContactResult(force=total, normal=normal, tangential=total - normal, point_force=f,
                             pressure=p, gap=g, active=active, points=x, normals=n, min_gap=jnp.min(g),
                             seam=active & jax.vmap(near_seam, (None, 0, None))(self.shape, y, self.ghat),
                             lag={"pressure": p, "anchor": y, "normal": _unit(n_loc)})

    # ------------------------------------------------------------- parameters
    @property
    def params(self) -> dict:
        return {"position": self.position, "rotation": self.rotation, "mu": self.mu,
                "pressure": self.pressure, "anchor": self.anchor, "normal": self.normal}

    def with_params(self, params: dict) -> "ContactTerm":
        return replace(self, **params)

    def check_params(self, value) -> dict:
        """Any of the parameters (the rest keep their values): ``position`` (d,), ``rotation``
        (2D: an angle; 3D: a rotation vector (3,)), ``mu`` (), ``pressure`` (S,), ``anchor``
        (S, d), ``normal`` (S, d; used as given: unit vectors)."""
        ref = self.params
        if not isinstance(value, Mapping) or not value or set(value) - set(ref):
            raise ValueError(f"params[{self.name!r}] must be a dict of some of " + ", ".join(
                f"{k!r} (shape {jnp.shape(v)})" for k, v in ref.items()) + f", got {value!r}")
        out = dict(ref)
        for k, v in value.items():
            try:
                v = jnp.asarray(v, jnp.float64)
            except (TypeError, ValueError):
                raise ValueError(f"params[{self.name!r}][{k!r}] must be numbers, got {v!r}") from None
            if v.shape != jnp.shape(ref[k]):
                raise ValueError(f"params[{self.name!r}][{k!r}] must have shape {jnp.shape(ref[k])}, got {v.shape}")
            if not isinstance(v, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(v))):
                raise ValueError(f"params[{self.name!r}][{k!r}] is not finite")
            out[k] = v
        return out

    # ---------------------------------------------------------------- host side
    def lists(self) -> np.ndarray:
        return np.asarray(self.idx)

    def placed(self, ids) -> "ContactTerm":
        return replace(self, pair_id=jnp.asarray(ids, jnp.int32))

    def loaded(self) -> bool:
        """Whether the tool moves with the load scale (its load-1 pose is not its load-0 one)."""
        if any(isinstance(x, jax.core.Tracer) for x in (self.position, self.rotation)):
            return True
        return bool(np.any(np.asarray(self.position) != np.asarray(self.position0))
                    or np.any(np.asarray(self.rotation) != np.asarray(self.rotation0)))


# one compiled program per tool and body: op by op, its vmapped gradients dispatched hundreds of
# small kernels per call, and a contact path checks its forces after every solve
_compiled_results = jax.jit(ContactTerm._results)


class ContactResult(NamedTuple):
    """What ``contact_forces`` returns: the tool's forces on the body and the contact state.

    force (d,)          the resultant force of the tool on the body
    normal, tangential  its parts along the points' contact normals (the sum of each point's
                        normal force) and the rest (friction)
    point_force (S, d)  each contact point's force
    pressure (S,)       the barrier's pressure -b'(g) (0 where inactive)
    gap (S,)            each point's gap g; ``min_gap`` its smallest value
    active (S,)         g < ghat (the barrier acts)
    points, normals     the points' deformed positions and the tool's outward normal there
    seam (S,)           active points within ghat of a seam of the tool's surface, where its
                        curvature jumps (a box's face meeting a rounded edge, a capsule's
                        ends): the implicit Jacobian is one-sided there (its derivative with
                        respect to the pose differs on the two sides); elsewhere, with the
                        C2 barrier, it is continuous as points enter and leave the contact
    lag                 {"pressure", "anchor", "normal"}: the lagged friction parameters for
                        the next step of a frictional path (``params={name: {**res.lag, ...}}``)"""

    force: jax.Array
    normal: jax.Array
    tangential: jax.Array
    point_force: jax.Array
    pressure: jax.Array
    gap: jax.Array
    active: jax.Array
    points: jax.Array
    normals: jax.Array
    min_gap: jax.Array
    seam: jax.Array
    lag: dict


class ContactPenetrationWarning(UserWarning):
    """A solve converged with contact points inside a tool (``min_gap < 0``): the barrier's
    pressure (``Contact.pressure``) is too low for the load, or the step too long."""


def penetration(term: "ContactTerm", d, load) -> float:
    """The smallest gap of the contact ``term``'s points at coefficients ``d`` (N, d) and load
    scale ``load`` (negative: a point inside the tool)."""
    return float(_smallest_gap(term, d, load))


# one compiled program, not one per eager operation (a converged contact solve checks it)
_smallest_gap = jax.jit(lambda term, d, load: jnp.min(term.gaps(term.points(d), load)))


def contact_forces(model, sol, name: str, params=None) -> ContactResult:
    """The contact of the tool ``name`` (a ``Contact`` term of ``model``) at the solution
    ``sol`` (solved with ``params``): forces (normal and tangential), pressure, gaps, active
    points (see ``ContactResult``)."""
    term_ = model.problem(params).term(name)
    if not isinstance(term_, ContactTerm):
        raise ValueError(f"term {name!r} is not a contact term (a {type(term_).__name__})")
    return term_.results(model.coefficients(sol), jnp.asarray(sol.load, jnp.float64))


@dataclass(frozen=True)
class Contact(TermSpec):
    """A rigid tool that the body's boundary may touch, not enter (see
    jaxrkpm.mechanics.contact): ``Contact(Sphere(0.5), position=(0, 1.6), gap=1e-3,
    pressure=1.0)``.

    shape        ``HalfSpace``, ``Sphere``, ``Capsule``, ``Box`` or ``Arc`` (in the tool's frame)
    position     (d,) the tool's origin at load scale 0 (``params``: at load scale 1)
    rotation     its rotation at load scale 0: an angle (2D) or rotation vector (3D)
    gap          ghat: the barrier's range (the contact's distance tolerance)
    pressure     p0: the barrier's pressure at half the gap (about the expected pressure)
    mu           friction coefficient (with the lagged ``pressure`` / ``anchor`` params)
    slip         the friction's slip tolerance eps (a length)
    where        X (M, d) -> (M,) bool on the contact points (the boundary quadrature
                 points): the part that may touch (default: the whole boundary)
    floor        g_min / ghat: below g_min the barrier is continued quadratically
    name         keys its parameters in ``Model.solve(params={name: {...}})``

    Accuracy: a touching point stands off the tool by less than ``gap`` (about gap/2 at
    p = p0); no point enters the tool while its pressure stays below about 20 p0 (above
    g_min = floor x gap below about 10 p0, at the default floor); ``contact_forces(...).min_gap``
    reports it. The contact points are the boundary quadrature points of the model's
    boundary rule (under SCNI: its boundary integral's, so that the patch test is exact); the
    tool's pose moves linearly with the load scale from the given pose (load 0) to the pose
    in ``params`` (load 1)."""

    shape: object
    position: tuple
    rotation: object = None
    gap: float = 1e-3
    pressure: float = 1.0
    mu: float = 0.0
    slip: float = 1e-4
    where: Callable | None = None
    floor: float = 0.1
    name: str = "contact"

    def __post_init__(self):
        if not isinstance(self.shape, SHAPES):
            raise ValueError("Contact.shape must be a HalfSpace, Sphere, Capsule, Box or Arc, got "
                             f"{type(self.shape).__name__}")
        for k in ("gap", "pressure", "slip"):
            positive(f"Contact.{k}", getattr(self, k))
        if not (isinstance(self.floor, (int, float)) and 0 < self.floor < 1):
            raise ValueError(f"Contact.floor must be in (0, 1), got {self.floor!r}")
        if not (isinstance(self.mu, (int, float, np.number)) and np.isfinite(self.mu) and self.mu >= 0):
            raise ValueError(f"Contact.mu must be a number >= 0, got {self.mu!r}")
        if self.where is not None and not callable(self.where):
            raise ValueError(f"Contact.where must be a predicate X (M, d) -> (M,) bool, got {self.where!r}")
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"Contact.name must be a non-empty string, got {self.name!r}")

    def build(self, ctx: Context) -> ContactTerm:
        body = ctx.body
        dim = body.dim
        c0 = np.asarray(self.position, float)
        if c0.shape != (dim,) or not np.all(np.isfinite(c0)):
            raise ValueError(f"contact {self.name!r}: position must be {dim} finite numbers, got {self.position!r}")
        rshape = () if dim == 2 else (3,)
        r0 = np.zeros(rshape) if self.rotation is None else np.asarray(self.rotation, float)
        if r0.shape != rshape or not np.all(np.isfinite(r0)):
            raise ValueError(f"contact {self.name!r}: rotation must be " + (
                "a finite angle (a number)" if dim == 2 else "a rotation vector (3 finite numbers)")
                + f", got {self.rotation!r}")
        rule = _contact_points(ctx, self.where, self.name)
        X, w = rule.points, rule.weights
        kappa = self.pressure / (self.gap * LN2_HALF)
        S = len(X)
        t = ContactTerm(idx=jnp.asarray(rule.idx, jnp.int32), psi=jnp.asarray(rule.psi), X=jnp.asarray(X),
                        w=jnp.asarray(w), kappa=jnp.asarray(kappa), ghat=jnp.asarray(float(self.gap)),
                        position0=jnp.asarray(c0), rotation0=jnp.asarray(r0), position=jnp.asarray(c0),
                        rotation=jnp.asarray(r0), mu=jnp.asarray(float(self.mu)), pressure=jnp.zeros(S),
                        anchor=jnp.zeros((S, dim)), normal=jnp.zeros((S, dim)), shape=self.shape,
                        floor=float(self.floor), slip=float(self.slip), name=self.name)
        g = np.asarray(t.gaps(t.X, 0.0))
        if np.any(g <= 0):
            i = int(np.argmin(g))
            raise ValueError(f"contact {self.name!r}: the tool overlaps the undeformed body at its load-0 pose "
                             f"(contact point {X[i].tolist()} at gap {g[i]:.3g}); place it clear of the body "
                             "(position=..., rotation=...) and move it in with params={name: {'position': ...}}")
        # the anchors start at the points themselves (in the tool's frame): no slip yet
        anchor = t.local(t.X, 0.0)
        return replace(t, anchor=anchor, normal=_unit(jax.vmap(jax.grad(self.shape.sdf))(anchor)))


def _contact_points(ctx: Context, where, name) -> Table:
    """The rows of the model's boundary rule (``ctx.balanced``, else its surface table) at
    which ``where`` holds; their shape functions are trimmed to the widest kept row."""
    rule = ctx.surface if ctx.balanced is None else ctx.balanced
    if where is not None:
        mask = boolean_mask(where(rule.points), f"contact {name!r}: where")
        if mask.shape != (len(rule.points),):
            raise ValueError(f"contact {name!r}: where must return ({len(rule.points)},) booleans "
                             f"(one per boundary quadrature point), got shape {mask.shape}")
        if not mask.any():
            raise ValueError(f"contact {name!r}: where selects no boundary point")
        rule = rule.subset(mask)
    keep = np.flatnonzero(np.any(rule.psi != 0, 0))
    width = int(keep.max()) + 1 if len(keep) else 1
    return Table(rule.points, rule.weights, rule.idx[:, :width], rule.psi[:, :width],
                 rule.dpsi[:, :width], rule.normals)
