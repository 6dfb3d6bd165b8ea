"""Needle-insertion target stabilisation (thesis chapter 6).

A needle pushed along x = 0.5 into the phantom of Figure 6.1 drags the target at (0.5, 0.4)
off the insertion line; a paddle holding a piece of the accessible boundary (static) or
moved by the robot (dynamic) keeps it there.

The phantom is configuration (``Phantom``): geometry, immobile edge, needle line and depth,
target, the paddle positions of Table 6.2, inclusions as stiffness fields. Each paddle
position is its own essential set, so each is its own ``Model``; the models share the
particle layout and integration table, so their problems differ only in the essential
partition and stack (zero-padded) into one batch: every paddle position x every insertion
increment runs in one compiled call (``lax.map`` or ``vmap`` over configurations of a
``scan`` over increments), optionally sharded over the visible devices.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..base.outcome import Outcome
from ..base.progress import progress_bar
from ..control.batching import BATCHING, batch_axes, default_batching, map_batch, run_batched, stack_models
from ..discretise.body import Body
from ..mechanics.loads import Springs
from ..mechanics.materials import Fung, Material
from ..mechanics.tissue import NearlyIncompressibleNeoHookean, with_barrier
from ..model.model import Model
from ..mechanics.problem import Problem
from ..solvers.implicit import point_jacobian, response, solve_path_diff
from ..solvers.path import LoadPath
from ..solvers.results import Limits, Status
from .data import INCLUSIONS, PHANTOM_OUTLINE, TABLE_6_2
from .data import NEEDLE as THESIS  # noqa: F401  (re-exported: needle.THESIS, the reference values)

# the phantoms' material laws (Phantom.material_law, Phantom3D.material_law, --material):
# the thesis' Fung; Fung with the volumetric barrier kappa/2 (ln J)^2; nearly incompressible
# neo-Hookean tissue. The tissue-like ones take Fung's small-strain shear modulus
# mu = 2 (alpha C_1212 + beta A_1212) (Table 5.2 tensors: 2 (0.5 alpha + 254 beta)).
TISSUE_LAWS = ("fung", "fung-barrier", "neo-hookean")
TISSUE_POISSON = 0.45          # soft tissue: 0.45-0.499


def fung_shear_modulus(alpha, beta):
    """Small-strain shear modulus of the thesis' Fung energy with the Table 5.2 tensors."""
    return 2.0 * (0.5 * alpha + 254.0 * beta)


def tissue_material(law: str, alpha: float, beta: float, factor=None, nu: float = TISSUE_POISSON,
                    mu: float | None = None) -> Material:
    """The material named ``law`` (one of :data:`TISSUE_LAWS`) with Fung constants ``alpha``,
    ``beta``; ``factor`` (X -> (n,)) scales every stiffness (the inclusion); "neo-hookean"
    has Poisson's ratio ``nu`` and shear modulus ``mu`` (default: Fung's); the barrier's
    bulk modulus is Fung's shear modulus."""
    if law not in TISSUE_LAWS:
        raise ValueError(f"unknown material {law!r}: choose one of {list(TISSUE_LAWS)}")
    mu = fung_shear_modulus(alpha, beta) if mu is None else float(mu)
    scaled = (lambda c: c) if factor is None else (lambda c: (lambda X: c * factor(X)))
    if law == "neo-hookean":
        return NearlyIncompressibleNeoHookean(scaled(mu), nu=nu)
    fung = Fung(alpha=scaled(alpha), beta=scaled(beta))
    if law == "fung":
        return fung
    return with_barrier(fung, kappa=scaled(fung_shear_modulus(alpha, beta)))


IMMOBILE = ("bottom", "top")


def lateral_deviation(e):
    """(..., L) lateral components -> (...): the signed component when there is one lateral
    direction (2D: the thesis' x deviation), else their length (3D)."""
    if e.shape[-1] == 1:
        return e[..., 0]
    return jnp.sqrt(jnp.sum(e * e, axis=-1)) if isinstance(e, jax.Array) else np.linalg.norm(e, axis=-1)


class NeedleTrack:
    """What the generic needle functions need of a phantom besides its models: the needle
    direction (d,) (a unit vector), the lateral basis (L, d) (orthonormal rows perpendicular
    to the needle), the target (d,) and the insertion depth. Mixed into the phantoms, which
    define ``needle_direction``, ``lateral``, ``target`` and ``insertion``."""

    def needle_at(self, depth) -> np.ndarray:
        """(d,) the needle particles' prescribed translation at insertion ``depth``."""
        return float(depth) * np.asarray(self.needle_direction, float)

    def lateral_components(self, u):
        """(..., d) target displacements -> (..., L) their components across the needle."""
        return u @ jnp.asarray(self.lateral, jnp.float64).T if isinstance(u, jax.Array) \
            else np.asarray(u) @ np.asarray(self.lateral, float).T

    def deviation_of(self, u):
        """(..., d) target displacements -> (...) lateral deviation (``lateral_deviation``)."""
        return lateral_deviation(self.lateral_components(u))

    def depths(self, increments: int) -> np.ndarray:
        """Needle depth after each of ``increments`` equal increments: (increments,), the last
        at ``insertion`` (a fractional count would step past it)."""
        if isinstance(increments, (bool, np.bool_)) or not isinstance(increments, (int, np.integer)):
            raise TypeError(f"increments must be a whole number of insertion increments, got {increments!r} "
                            f"({type(increments).__name__})")
        if increments < 1:
            raise ValueError(f"increments must be >= 1, got {increments}")
        return self.insertion * np.arange(1, increments + 1) / increments


@dataclass(frozen=True)
class Phantom(NeedleTrack):
    """The Figure 6.1 phantom: unit square with the corner x + y < 0.5 cut away, lattice
    particles at ``spacing``, the ``needle_particles`` particles on the needle line nearest
    the entry (0.5, 0) pushed along +y by ``insertion`` (15%), target (0.5, 0.4), Fung
    material of chapter 5 (Table 6.1 tensors; ``material_law`` "fung-barrier" or "neo-hookean"
    (ν = 0.45) for the tissue-like laws of :func:`tissue_material`), inclusions x
    ``stiffness_ratio``.

    ``immobile``: "bottom" (default) holds the bottom edge right of the needle entry;
    "top" holds the edge y = 1 (another reading of the figure; the text does not say which
    edge is held). Only "bottom" reproduces the thesis in kind: with "top" the unsupported
    deviation is 0.0007 (thesis 0.0307) and four of the five paddles increase it."""

    vertices: tuple = PHANTOM_OUTLINE
    spacing: float = 0.1
    immobile: str = "bottom"
    needle_x: float = 0.5
    needle_particles: int = 3
    insertion: float = 0.15
    target: tuple = (0.5, 0.4)
    paddles: tuple = TABLE_6_2
    stiffness_ratio: float = 100.0
    alpha: float = 1.0
    beta: float = 1.0
    support: float = 2.5
    integration: str = "gauss"
    material_law: str = "fung"
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        if self.material_law not in TISSUE_LAWS:
            raise ValueError(f"unknown material_law {self.material_law!r}: choose one of {list(TISSUE_LAWS)}")
        if not (np.isfinite(self.insertion) and self.insertion > 0):
            raise ValueError(f"insertion must be a positive depth, got {self.insertion}")
        if self.immobile not in IMMOBILE:
            raise ValueError(f"unknown immobile edge {self.immobile!r}: choose {list(IMMOBILE)}")
        if self.needle_particles < 1:
            raise ValueError(f"needle_particles must be >= 1, got {self.needle_particles}")
        ratio = self.stiffness_ratio
        if isinstance(ratio, (bool, np.bool_)) or not isinstance(ratio, (int, float, np.integer, np.floating)) \
                or not (np.isfinite(ratio) and ratio > 0):
            raise ValueError(f"stiffness_ratio must be a positive factor (the inclusion's stiffness over "
                             f"the phantom's), got {ratio!r}")

    @property
    def body(self) -> Body:
        """Lattice particles in the closed phantom (the thesis' nodes lie on the cut edge)."""
        if "body" not in self._cache:
            V = np.asarray(self.vertices, float)
            h = self.spacing
            lo, hi = V.min(0), V.max(0)
            n = np.round((hi - lo) / h).astype(int) + 1
            L = np.stack(np.meshgrid(lo[0] + h * np.arange(n[0]), lo[1] + h * np.arange(n[1]),
                                     indexing="ij"), -1).reshape(-1, 2)
            from ..discretise import polygons
            keep = polygons.contains(V, L) | (polygons.distance_to_boundary(V, L) <= 1e-9 * h)
            self._cache["body"] = Body.points(L[keep], V, h)
        return self._cache["body"]

    @property
    def needle_direction(self) -> np.ndarray:
        """The needle advances along +y (Figure 6.1)."""
        return np.array([0.0, 1.0])

    @property
    def lateral(self) -> np.ndarray:
        """(1, 2): the lateral deviation is the target's x displacement (section 6.3)."""
        return np.array([[1.0, 0.0]])

    @property
    def paddle_bounds(self):
        """(lower, upper) of the continuous paddle position q: the Table 6.2 chain, 1..P."""
        return 1.0, float(len(self.paddles))

    def material(self, inclusion: str = "none"):
        """``material_law`` (default the thesis' Fung, eq 6.1; see :func:`tissue_material`);
        inside the inclusion square every stiffness is x stiffness_ratio."""
        if inclusion not in INCLUSIONS:
            raise ValueError(f"unknown inclusion {inclusion!r}: choose {list(INCLUSIONS)}")
        box = INCLUSIONS[inclusion]
        if box is None:
            return tissue_material(self.material_law, self.alpha, self.beta)
        h = 0.5 * self.spacing
        (x0, x1), (y0, y1) = box
        factor = inclusion_field(((x0 - h, x1 + h), (y0 - h, y1 + h)), self.stiffness_ratio)
        return tissue_material(self.material_law, self.alpha, self.beta, factor)

    def particle(self, point) -> int:
        """The particle at ``point`` (a lattice node of the phantom)."""
        X = self.body.X
        dist = np.linalg.norm(X - np.asarray(point, float), axis=1)
        i = int(np.argmin(dist))
        if dist[i] > 0.25 * self.spacing:
            raise ValueError(f"no particle at {tuple(point)} (nearest {X[i].tolist()}); "
                             f"paddle coordinates must be nodes of the phantom's lattice")
        return i

    def sets(self, paddle: int | None) -> dict:
        """Essential sets: "wall" (immobile edge), "needle", and "paddle" (1-based index into
        ``paddles``; None for no paddle)."""
        X = self.body.X
        eps = 1e-9
        if self.immobile == "top":
            wall = np.flatnonzero(X[:, 1] > X[:, 1].max() - eps)
        else:
            wall = np.flatnonzero((X[:, 1] < X[:, 1].min() + eps) & (X[:, 0] > self.needle_x + eps))
        line = np.flatnonzero(np.abs(X[:, 0] - self.needle_x) < 1e-9)
        if len(line) < self.needle_particles:
            raise ValueError(f"only {len(line)} particles on the needle line x = {self.needle_x}")
        needle = np.sort(line[np.argsort(X[line, 1], kind="stable")[:self.needle_particles]])
        out = {"wall": wall, "needle": needle}
        if paddle is not None:
            if isinstance(paddle, (bool, np.bool_)) or not isinstance(paddle, (int, np.integer)):
                raise TypeError(f"paddle must be a 1-based int index into the {len(self.paddles)} "
                                f"paddle positions (or None), got {paddle!r}")
            if not 1 <= paddle <= len(self.paddles):
                raise ValueError(f"paddle index {paddle} out of range 1..{len(self.paddles)}")
            out["paddle"] = np.array(sorted(self.particle(p) for p in self.paddles[paddle - 1]))
        return out

    def model(self, inclusion: str = "none", paddle: int | None = None) -> Model:
        key = ("model", inclusion, paddle)
        if key not in self._cache:
            self._cache[key] = Model(self.body, self.material(inclusion), self.integration,
                                     essential=self.sets(paddle), support=self.support)
        return self._cache[key]

    def contact_face(self, paddle: int):
        """(centre (2,), outward unit normal (2,), tangent (1, 2), face half length (1,)) of
        glued paddle position ``paddle``: the segment between its two particles, where a
        contact paddle's face is placed (``jaxrkpm.thesis.contact_paddle``)."""
        self.sets(paddle)             # a clear error for a bad index
        a, b = (np.asarray(p, float) for p in self.paddles[paddle - 1])
        t = (b - a) / np.linalg.norm(b - a)
        n = np.array([t[1], -t[0]])
        centre = 0.5 * (a + b)
        from ..discretise import polygons
        if polygons.contains(np.asarray(self.vertices, float), (centre + 1e-3 * self.spacing * n)[None])[0]:
            n = -n
        return centre, n, t[None], np.array([0.5 * np.linalg.norm(b - a)])

    # ------------------------------------------------ continuous paddle (beyond the thesis)
    @property
    def paddle_chain(self) -> np.ndarray:
        """(P+1, 2) the boundary particles the Table 6.2 paddles span, in order: paddle p
        covers chain[p-1] and chain[p]."""
        chain = [self.paddles[0][0]] + [pair[1] for pair in self.paddles]
        for p, (a, b) in enumerate(self.paddles):
            if not (np.allclose(a, chain[p]) and np.allclose(b, chain[p + 1])):
                raise ValueError("the paddle positions must form a chain along the boundary "
                                 "(each starts where the previous ends) for a continuous paddle")
        return np.asarray(chain, float)

    def paddle_points(self, q):
        """(2, 2) the ends of a paddle at continuous position q in [1, P]: at an integer q
        the two particles of Table 6.2's paddle q; in between it slides along the boundary
        (its ends at chain coordinates q - 1 and q, linear between chain particles)."""
        chain = jnp.asarray(self.paddle_chain)
        n = chain.shape[0] - 1

        def at(x):
            i = jnp.clip(jnp.floor(x), 0, n - 1).astype(int)
            return chain[i] + (x - i) * (chain[i + 1] - chain[i])
        q = jnp.asarray(q, jnp.float64)
        return jnp.stack([at(q - 1.0), at(q)])

    def arc_length(self, q) -> float:
        """Distance along the boundary from the chain's first particle to the paddle centre."""
        chain = self.paddle_chain
        seg = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(chain, axis=0), axis=1))]
        return float(np.interp(q - 0.5, np.arange(len(chain)), seg))

    def spring_model(self, inclusion: str = "none", stiffness: float = 1e6) -> Model:
        """Wall and needle as essential sets; the paddle as two stiff zero-length springs at
        its ends (``paddle_points``), movable through ``model.springs_at``. With stiffness
        1e6 a paddle at an integer position holds its particles to ~1e-5 of the essential
        paddle's result (penalty error O(1/k))."""
        key = ("spring_model", inclusion, float(stiffness))
        if key not in self._cache:
            chain = self.paddle_chain
            t = np.linspace(0.0, 1.0, 41)[:, None]
            path = np.concatenate([a + t * (b - a) for a, b in zip(chain[:-1], chain[1:])])
            nb = self.body.neighbours(path, self.support * self.spacing)
            region = np.unique(nb.idx[nb.mask])
            springs = Springs(np.asarray(self.paddle_points(1.0)), stiffness, region)
            self._cache[key] = Model(self.body, self.material(inclusion), self.integration,
                                     essential=self.sets(None), support=self.support, springs=springs)
        return self._cache[key]


def inclusion_field(box, ratio: float):
    """X (Q, 2) -> (Q,): ``ratio`` inside the square box ((x0, x1), (y0, y1)), 1 outside."""
    (x0, x1), (y0, y1) = box

    def factor(X):
        X = np.asarray(X)
        inside = (X[:, 0] >= x0) & (X[:, 0] <= x1) & (X[:, 1] >= y0) & (X[:, 1] <= y1)
        return np.where(inside, ratio, 1.0)
    return factor


class Insertion(NamedTuple):
    """Per configuration and increment: target displacement (B, n, 2), solve status (B, n),
    Newton iterations (B, n), paddle Jacobian d(target)/d(paddle translation) (B, n, 2, 2)."""

    target_u: jax.Array
    status: jax.Array
    iterations: jax.Array
    jacobian: jax.Array


# a lock-step member that needs more Newton iterations than this in an increment leaves the
# lock step (``_lock_step``): converging increments take a handful
LOCK_ITERATIONS = 8
# the members that left are solved again in groups of this fraction of the batch (``_lock_step``)
STRAGGLER_GROUPS = 4


@partial(jax.jit, static_argnames=("driver", "batched", "with_jacobian", "batching", "lock_iterations"))
def _insert_batch(driver: LoadPath, prob: Problem, G, dG, lim, idx, psi, *, batched, with_jacobian, batching,
                  lock_iterations=LOCK_ITERATIONS):
    """prob: the batched problems (``batched``: which leaves carry the batch axis, see
    ``stack_models``), solved by ``driver``; G (B, n+1, Nb, d) prescribed values per increment
    (G[:, 0] the start); dG (B, m, Nb, d) the paddle directions for the Jacobian; idx, psi
    (P, K) the target's shape functions.

    ``batching``: "map" runs the configurations one after another (``lax.map``); "vmap"
    advances all of them through each increment at once, their Newton while-loops in lock
    step (``_lock_step``: a member that needs more than ``lock_iterations`` iterations or a
    step cut leaves the lock step and is solved again afterwards, so that no member holds the
    batch). Which wins depends on the device (``experiments/bench_sweep.py``):

    - CPU: "map". XLA:CPU runs the batched forms of the assembly's contractions and scatters
      slower per member than the unbatched ones. "map" solves with modified Newton
      (``Model.newton_reuse``), as the eager loop does by default, and carries each
      increment's Jacobian factorisation into the next increment's predictor (the eager loop
      makes that matrix twice).
    - GPU: "vmap" (one batched kernel per operation, native batched factorisations; see
      ``jaxrkpm.solvers.linalg.dense.one_at_a_time``, which also keeps vmapped solves from
      deadlocking XLA:CPU)."""

    def step(prob, dG, lim, carry, g1):
        u, g0, state = carry
        # ``state``: the Jacobian's factorisation at the equilibrium this increment starts
        # from, the predictor's matrix too (the eager loop, model.solve then
        # model.jacobian, makes it twice: same matrix, same results)
        sol = solve_path_diff(driver, prob, lim, u, g0, g1, jnp.float64(1.0), jnp.float64(1.0), state)
        tu = prob.point_values(idx, psi, sol.u, sol.g)[0]
        if with_jacobian:
            state = driver.linear.state_at(prob, sol.u, sol.g, sol.load)
            du = response(prob, driver.linear, sol.u, sol.g, sol.load, dG, state)
            J = point_jacobian(prob, idx, psi, sol.u, sol.g, du, dG)[0]             # (d, m)
        else:
            J = jnp.zeros((tu.shape[0], dG.shape[0]))
        return (sol.u, sol.g, state), Insertion(tu, sol.status, sol.iterations, J)

    def start(prob, G):
        u0 = jnp.zeros((prob.n_free, G.shape[-1]))
        return (u0, G[0], driver.linear.empty(prob, u0.dtype))

    if batching == "vmap":
        return _lock_step(step, start, prob, batched, G, dG, lim, lock_iterations)

    def one(prob, G, dG):
        return jax.lax.scan(partial(step, prob, dG, lim), start(prob, G), G[1:])[1]
    return Insertion(*map_batch(one, prob, batched, G, dG))


def straggler_width(members: int) -> int:
    """How many of ``members`` one group of ``_lock_step``'s stragglers holds."""
    return max(1, -(-members // STRAGGLER_GROUPS))


def _lock_step(step, start, prob, batched, G, dG, lim, lock_iterations):
    """Every member through every increment in lock step (vmap), with the results of solving
    each member alone.

    Under vmap a while loop runs until its slowest member is done (the members already done
    are frozen by a select, computed and discarded), so one member in trouble would hold the
    whole batch: a failing increment's step cuts spent tens of times the iterations of a
    converging one. So the lock step solves each increment with at most ``lock_iterations``
    Newton iterations and no step cut: a member whose increment does not converge so leaves
    (it idles through the remaining increments: zero increments, converged at once) and
    keeps its last converged state. Then the members that left are solved again from that
    state with the full limits, in groups of ``straggler_width`` members (a group's lock step
    holds only the stragglers; an increment no member of the group still needs is skipped).
    Converging increments within the cap follow the same iterates either way (the cap and
    the step cuts act only on a failing attempt), so every member's results, statuses and
    iteration counts are those of its unbatched solve."""
    B, n = G.shape[0], G.shape[1] - 1
    axes = batch_axes(prob, batched)
    vstep = jax.vmap(step, in_axes=(axes, 0, None, 0, 0))
    lock = Limits(lim.steps, jnp.minimum(lim.max_iter, lock_iterations), jnp.zeros_like(lim.max_cuts))

    def locked(c, g1):
        carry, stay = c
        g0 = carry[1]
        g1 = jnp.where(stay[:, None, None], g1, g0)           # a member that left idles
        new, out = vstep(prob, dG, lock, carry, g1)
        ok = stay & (out.status == Status.CONVERGED)
        keep = lambda a, b: jnp.where(ok.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)
        return (jax.tree.map(keep, new, carry), ok), out

    carry0 = jax.vmap(start, in_axes=(axes, 0))(prob, G)
    last, out = jax.lax.scan(locked, (carry0, jnp.ones(B, bool)), jnp.swapaxes(G[:, 1:], 0, 1))
    last = last[0]                                             # each member's last converged state
    out = Insertion(*(jnp.swapaxes(x, 0, 1) for x in out))     # (B, n, ...)
    done = jnp.sum(jnp.cumprod(out.status == Status.CONVERGED, axis=1), axis=1)   # increments before leaving

    width = straggler_width(B)
    leaves, treedef = jax.tree.flatten(prob)

    def stragglers(c):
        out, pending = c
        sel = jnp.nonzero(pending, size=width, fill_value=0)[0]
        real = jnp.arange(width) < jnp.sum(pending)
        k = done[sel]
        group = treedef.unflatten([x[sel] if b else x for x, b in zip(leaves, batched)])
        Gs = G[sel[:, None], jnp.minimum(k[:, None] + jnp.arange(n + 1), n)]   # from where each left
        idle = jax.tree.map(lambda x: jnp.zeros((width,) + x.shape[2:], x.dtype), out)

        def again(carry, i):
            active = real & (k + i < n)
            # the lanes with no increment left (or no member) idle at their state: a lane
            # solving on would hold the group as a member does
            g1 = jnp.where(active[:, None, None], Gs[:, i + 1], carry[1])
            run = lambda: vstep(group, dG[sel], lim, carry, g1)
            return jax.lax.cond(jnp.any(active), run, lambda: (carry, idle))

        _, res = jax.lax.scan(again, jax.tree.map(lambda x: x[sel], last), jnp.arange(n))
        rows = jnp.where(real, sel, B)[:, None]                 # out of range: dropped
        cols = jnp.minimum(k[:, None] + jnp.arange(n), n)
        out = jax.tree.map(lambda o, r: o.at[rows, cols].set(jnp.swapaxes(r, 0, 1), mode="drop"), out, res)
        return out, pending.at[rows[:, 0]].set(False, mode="drop")

    return jax.lax.while_loop(lambda c: jnp.any(c[1]), stragglers, (out, done < n))[0]


def insert(models: Sequence[Model], depths, point, *, jacobian_set: str | None = "paddle",
           n_devices: int | None = None, max_iter: int = 25, steps: int = 1, direction=None,
           batching: str | None = None, like: Sequence[Model] = ()) -> Insertion:
    """Insert the needle of every model through ``depths`` (n,) (or (B, n): each model's own)
    in one compiled, batched call and record the displacement of ``point`` (d,) at every
    increment; with ``jacobian_set``, also the implicit Jacobian of the point w.r.t. a rigid
    translation of that set.
    ``direction`` (d,): the needle's unit direction (default: the last coordinate axis, +y
    in 2D as in Figure 6.1; pass ``phantom.needle_direction``).
    ``batching``: "map" runs the configurations one after another on each device, "vmap"
    all at once in lock step; None (default): "map" on CPU, "vmap" elsewhere (GPU), as
    measured (see ``_insert_batch``);
    ``n_devices``: shard them over that many local devices (None: all of them, e.g. every
    GPU of the machine; ``jaxrkpm.control.batching.run_batched``). ``like``: models that set
    the padded shapes and batched leaves with them (``stack_models``: one program for a
    sweep's chunks).

    Each model keeps its other sets fixed (zero). Failed solves do not raise: their status
    is recorded and the next increment starts from the last converged state."""
    if len(models) == 0:
        raise ValueError("insert needs at least one model")
    batching = default_batching() if batching is None else batching
    if batching not in BATCHING:
        raise ValueError(f"unknown batching {batching!r}: choose one of {list(BATCHING)}")
    depths = np.asarray(depths, float)
    if depths.ndim not in (1, 2) or depths.shape[-1] == 0 or not np.all(np.isfinite(depths)):
        raise ValueError(f"depths must be a non-empty 1D array of finite needle depths (or one row per "
                         f"model), got {depths!r}")
    if depths.ndim == 2 and depths.shape[0] != len(models):
        raise ValueError(f"depths has {depths.shape[0]} rows for {len(models)} models: give one row per "
                         "model, or one 1D array for all")
    depths = np.broadcast_to(depths, (len(models), depths.shape[-1]))
    ref = models[0]
    prob, batched = stack_models(models, like)
    # one member at a time ("map"): modified Newton's branch is a branch (as in an eager
    # solve); in lock step (vmap) it would run both sides, so full Newton stays there
    driver = ref.solver(reuse=ref.newton_reuse if batching == "map" else 0.0)
    d = ref.dim
    direction = np.eye(d)[-1] if direction is None else np.asarray(direction, float)
    if direction.shape != (d,) or not np.isclose(np.linalg.norm(direction), 1.0):
        raise ValueError(f"direction must be a unit vector of shape ({d},), got {np.asarray(direction).tolist()}")
    # host arrays, built at once: per model and increment ``Model.prescribed`` (device
    # arrays, a dispatch each) took longer than the batched solve itself at thousands of models
    G = np.zeros((len(models), depths.shape[1] + 1, len(ref.sets.bnd), d))
    dG = np.zeros((len(models), d if jacobian_set else 1) + G.shape[2:])
    for b, m in enumerate(models):
        for name in ("needle",) + ((jacobian_set,) if jacobian_set else ()):
            if name not in m.sets.slices:
                raise ValueError(f"model {b} has no essential set {name!r} (its sets: {list(m.sets.names)})")
        G[b, 1:, m.sets.slices["needle"]] = depths[b][:, None, None] * direction      # the rigid needle
        if jacobian_set:
            for a in range(d):
                dG[b, a, m.sets.slices[jacobian_set], a] = 1.0                       # Model.directions
    sf = ref.shape_functions(np.atleast_2d(point), gradients=False)
    fn = partial(_insert_batch, driver, batched=batched, with_jacobian=jacobian_set is not None, batching=batching)
    lim = Limits.of(steps, max_iter)
    idx, psi = jnp.asarray(sf.idx), jnp.asarray(sf.psi)
    return run_batched(lambda pr, g, dg: fn(pr, g, dg, lim, idx, psi),
                       (prob, jnp.asarray(G), jnp.asarray(dG)), n_devices, (batch_axes(prob, batched), 0, 0))


def controllability(J, lateral=((1.0, 0.0),)) -> np.ndarray:
    """delta x_min: the paddle travel per unit lateral target correction (section 6.3.2),
    J = d target / d paddle translation (..., d, d), ``lateral`` (L, d) the orthonormal rows
    across the needle -> (...).

    The paddle move that shifts the target by a lateral e (and not along the needle) is
    J^-1 e; delta x_min is its largest length over unit lateral e, the largest singular value
    of J^-1 lateral^T. With one lateral direction (2D) that is the thesis' ||J^-1 [1 0]^T||
    (the same quantity; equal to round-off)."""
    J = np.asarray(J)
    B = np.asarray(lateral, float).T                                  # (d, L)
    M = np.linalg.solve(J, np.broadcast_to(B, J.shape[:-1] + B.shape[-1:]))
    return np.linalg.svd(M, compute_uv=False)[..., 0]


# ---------------------------------------------------------------------- sweeps
@dataclass
class StaticSweep:
    """The OPTIMAL STATIC PADDLE POSITION procedure for one inclusion case."""

    inclusion: str
    depths: np.ndarray            # (n,)
    deviation: np.ndarray         # (P, n) lateral target deviation per paddle and increment
    no_paddle: np.ndarray         # (n,)   (NeedleTrack.deviation_of: signed x in 2D, a length in 3D)
    status: np.ndarray            # (P, n)
    no_paddle_status: np.ndarray  # (n,)
    jacobian: np.ndarray          # (P, n, d, d) d target / d paddle translation
    target_u: np.ndarray          # (P, n, d) target displacement
    no_paddle_u: np.ndarray       # (n, d)
    lateral: np.ndarray           # (L, d) the phantom's lateral basis

    @property
    def final(self) -> np.ndarray:
        return self.deviation[:, -1]

    @property
    def converged_paddles(self) -> np.ndarray:
        """(P,) True where every increment of that paddle's insertion converged."""
        return np.all(self.status == Status.CONVERGED, axis=1)

    @property
    def best(self) -> int:
        """1-based paddle index with the smallest |final deviation| among the paddles whose
        insertion converged at every increment (a failed one stopped short of full depth)."""
        dev = np.where(self.converged_paddles, np.abs(self.final), np.inf)
        if not np.isfinite(dev).any():
            raise RuntimeError("no paddle position converged at every increment")
        return int(np.argmin(dev)) + 1

    @property
    def controllability(self) -> np.ndarray:
        """(P, n) delta x_min at every increment (the thesis computes it after the first)."""
        return controllability(self.jacobian, self.lateral)

    @property
    def converged(self) -> bool:
        return bool(np.all(self.status == Status.CONVERGED) and np.all(self.no_paddle_status == Status.CONVERGED))


def static_sweep(phantom: Phantom, inclusion: str = "none", increments: int = 15,
                 paddles: Sequence[int] | None = None, n_devices: int | None = None,
                 progress: bool = True) -> StaticSweep:
    """Every paddle position x every increment in one batched call, plus the no-paddle run.
    ``phantom``: a :class:`Phantom` or any phantom with the same interface (``NeedleTrack``,
    ``model(inclusion, paddle)``, ``paddles``), e.g. the 3D :class:`jaxrkpm.thesis.phantom3d.Phantom3D`.
    ``progress``: a bar of its stages on a terminal (the models, the batched insertion, the
    no-paddle run)."""
    paddles = list(range(1, len(phantom.paddles) + 1)) if paddles is None else list(paddles)
    if not paddles:
        raise ValueError(f"paddles is empty: give 1-based paddle indices in 1..{len(phantom.paddles)} "
                         "(or None for all)")
    for p in paddles:   # a clear error before anything is built (Phantom.sets checks each)
        phantom.sets(p)
    depths = phantom.depths(increments)
    direction = phantom.needle_direction
    with progress_bar(len(paddles) + 2, desc=f"static sweep ({inclusion})", unit="step", progress=progress) as bar:
        models = []
        for p in paddles:
            bar.set_postfix_str(f"model of paddle {p}")
            models.append(phantom.model(inclusion, p))
            bar.update()
        bar.set_postfix_str(f"{len(paddles)} paddles x {increments} increments, batched")
        runs = insert(models, depths, phantom.target, n_devices=n_devices, direction=direction)
        bar.update()
        bar.set_postfix_str("no paddle")
        free = insert([phantom.model(inclusion, None)], depths, phantom.target, jacobian_set=None,
                      direction=direction)
        bar.update()
    tu, fu = np.asarray(runs.target_u), np.asarray(free.target_u[0])
    return StaticSweep(inclusion, depths, phantom.deviation_of(tu), phantom.deviation_of(fu),
                       np.asarray(runs.status), np.asarray(free.status[0]), np.asarray(runs.jacobian),
                       tu, fu, np.asarray(phantom.lateral, float))


class HoldStatus(Outcome):
    """Outcome of the closed-loop paddle (``dynamic_paddle``)."""

    CONVERGED = 0, "target held on the needle line at every increment"
    NOT_HELD = 1, "the corrections did not bring the lateral deviation below tol"
    SOLVE_FAILED = 2, "a solve failed (see solve_status); the increments before it are kept"


class OptimizeStatus(Outcome):
    """Outcome of the paddle optimisation (``optimize_paddle``)."""

    CONVERGED = 0, "the deviation or the step fell below its tolerance"
    MAX_ITERATIONS = 1, "the iteration budget ran out; the best iterate is returned"
    START_FAILED = 2, "the insertion fails at the start position (see solve_status)"


@dataclass
class DynamicRun:
    """Closed loop: the paddle moves during insertion to hold the target on the needle line."""

    paddle: int
    depths: np.ndarray        # (n,)
    deviation: np.ndarray     # (n,) lateral target deviation after the correction
    uncorrected: np.ndarray   # (n,) lateral target deviation after the feed-forward move only
    paddle_u: np.ndarray      # (n, d) paddle translation
    iterations: np.ndarray    # (n,) correction solves per increment
    status: HoldStatus
    message: str
    solution: object = None   # the last converged Solution (for plots and post-processing)
    solve_status: Status = Status.CONVERGED   # of the solve that stopped the loop, if one did

    @property
    def travel(self) -> float:
        """Path length of the paddle from rest."""
        p = np.vstack([np.zeros(self.paddle_u.shape[1]), self.paddle_u])
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def cancelling_move(Jp, lateral, e) -> np.ndarray:
    """The minimum-norm paddle translation (d,) that moves the target by -e across the needle
    (e (L,) lateral components), from J = d target / d paddle translation (d, d): the
    lateral rows A = lateral J, dp = -A^T (A A^T)^-1 e (2D: the x-row of J)."""
    A = np.asarray(lateral, float) @ np.asarray(Jp)
    return -A.T @ np.linalg.solve(A @ A.T, np.asarray(e, float))


def dynamic_paddle(phantom: Phantom, paddle: int, inclusion: str = "none", increments: int = 15,
                   tol: float = 1e-6, max_corrections: int = 10, progress: bool = True) -> DynamicRun:
    """Move the paddle during insertion so the target stays on the needle line.

    Each increment: a feed-forward paddle move cancels the lateral target motion the implicit
    Jacobians predict for the needle increment (``cancelling_move``: minimum norm, from the
    lateral rows of d target/d paddle); then corrections with the Jacobian at the new
    equilibrium until |lateral deviation| < tol. A failed solve stops the loop with its
    status; what was computed is kept. Any phantom with the ``NeedleTrack`` interface.
    ``progress``: a bar of the increments on a terminal."""
    model = phantom.model(inclusion, paddle)
    target = np.atleast_2d(phantom.target)
    depths = phantom.depths(increments)
    B, direction = np.asarray(phantom.lateral, float), np.asarray(phantom.needle_direction, float)
    d = model.dim
    sol = model.initial()
    p = np.zeros(d)
    dev, pre, pu, its = [], [], [], []
    status, message, solve_status = HoldStatus.CONVERGED, HoldStatus.CONVERGED.message, Status.CONVERGED
    depth_prev = 0.0

    def solve_at(depth, p, start):
        return model.solve({"needle": phantom.needle_at(depth), "paddle": p}, initial=start, throw=False)

    def lateral_error(s):
        return B @ np.asarray(model.displacement(s, target)[0])          # (L,)

    bar = progress_bar(len(depths), desc=f"dynamic paddle {paddle} ({inclusion})", unit="increment",
                       progress=progress)
    for depth in depths:
        bar.update()
        Jp = np.asarray(model.jacobian(sol, "paddle", target))           # (d, d)
        Jn = np.asarray(model.jacobian(sol, "needle", target)) @ direction   # (d,)
        p = p + cancelling_move(Jp, B, B @ Jn * (depth - depth_prev))
        new = solve_at(depth, p, sol)
        k = 0
        if int(new.status) == Status.CONVERGED:
            e = lateral_error(new)
            pre.append(float(lateral_deviation(e)))
            while np.linalg.norm(e) >= tol and k < max_corrections:
                p = p + cancelling_move(model.jacobian(new, "paddle", target), B, e)
                new = solve_at(depth, p, new)
                k += 1
                if int(new.status) != Status.CONVERGED:
                    break
                e = lateral_error(new)
        if int(new.status) != Status.CONVERGED:
            status, message, solve_status = HoldStatus.SOLVE_FAILED, new.message, new.outcome
            break
        sol, depth_prev = new, depth
        dev.append(float(lateral_deviation(e)))
        pu.append(p.copy())
        its.append(k)
        if np.linalg.norm(e) >= tol:
            status = HoldStatus.NOT_HELD
            message = (f"|lateral deviation| {np.linalg.norm(e):.2e} >= {tol:g} after {k} corrections "
                       f"at depth {depth:.4f}")
            break
    bar.close()
    n = len(dev)
    return DynamicRun(paddle, depths[:n], np.array(dev), np.array(pre[:n]),
                      np.array(pu).reshape(n, d), np.array(its, int), status, message, sol, solve_status)


def static_state(phantom: Phantom, inclusion: str = "none", paddle: int | None = None,
                 increments: int = 15, progress: bool = True):
    """The equilibrium of one static configuration at full insertion, reached through the
    same increments as the sweep (each warm-started from the last): (model, Solution).
    A failed increment stops there; the last converged state is returned. ``progress``: a
    bar of the increments on a terminal."""
    model = phantom.model(inclusion, paddle)
    sol = model.initial()
    name = "no paddle" if paddle is None else f"paddle {paddle}"
    with progress_bar(increments, desc=f"insertion, {name} ({inclusion})", unit="increment", progress=progress) as bar:
        for depth in phantom.depths(increments):
            new = model.solve({"needle": phantom.needle_at(depth)}, initial=sol, throw=False)
            bar.update()
            if int(new.status) != Status.CONVERGED:
                break
            sol = new
    return model, sol


# ------------------------------------------------- optimised placement (beyond the thesis)
@dataclass
class PaddleOptimum:
    """The continuous paddle position q minimising the squared final lateral target
    deviation, found by optax (Adam) through the solve. q: the phantom's paddle coordinates
    (``paddle_points``): a scalar 1..P along the Table 6.2 chain in 2D, two surface
    coordinates in 3D."""

    inclusion: str
    q: float | np.ndarray       # optimum
    deviation: float            # final lateral deviation there
    history: np.ndarray         # (iterations, 2k + 1): q (k), deviation, d(deviation^2)/dq (k)
    rejected: int               # steps whose insertion failed (det F <= 0 ...), undone and shortened
    status: OptimizeStatus
    message: str
    solve_status: Status = Status.CONVERGED   # of the start position's insertion

    @property
    def start_deviation(self) -> float:
        """The final lateral deviation at the start position (the first iterate)."""
        return float(self.history[0, (self.history.shape[1] - 1) // 2]) if len(self.history) else np.nan


def spring_insertion(model: Model, phantom: Phantom, q, depths):
    """Insert the needle through ``depths`` with the spring paddle at position q, each
    increment warm-started from the last: (last Solution, lateral target deviation per
    increment, status). A failed increment stops there (the last converged state is returned)."""
    springs = {"springs": model.springs_at(phantom.paddle_points(q))}
    target = np.atleast_2d(phantom.target)
    sol, dev = model.initial(), []
    for depth in depths:
        new = model.solve({"needle": phantom.needle_at(depth)}, params=springs, initial=sol, throw=False)
        if int(new.status) != Status.CONVERGED:
            return sol, np.array(dev), new.outcome
        sol = new
        dev.append(float(phantom.deviation_of(model.displacement(sol, target)[0])))
    return sol, np.array(dev), Status.CONVERGED


def final_deviation_and_gradient(model: Model, phantom: Phantom, q, depths):
    """(lateral deviation at full insertion, d(deviation)/dq (the shape of q), status): the
    insertion path selects the equilibrium; the derivative is the implicit one at the final
    state (the solve is differentiable in the spring points)."""
    sol, dev, status = spring_insertion(model, phantom, q, depths[:-1])
    if status != Status.CONVERGED:
        return np.nan, np.full(np.shape(q), np.nan) if np.ndim(q) else np.nan, status
    sf = model.shape_functions(np.atleast_2d(phantom.target), gradients=False)
    idx, psi = jnp.asarray(sf.idx), jnp.asarray(sf.psi)

    def final(q):
        s = model.solve({"needle": phantom.needle_at(depths[-1])}, initial=sol, throw=False,
                        params={"springs": model.springs_at(phantom.paddle_points(q))})
        return phantom.deviation_of(model.constraint.point_values(idx, psi, s.u, s.g)[0]), s.status

    (d, st), g = jax.value_and_grad(final, has_aux=True)(jnp.asarray(q, jnp.float64))
    return float(d), (np.asarray(g) if np.ndim(q) else float(g)), Status.of(st)


def optimize_paddle(phantom: Phantom, inclusion: str = "none", start=None,
                    increments: int = 15, iterations: int = 30, learning_rate: float = 0.1,
                    decay: float = 0.9, stiffness: float = 1e6, tol: float = 1e-7,
                    step_tol: float = 1e-4, progress: bool = True) -> PaddleOptimum:
    """Adam on the paddle coordinates q within ``phantom.paddle_bounds`` for min
    deviation(q)^2 at full insertion, from ``start`` (default: the middle of the bounds),
    the learning rate decaying by ``decay`` per iteration (plain Adam circles a minimum at a
    fixed step). A step into a position whose insertion fails (the material inverts near the
    needle tip) is undone and the steps halved: the optimum may sit on that feasibility
    edge. Stops when |deviation| < tol, a step is below ``step_tol`` (largest coordinate),
    or after ``iterations``; returns the best iterate. ``progress``: a bar of the
    iterations on a terminal."""
    import optax
    lo, hi = (np.asarray(b, float) for b in phantom.paddle_bounds)
    q = 0.5 * (lo + hi) if start is None else np.asarray(start, float)
    if q.shape != lo.shape or not np.all(np.isfinite(q)):
        raise ValueError(f"start must be {lo.size} finite paddle coordinate(s) of shape {lo.shape}, "
                         f"got {np.asarray(start).tolist()}")
    model = phantom.spring_model(inclusion, stiffness)
    depths = phantom.depths(increments)
    opt = optax.adam(optax.exponential_decay(learning_rate, transition_steps=1, decay_rate=decay))
    state = opt.init(jnp.asarray(q))
    d, g, st = final_deviation_and_gradient(model, phantom, q, depths)
    k = q.size
    if st != Status.CONVERGED:
        return PaddleOptimum(inclusion, _coordinates(q), np.nan, np.zeros((0, 2 * k + 1)),
                             0, OptimizeStatus.START_FAILED,
                             f"the insertion fails at the start position q = {q.tolist()} ({st.name})", st)

    def row(q, d, g):
        return [*np.ravel(q), d, *np.ravel(2 * d * np.asarray(g))]

    hist, rejected, scale = [row(q, d, g)], 0, 1.0
    status, message = OptimizeStatus.MAX_ITERATIONS, f"{iterations} iterations"
    bar = progress_bar(iterations, desc=f"optimize paddle ({inclusion})", unit="iteration", progress=progress)
    for _ in range(iterations):
        bar.update()
        bar.set_postfix(deviation=f"{d:.2e}")
        if abs(d) < tol:
            status, message = OptimizeStatus.CONVERGED, f"|deviation| < {tol:g}"
            break
        upd, new_state = opt.update(jnp.asarray(2 * d * np.asarray(g)), state)
        q_new = np.clip(q + scale * np.asarray(upd), lo, hi)
        if np.max(np.abs(q_new - q)) < step_tol:
            status, message = OptimizeStatus.CONVERGED, f"step below {step_tol:g}"
            break
        d_new, g_new, st = final_deviation_and_gradient(model, phantom, q_new, depths)
        if st != Status.CONVERGED:
            rejected += 1
            scale *= 0.5          # stay on the feasible side: undo, shorten the steps
            continue
        q, d, g, state = q_new, d_new, g_new, new_state
        hist.append(row(q, d, g))
    bar.close()
    hist = np.array(hist)
    best = int(np.argmin(np.abs(hist[:, k])))
    if rejected:
        message += f"; {rejected} steps into infeasible positions (insertion fails) undone"
    return PaddleOptimum(inclusion, _coordinates(hist[best, :k].reshape(lo.shape)), float(hist[best, k]),
                         hist, rejected, status, message)


def _coordinates(q):
    """A scalar paddle coordinate as a float, several as an array."""
    q = np.asarray(q, float)
    return float(q) if q.ndim == 0 else q
