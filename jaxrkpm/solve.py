"""The discrete problem inside jit, and the Newton solver.

Inside jit there is only gather -> F -> E -> W -> scatter: all geometry arrives in
``Ops`` (built once by ``Model``). Unknowns are the free RK coefficients u_f (Nf, d);
prescribed values g (Nb, d) and the load scale are explicit, differentiable inputs.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .linear import DenseSolver, Stability, dense_tangent, lowest_modes
from .refinement import preconditioned_cg
from .materials import det, green_lagrange
from .outcome import Outcome


class Status(Outcome):
    """Outcome of a solve (an int code inside jit; ``Status.of(sol.status)`` outside)."""

    CONVERGED = 0, "converged"
    MAX_ITERATIONS = 1, ("Newton reached its iteration cap on the smallest load step allowed "
                         "(or once the failed attempts had spent their work budget)")
    NONFINITE = 2, ("non-finite residual or energy (NaN/inf) on the smallest load step allowed "
                    "(or once the failed attempts had spent their work budget)")
    INVERTED = 3, ("a step would invert the material (det F <= 0 at an integration point) "
                   "even on the smallest load step allowed (or once the failed attempts had "
                   "spent their work budget)")
    LINE_SEARCH = 4, ("the line search found no decrease of energy or residual "
                      "on the smallest load step allowed (or once the failed attempts had "
                      "spent their work budget)")
    UNSTABLE_TANGENT = 5, ("the tangent K_ff is not positive definite at the equilibrium "
                           "reached (loss of stability: a limit or bifurcation point, buckling "
                           "or loss of ellipticity passed), even on the smallest load step "
                           "allowed (or once the failed attempts had spent their work budget); "
                           "the path is stopped at the last stable state (solve with "
                           "check_stability=False to follow the unstable branch)")
    STABILITY_UNKNOWN = 6, ("converged, but the factorisation could not tell whether K_ff is "
                            "positive definite (perturbed or permuted pivots): the state may lie "
                            "past a critical point")
    LINEAR_SOLVE = 7, ("the iterative linear solver (solver='krylov') did not converge on the "
                       "smallest load step allowed (or once the failed attempts had spent their "
                       "work budget)")

    @property
    def equilibrium(self) -> bool:
        """An equilibrium was reached (converged, whatever the stability check said)."""
        return self in (Status.CONVERGED, Status.STABILITY_UNKNOWN)


def reached_equilibrium(status):
    """Inside jit: the status code(s) of an equilibrium (CONVERGED or STABILITY_UNKNOWN)."""
    return (status == Status.CONVERGED) | (status == Status.STABILITY_UNKNOWN)


class Ops(NamedTuple):
    """Geometry and topology as arrays (no Python objects), passed into jit."""

    idx: jax.Array      # (Q, K) neighbour particles of each integration point
    dpsi: jax.Array     # (Q, K, d) shape function gradients
    w: jax.Array        # (Q,) integration weights
    free: jax.Array     # (Nf,) free particle indices
    bnd: jax.Array      # (Nb,) essential particle indices
    Dbinv: jax.Array    # (Nb, Nb) (D^b)^-1
    nb_idx: jax.Array   # (Nb, Kb) neighbours of the essential particles
    nb_psi: jax.Array   # (Nb, Kb) Psi_J(X_b), zero for essential J
    f_ext: jax.Array    # (N, d) nodal dead load at load scale 1
    pair_id: jax.Array  # (G, K, K) index of the particle pair (idx[q,k], idx[q,m]) for the q of group G
    pair_i: jax.Array   # (P,) first particle of each pair
    pair_j: jax.Array   # (P,)
    pair_t: jax.Array   # (P,) index of the transposed pair (pair_j, pair_i)
    elim: Any           # jaxrkpm.linear.Elimination: (D^b)^-1 D^nb by boundary component
    spacing: jax.Array  # () particle spacing
    groups: jax.Array   # (G, S) integration points sharing one neighbour list (padded with Q)
    sp_idx: jax.Array   # (S, Ks) particles whose shape functions may reach each spring point
    sp_pair: jax.Array  # (S, Ks, Ks) index of the particle pair (sp_idx[s,k], sp_idx[s,m])


class Params(NamedTuple):
    point: dict   # name -> (Q,) values at the integration points
    tensors: dict  # name -> global arrays (e.g. Fung's A and C)
    springs: dict  # "psi" (S, Ks) shape functions at the spring points, "k" (S,) stiffnesses


@dataclass(frozen=True)
class Config:
    """Static solver settings (immutable and hashable: part of the jit cache key).

    ``Model.config(**overrides)`` gives a model's; every field may be overridden per solve
    (``model.solve(..., rtol=1e-12)``)."""

    W: Callable                   # strain energy W(E, params)
    linear: Any                   # jaxrkpm.linear.DenseSolver() or SparseSolver(system)
    rtol: float = 1e-10           # residual tolerance relative to the internal force scale
    line_search: int = 8          # step halvings in the line search
    armijo: float = 1e-4          # sufficient-decrease constant of the energy line search
    easy: int = 4                 # a load step converging within this many iterations lets dt grow
    growth: float = 1.5           # ... by this factor (never above the initial step)
    check_stability: bool = True  # an equilibrium with K_ff not positive definite -> UNSTABLE_TANGENT
    #                               (False also lets iterative linear solves stop early)
    stable_branch: bool = False   # past a critical point, go on to a stable equilibrium of the same
    #                               load (see ``switch_branch``); dense solver and check_stability only.
    #                               Off in Config: it makes every dense solve_path compile ~70% longer
    #                               (9x9: 6.2 -> 10.7 s CPU); ``Model.solve`` switches it on by
    #                               itself where a plain solve stops at a critical point. The compressed Fung / Quadratic squares
    #                               stop with or without it: past their last stable state the energy
    #                               has no minimum with det F > 0 (a corner collapses; see ``descend``)
    locate: int = 6               # halvings of the initial load step that pin a critical point
    #                               before the branch switch (it lies within dt0 / 2**locate)
    reuse: float = 0.0            # modified Newton (``newton``): 0 assembles and factorises the
    #                               tangent at every iteration; in (0, 1) a kept factorisation
    #                               serves the next iteration (the next load step's predictor
    #                               too) while the last step cut |r| by at least this factor.
    #                               Same residual tolerance; assembly dominates 3D solves.
    #                               Dense solver only (ignored by the sparse one)

    def __post_init__(self):
        if not callable(self.W):
            raise ValueError("Config.W must be the material's strain energy W(E, params)")
        for name in ("rtol", "armijo", "growth"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if int(self.line_search) < 0 or int(self.easy) < 0 or int(self.locate) < 0:
            raise ValueError("line_search, easy and locate must be >= 0")
        if not (isinstance(self.reuse, (int, float)) and 0 <= self.reuse < 1):
            raise ValueError(f"reuse must be a number in [0, 1) (0: full Newton), got {self.reuse!r}")


MAX_STEPS = 1000   # initial load steps of one solve (Limits.of)
MAX_ITER = 1000    # Newton iterations per load step
MAX_CUTS = 50      # halvings of the load step (2**-50 of the increment: below round-off)
FAILED_WORK = 2    # Newton iterations of failed attempts allowed per iteration of useful work (solve_path)


class Limits(NamedTuple):
    """Dynamic solver limits (arrays, so changing them does not recompile)."""

    steps: jax.Array      # initial (and largest) number of load steps
    max_iter: jax.Array   # Newton iterations per load step
    max_cuts: jax.Array   # halvings of the initial load step before giving up

    @staticmethod
    def of(steps=1, max_iter=25, max_cuts=10) -> "Limits":
        """Validated limits: 1 <= steps <= MAX_STEPS, 1 <= max_iter <= MAX_ITER,
        0 <= max_cuts <= MAX_CUTS (each step costs an assembly and a factorisation, so a
        bigger count only buys minutes of run time; the adaptive stepping refines where
        needed)."""
        for name, v, lo, hi in (("steps", steps, 1, MAX_STEPS), ("max_iter", max_iter, 1, MAX_ITER),
                                ("max_cuts", max_cuts, 0, MAX_CUTS)):
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
                raise TypeError(f"{name} must be an int, got {v!r}")
            if not lo <= int(v) <= hi:
                raise ValueError(f"{name} must lie in {lo}..{hi}, got {v}")
        return Limits(jnp.asarray(int(steps)), jnp.asarray(int(max_iter)), jnp.asarray(int(max_cuts)))


MAX_CRITICAL = 8    # critical points one solve records (more are counted in Solution.branch)
CRITICAL_EIGS = 3   # lowest eigenvalues of K_ff recorded at each


class Critical(NamedTuple):
    """Critical points a solve passed (the first ``MAX_CRITICAL``; NaN where unfilled).

    The tangent K_ff lost positive definiteness between the load fractions ``t_stable`` (the
    last stable equilibrium) and ``t_unstable`` (the first equilibrium on the path with a
    negative eigenvalue; ``t_unstable - t_stable`` <= dt0 / 2**Config.locate); ``eigenvalues``
    (K, CRITICAL_EIGS) the lowest eigenvalues of K_ff there, ``mode`` (K, Nf, d) the critical
    mode (unit norm) along which the solve left the unstable branch."""

    t_stable: jax.Array      # (K,)
    t_unstable: jax.Array    # (K,)
    eigenvalues: jax.Array   # (K, CRITICAL_EIGS)
    mode: jax.Array          # (K, Nf, d)

    @staticmethod
    def empty(u) -> "Critical":
        nan = jnp.full((MAX_CRITICAL,), jnp.nan, u.dtype)
        return Critical(nan, nan, jnp.full((MAX_CRITICAL, CRITICAL_EIGS), jnp.nan, u.dtype),
                        jnp.full((MAX_CRITICAL,) + u.shape, jnp.nan, u.dtype))

    def record(self, k, when, t_stable, t_unstable, eigenvalues, mode) -> "Critical":
        """With entry k set where ``when`` (k >= MAX_CRITICAL: dropped)."""
        def put(a, v):
            return jnp.where(when, a.at[k].set(v, mode="drop"), a)
        return Critical(put(self.t_stable, t_stable), put(self.t_unstable, t_unstable),
                        put(self.eigenvalues, eigenvalues), put(self.mode, mode))


class Solution(NamedTuple):
    """A solve's result (a pytree: batched solves stack every field).

    u (Nf, d) free coefficients at the last converged load; g (Nb, d) prescribed values and
    ``load`` the load scale there; ``t`` the fraction of the requested increment reached;
    ``status`` a Status code. ``branch`` counts the critical points this solve passed by
    switching to a stable branch (0: the state lies on the branch the solve started on;
    CONVERGED with branch > 0: a stable state of a secondary, bifurcated branch) and
    ``critical`` records them (see ``Critical``)."""

    u: jax.Array
    g: jax.Array
    load: jax.Array
    status: jax.Array
    t: jax.Array
    iterations: jax.Array
    steps: jax.Array
    cuts: jax.Array
    residual_norm: jax.Array
    branch: jax.Array     # () critical points passed by switching to a stable branch (0: primary)
    critical: "Critical"  # the critical points this solve passed (fixed size, NaN where unfilled)

    @property
    def converged(self) -> bool:
        """Every solve reached an equilibrium (CONVERGED, or STABILITY_UNKNOWN)."""
        st = np.asarray(self.status)
        return bool(np.all((st == Status.CONVERGED) | (st == Status.STABILITY_UNKNOWN)))

    @property
    def outcome(self) -> Status:
        """The status as a Status member (prints as its name); one solve only."""
        return Status.of(self.status)

    @property
    def message(self) -> str:
        st = np.asarray(self.status)
        if st.ndim:
            bad = np.flatnonzero(st != 0)
            if not len(bad):
                return f"all {st.size} solves converged"
            return (f"{len(bad)} of {st.size} solves did not converge; first (#{bad[0]}): "
                    + Status.of(st.flat[bad[0]]).message)
        s = Status.of(st)
        if s == Status.CONVERGED:
            where = ""
            if int(self.branch):
                t = np.asarray(self.critical.t_unstable)
                where = (f" on a stable secondary branch, past {int(self.branch)} critical point(s) "
                         f"(first at {100 * t[0]:.2f}% of the increment)")
            return (f"converged{where} in {int(self.steps)} load steps, {int(self.iterations)} Newton "
                    f"iterations (|r| = {float(self.residual_norm):.2e})")
        if s == Status.STABILITY_UNKNOWN:
            return (f"{s.name}: {s.message} (after {int(self.steps)} load steps, "
                    f"{int(self.iterations)} Newton iterations)")
        return (f"{s.name}: {s.message}; stopped at {100 * float(self.t):.1f}% of the increment "
                f"after {int(self.steps)} steps and {int(self.cuts)} step cuts; the last converged "
                f"state is kept")


# ------------------------------------------------------------------------ discrete model
def coefficients(ops: Ops, u, g):
    """Full RK coefficients (N, d): free ones from u, essential ones by eq 3.22."""
    N, dim = ops.f_ext.shape
    # the free and the essential particles are distinct: said, so that the derivatives of
    # these scatters are plain gathers (JAX otherwise tracks which of the duplicates won
    # with an integer scatter and gather of its own: 6 more kernels in every residual)
    d = jnp.zeros((N, dim), u.dtype).at[ops.free].set(u, unique_indices=True)
    s = jnp.einsum("bk,bki->bi", ops.nb_psi, d[ops.nb_idx])
    return d.at[ops.bnd].set(ops.Dbinv @ (g - s), unique_indices=True)


def deformation_gradients(idx, dpsi, d):
    """F = I + sum_K d_K (x) grad Psi_K at each point: (Q, d, d)."""
    return jnp.eye(d.shape[1]) + jnp.einsum("qkj,qki->qij", dpsi, d[idx])


def _point_energy(W):
    def psi(F, p):
        return W(green_lagrange(F), p)
    return psi


def _merged(params: Params):
    return {**params.point, **params.tensors}, {**{k: 0 for k in params.point},
                                                 **{k: None for k in params.tensors}}


def spring_energy(ops: Ops, params: Params, d):
    """Zero-length springs that hold material points to their reference positions:
    1/2 sum_s k_s |u(X_s)|^2 with u(X_s) = sum_K Psi_K(X_s) d_K (an elastic support, or a
    penalty paddle whose points X_s may move: they enter only through params.springs)."""
    sp = params.springs
    u = jnp.einsum("sk,ski->si", sp["psi"], d[ops.sp_idx])
    return 0.5 * jnp.sum(sp["k"][:, None] * u * u)


def by_group(ops: Ops, x):
    """Per-point values x (Q, ...) laid out by integration-point group (G, S, ...); the
    padding slots (index Q) hold zeros."""
    return jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])[ops.groups]


def _group_params(ops: Ops, params: Params):
    """The material parameters by group (padding slots: the first point's values, so W
    stays finite there; their weight is zero) and their vmap axes."""
    p, axes = _merged(params)
    slot = jnp.minimum(ops.groups, ops.w.shape[0] - 1)
    return {k: v[slot] if axes[k] == 0 else v for k, v in p.items()}, axes


def group_gradients(ops: Ops, d):
    """F at the integration points by group: (G, S, d, d), F = I in the padding slots.

    The points of a group share one neighbour list, so the coefficients are gathered once
    per group, and the residual's transpose (the scatter back onto the particles) sums a
    group's points before it scatters: at the 10^3 Gauss cube (8 points a cell) the energy
    with its gradient took ~3x less time than point by point (same run, interleaved)."""
    rep = ops.idx[ops.groups[:, 0]]                    # (G, K): the group's neighbour list
    return jnp.eye(d.shape[1]) + jnp.einsum("gskj,gki->gsij", by_group(ops, ops.dpsi), d[rep])


def _per_group(f, axes):
    """f(F, p) of one point, mapped over (G, S) points."""
    return jax.vmap(jax.vmap(f, in_axes=(0, axes)), in_axes=(0, axes))


def _group_sum_scatter(ops: Ops, contrib, like):
    """sum over a group's points of contrib (G, S, K, d), scattered onto the particles of
    the group's neighbour list: (N, d)."""
    rep = ops.idx[ops.groups[:, 0]]
    return jnp.zeros_like(like).at[rep].add(contrib.sum(1))


def energy_full(ops: Ops, params: Params, W, d, load, dF=0.0):
    """Total potential energy in the full coefficients; aux: min det F.

    ``dF`` (G, S, d, d), added to F at the integration points by group, is zero in value: the
    energy's gradient with respect to it is the stress w P there (``energy_residual_stress``), which
    the backward pass of the residual computes anyway."""
    F = group_gradients(ops, d) + dF
    p, axes = _group_params(ops, params)
    Wq = _per_group(_point_energy(W), axes)(F, p)
    det_F = jnp.where(ops.groups < ops.w.shape[0], det(F), jnp.inf)   # padding: not a point
    return (jnp.sum(by_group(ops, ops.w) * Wq) + spring_energy(ops, params, d) - load * jnp.sum(ops.f_ext * d),
            jnp.min(det_F))


def energy(ops, params, W, u, g, load, dF=0.0):
    return energy_full(ops, params, W, coefficients(ops, u, g), load, dF)


def residual(ops, params, W, u, g, load):
    """r_f = dPi/du_f (Nf, d)."""
    return jax.grad(lambda v: energy(ops, params, W, v, g, load)[0])(u)


def energy_residual_stress(ops, params, W, u, g, load):
    """(Pi, min det F, r_f, w P) in one pass: the energy, its gradient and the weighted first
    Piola stress at the integration points by group (G, S, d, d), the gradient with respect
    to ``energy_full``'s dF (so the force scale needs no second pass through the material:
    at the 9x9 box that pass cost ~2x the residual)."""
    (Pi, det_min), (r, wP) = jax.value_and_grad(lambda x, e: energy(ops, params, W, x, g, load, e),
                                                argnums=(0, 1), has_aux=True)(u, zero_stress(ops, u))
    return Pi, det_min, r, wP


def zero_stress(ops: Ops, u):
    """Zeros of the shape of the stress by group (G, S, d, d), in u's dtype."""
    return jnp.zeros(ops.groups.shape + (u.shape[-1],) * 2, u.dtype)


def _weighted(ops: Ops, X):
    """w X for per-point (G, S, ...) tensors X (zero in the padding slots)."""
    return by_group(ops, ops.w).reshape(ops.groups.shape + (1,) * (X.ndim - 2)) * X


def _scatter_norm(ops: Ops, wX):
    """|| sum_q |grad Psi| |w X| || for weighted per-point (G, S, d, d) tensors w X: the size of
    the terms summed onto the particles."""
    contrib = jnp.einsum("gskj,gsij->gski", jnp.abs(by_group(ops, ops.dpsi)), jnp.abs(wX))
    return jnp.linalg.norm(_group_sum_scatter(ops, contrib, jnp.zeros(ops.f_ext.shape, wX.dtype)))


def stress_force_scale(ops, wP):
    """|| sum_q |grad Psi| |w P| || + |f_ext| from the weighted stress w P (G, S, d, d): the
    size of the terms summed into the residual."""
    return _scatter_norm(ops, wP) + jnp.linalg.norm(ops.f_ext)


ROUNDOFF_FACTOR = 100.0   # the convergence floor in units of eps x stiffness scale (see force_scales);
#                           the round-off actually left in |r| is ~0.05-0.5 of one unit


def force_scales(ops, params, W, d):
    """(``stress_force_scale``, round-off floor) at d from one pass (a jvp of the stress
    along F gives P and dP/dF : F together; two passes cost ~2x, measured at the 9x9 box).

    The floor is the residual norm below which |r| carries no information: ROUNDOFF_FACTOR x
    machine epsilon x || sum_q w |grad Psi| |dP/dF : F| ||, the force that rounding the strain
    E = (F^T F - I)/2 to machine precision produces (dP/dF : F is the stress change of a unit
    relative stretch: a stiffness). Without it, a tiny load step (steps=10**6, or a 1e-9
    prescribed displacement) asks for |r| <= rtol x (a tiny force) and never converges."""
    F = group_gradients(ops, d)
    p, axes = _group_params(ops, params)

    def stress_and_stiffness(F, p):
        return jax.jvp(lambda G: jax.grad(_point_energy(W))(G, p), (F,), (F,))

    P, dP = _per_group(stress_and_stiffness, axes)(F, p)
    eps = jnp.finfo(d.dtype).eps
    return stress_force_scale(ops, _weighted(ops, P)), ROUNDOFF_FACTOR * eps * _scatter_norm(ops, _weighted(ops, dP))


# doubles of (chunk, K, K, d, d) local tangent blocks held at once by pair_blocks (public: a
# test sweeps a small table in several windows by lowering it). Small enough that a chunk's
# blocks stay in cache between the GEMM that writes them and the scatter that sums them
# (2 MB): at the 10^3 cube (K = 64, 7 groups a chunk) the pair blocks took 2-5x less time
# than with the whole table at once (2^25; same run, interleaved, load average 7)
BLOCK_BUDGET = 2**18
# neighbours per part of a group's list when only one triangle of its (K, K) blocks is
# computed (public: a test sets it beyond K to compare with the whole square). A group's
# blocks are symmetric, K_mk = K_km^T, so of the parts' (a, b) products only a <= b are
# formed: with K = 64 in 4 parts, 10 of 16, and the transposes come from one gather over
# the pairs. Measured at the 20^3 cube (K = 64, same run, quiet): 1.36-1.40 -> 1.00-1.09 s
# (2 parts: 1.14-1.25 s; 8 parts: 1.00-1.12 s)
HALF_PART = 16


def material_tangent(W, F, p, axes):
    """dP/dF at every point, (Q, d, d, d, d) with [q, i, j, k, l] = dP_ij / dF_kl: the stress
    linearised once and applied to the d^2 unit directions. jax.hessian of the point energy
    (the same numbers) vmaps those directions into (Q, d^2, ...) arrays that XLA:CPU pads
    and copies: measured at 54,872 points (20^3 cube), 270 ms against 117 ms."""
    stress = jax.vmap(jax.grad(_point_energy(W)), in_axes=(0, axes))
    _, lin = jax.linearize(lambda G: stress(G, p), F)
    dim = F.shape[-1]
    unit = jnp.eye(dim * dim, dtype=F.dtype).reshape(dim * dim, dim, dim)
    return jnp.stack([lin(jnp.broadcast_to(e, F.shape)) for e in unit], -1).reshape(F.shape + (dim, dim))


def pair_blocks(ops, params, W, d):
    """Tangent in the full coefficients as (P, d, d) blocks over the particle pairs:
    K_IJ = sum_q w_q grad Psi_I . dP/dF . grad Psi_J (dP/dF by autodiff of W).

    Integration points with the same neighbour list (the Gauss points of one background
    cell) are summed together as one batched matrix product before the scatter into the
    pair sums, so the scatter runs once per group, not once per point. Large tables are
    swept in chunks of groups (a scan that accumulates the pair sums) so the (G, K, K, d, d)
    local blocks never exist all at once. Long lists (K >= 2 HALF_PART) form one triangle
    of each group's blocks: the pair sums U then hold each pair's blocks in one of its two
    orders, and K_IJ = U_IJ + U_JI^T (I != J)."""
    F = deformation_gradients(ops.idx, ops.dpsi, d)
    p, axes = _merged(params)
    C = material_tangent(W, F, p, axes)   # (Q, d, d, d, d)
    Q, K, dim = ops.dpsi.shape
    n_pairs = ops.pair_i.shape[0]
    G = ops.groups.shape[0]
    n_parts = max(1, K // HALF_PART)
    half = n_parts >= 2
    cut = np.linspace(0, K, n_parts + 1).astype(int)
    parts = [slice(a, b) for a, b in zip(cut[:-1], cut[1:])]
    # within a diagonal product (a, a) both orders of a pair are formed: the (m, k), m > k,
    # are sent past the last pair (a scatter drops them)
    below = np.tril(np.ones((K, K), bool), -1)

    def ext(x):  # index Q is the padding of the groups: a zero row
        return jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])

    wdpsi, C, dpsi = ext(ops.dpsi * ops.w[:, None, None]), ext(C), ext(ops.dpsi)

    def chunk_sum(acc, grp, pid):
        # K_km[a, b] = sum_(s, l) Y[(s, l), (k, a, b)] dpsi[s, m, l] with Y = w dpsi . C: one
        # batched GEMM per group and pair of parts, laid out (group, m, (k, a, b)) so that
        # its output rows are already the (d, d) blocks of the pairs (k, m) (pid transposed
        # to match); summed into acc in place (a scatter-add into the carried sums)
        c, s = grp.shape
        Y = jnp.einsum("cskj,csajbl->cslkab", wdpsi[grp], C[grp]).reshape(c, s * dim, K, dim * dim)
        B = dpsi[grp].transpose(0, 1, 3, 2).reshape(c, s * dim, K)
        pid = pid.transpose(0, 2, 1)
        blocks, ids = [], []
        for a, rows in enumerate(parts):
            for cols in parts[a:]:
                blocks.append(jnp.einsum("cxm,cxn->cmn", B[:, :, rows], Y[:, :, cols].reshape(c, s * dim, -1)))
                ij = pid[:, rows, cols]
                if half and rows == cols:
                    ij = jnp.where(below[rows, cols], n_pairs, ij)
                ids.append(ij.reshape(-1))
        blocks = jnp.concatenate([b.reshape(-1, dim, dim) for b in blocks])
        return acc + jax.ops.segment_sum(blocks, jnp.concatenate(ids), num_segments=n_pairs)

    zero = jnp.zeros((n_pairs, dim, dim), d.dtype)
    # windows of equal size: with ``chunk`` groups each the last window, shifted back to end
    # at G, recomputed up to a whole window of groups already summed (the needle phantom,
    # G = 106 in windows of 104: 1.86 ms against 0.80 ms in two windows of 53)
    windows = -(-G // max(1, BLOCK_BUDGET // (K * K * dim * dim)))
    chunk = -(-G // windows)
    if windows == 1:
        U = chunk_sum(zero, ops.groups, ops.pair_id)
    else:
        def body(i, acc):
            # a window of ``chunk`` groups sliced in place (padding the (G, K, K) pair-id
            # table to whole chunks would copy it: GBs for a 3D body); the last window is
            # shifted back to end at G, and its groups already summed point at the zero
            # padding row Q instead
            start = jnp.minimum(i * chunk, G - chunk)
            grp = jax.lax.dynamic_slice_in_dim(ops.groups, start, chunk)
            seen = (start + jnp.arange(chunk) < i * chunk)[:, None]
            pid = jax.lax.dynamic_slice_in_dim(ops.pair_id, start, chunk)
            return chunk_sum(acc, jnp.where(seen, Q, grp), pid)

        U = jax.lax.fori_loop(0, windows, body, zero)
    if half:
        U = U + jnp.where((ops.pair_i == ops.pair_j)[:, None, None], 0.0, jnp.swapaxes(U[ops.pair_t], -1, -2))
    return U + spring_blocks(ops, params, n_pairs, dim)


def spring_blocks(ops, params, n_pairs, dim):
    """The springs' tangent k_s Psi_K(X_s) Psi_M(X_s) I as (P, d, d) pair blocks."""
    sp = params.springs
    kk = jnp.einsum("s,sk,sm->skm", sp["k"], sp["psi"], sp["psi"])
    scal = jax.ops.segment_sum(kk.ravel(), ops.sp_pair.ravel(), num_segments=n_pairs)
    return scal[:, None, None] * jnp.eye(dim)


def tangent(ops, params, cfg: Config, u, g):
    """The tangent as the linear solver takes it: dense K_ff, or (P, d, d) pair blocks."""
    return cfg.linear.matrix(ops, pair_blocks(ops, params, cfg.W, coefficients(ops, u, g)))


def linear_state(ops, params, cfg: Config, u, g):
    """The linear solver's factorisation of K_ff at (u, g) (see jaxrkpm.linear)."""
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


# ------------------------------------------------------------------ the stable branch
SWITCH_AMPLITUDE = 0.05   # the kick along the critical mode: its largest entry, in particle spacings
SHIFT_FLOOR = 1e-10       # smallest tangent shift, relative to the largest diagonal entry of K_ff
COLLAPSE_DET = 1e-3       # a descent whose iterate has det F below this at an integration point is
#                           running into det F = 0 (the material collapsing: see ``descend``)


def switches_branch(cfg: Config) -> bool:
    """Whether solves with ``cfg`` go on past a critical point (static): the stable-branch
    option needs the stability check and the dense tangent (its eigenpairs); the sparse path
    stops with UNSTABLE_TANGENT as before."""
    return bool(cfg.stable_branch and cfg.check_stability and isinstance(cfg.linear, DenseSolver))


def when(need, f, default):
    """f() where ``need``, else ``default``, as a while loop that runs at most once: unlike a
    lax.cond under vmap (which evaluates both sides for every member), the loop costs nothing
    while no batch member needs it; and a ``default`` that holds large arrays (a kept
    factorisation) passes through in place, where a lax.cond copied it (measured in the
    control loop: ~40 ms a call for a 2,400^2 dense state)."""
    def body(c):
        return jnp.array(False), f()
    return jax.lax.while_loop(lambda c: c[0], body, (jnp.asarray(need), default))[1]


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
    trust-region minimisation from there (``jaxrkpm.minimise.stable_beyond``) drives the
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


def joined(first: Solution, rest: Solution) -> Solution:
    """One Solution of a path solved in two parts: ``first`` stopped at the fraction t1 of
    the increment, ``rest`` went on from its state to the same end. Fractions of the rest
    (its t, its critical points) become fractions of the whole path, t1 + (1 - t1) t; the
    counters add up; the state is the rest's."""
    t1 = first.t

    def whole(t):
        return t1 + (1 - t1) * t

    crit = rest.critical._replace(t_stable=whole(rest.critical.t_stable),
                                  t_unstable=whole(rest.critical.t_unstable))
    return rest._replace(t=whole(rest.t), iterations=first.iterations + rest.iterations,
                         steps=first.steps + rest.steps, cuts=first.cuts + rest.cuts,
                         branch=first.branch + rest.branch, critical=crit)


# ------------------------------------------------------------ implicit differentiation
def _zero_tangent(x):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.integer) or x.dtype == jnp.bool_:
        return np.zeros(x.shape, dtype=jax.dtypes.float0)
    return jnp.zeros_like(x)


REFINE_MAX = 20   # CG preconditioned by a kept factorisation: at most this many iterations
#                   (each m Hessian-vector products)


def sensitivity(ops, params, cfg: Config, u, g, load, rhs, state=None, refine: float = 0.0, guess=None):
    """x = K_ff^-1 rhs at the equilibrium (u, g, load), rhs (Nf, d) or (Nf, d, m): the one
    linearised solve behind every implicit derivative (solve's JVP, ``response``, Jacobians).
    ``state``: a factorisation of K_ff there to reuse (default: factorise now).
    ``refine`` > 0: ``state`` factorises a nearby, earlier tangent (a factorisation kept across
    control steps): conjugate gradients with the exact product, preconditioned by that
    factorisation (``jaxrkpm.refinement.preconditioned_cg``), until |rhs - K x| <= refine |rhs|
    per column (at most REFINE_MAX iterations), so the result is K_ff^-1 rhs of this state to
    that relative residual. Why CG, not the stationary refinement x += solve(rhs - K x): that
    contracts by the kept factorisation's chord factor per step, and needed 25 corrections
    where CG took 9 (10^3 cube, a factorisation 10 control steps old; 0.49 s against 0.23 s).
    ``guess`` (rhs's shape): where CG starts (e.g. the solution at the previous control step;
    the result meets the same residual test). 0: ``state`` factorises this very tangent (no
    refinement).

    A custom linear solve: the matrix-vector product is the exact Hessian-vector product of
    the energy, the solve uses the factorisation, and symmetry makes it transposable (so
    reverse mode works too)."""
    if state is None:
        state = linear_state(ops, params, cfg, u, g)

    def hvp(v):
        return jax.jvp(lambda x: residual(ops, params, cfg.W, x, g, load), (u,), (v,))[1]

    # several right-hand sides (Nf, d, m) are one block: the product column by column
    matvec = hvp if rhs.ndim == u.ndim else jax.vmap(hvp, in_axes=-1, out_axes=-1)

    def solve(mv, b):
        if not refine:
            return cfg.linear.solve(state, b)
        x0 = None if guess is None else jax.lax.stop_gradient(guess)
        return preconditioned_cg(mv, partial(cfg.linear.solve, state), b, refine, REFINE_MAX,
                                 columns=b.ndim > u.ndim, loop=jax.lax.while_loop, x0=x0)[0]

    return jax.lax.custom_linear_solve(matvec, rhs, solve=solve, symmetric=True)


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def solve_path_diff(ops, params, cfg, lim, u0, g0, g1, l0, l1, state0=None):
    """``solve_path`` differentiable in (g1, l1, params) by the implicit function theorem at
    the converged state: K_ff du = -(dr/dg dg + dr/dl dl + dr/dp dp). No Newton iteration is
    differentiated; the path start (u0, g0, l0) and ``state0`` only select the equilibrium
    branch and where Newton starts."""
    return solve_path(ops, params, cfg, lim, u0, g0, g1, l0, l1, state0)


@solve_path_diff.defjvp
def _solve_path_jvp(cfg, primals, tangents):
    ops, params, lim, u0, g0, g1, l0, l1, state0 = primals
    _, dparams, _, _, _, dg1, _, dl1, _ = tangents
    sol = solve_path_diff(ops, params, cfg, lim, u0, g0, g1, l0, l1, state0)
    # a failed solve has no derivative: NaN, never the finite derivative of the kept state
    # (a factor, not a select, so the tangent stays linear and reverse mode transposes it)
    valid = jnp.where(reached_equilibrium(sol.status), 1.0, jnp.nan)
    dg, dl = sol.t * valid * dg1, sol.t * valid * dl1
    _, dr = jax.jvp(lambda g, l, p: residual(ops, p, cfg.W, sol.u, g, l),
                    (sol.g, sol.load, params), (dg, dl, dparams))
    du = -sensitivity(ops, params, cfg, sol.u, sol.g, sol.load, dr) * valid
    dsol = Solution(du, dg, dl, *jax.tree.map(_zero_tangent, tuple(sol[3:])))
    return sol, dsol


solve_path_jit = jax.jit(solve_path_diff, static_argnames=("cfg",))


def response(ops, params, cfg: Config, u, g, load, dG, state=None, refine: float = 0.0, guess=None):
    """Implicit sensitivity of the free coefficients to m prescribed directions dG (m, Nb, d):
    K_ff du = -K_fg dG with one factorisation (``state``, or a new one; ``refine`` and
    ``guess``, a response (m, Nf, d) to start from: see ``sensitivity``). Returns (m, Nf, d)."""
    dr = jax.vmap(lambda dg: jax.jvp(lambda x: residual(ops, params, cfg.W, u, x, load),
                                     (g,), (dg,))[1])(dG)                      # (m, Nf, d)
    x0 = None if guess is None else -jnp.moveaxis(guess, 0, -1)
    du = -sensitivity(ops, params, cfg, u, g, load, jnp.moveaxis(dr, 0, -1), state, refine, x0)   # (Nf, d, m)
    return jnp.moveaxis(du, -1, 0)


def point_values(ops, idx, psi, u, g):
    """Displacement at points with precomputed (P, K) shape functions: (P, d)."""
    d = coefficients(ops, u, g)
    return jnp.einsum("pk,pki->pi", psi, d[idx])


def point_jacobian(ops, idx, psi, u, g, du, dG):
    """d(displacement at points)/d(direction) from the responses du (m, Nf, d) to the
    directions dG (m, Nb, d): (P, d, m) (the point values are linear in (u, g))."""
    dU = jax.vmap(lambda a, b: jax.jvp(lambda x, y: point_values(ops, idx, psi, x, y), (u, g), (a, b))[1])(du, dG)
    return jnp.moveaxis(dU, 0, -1)


@partial(jax.jit, static_argnames=("cfg",))
def implicit_jacobian(ops, params, cfg: Config, u, g, load, dG, idx, psi, state=None):
    """d(displacement at points)/d(direction) for the m directions dG: (P, d, m)."""
    du = response(ops, params, cfg, u, g, load, dG, state)
    return point_jacobian(ops, idx, psi, u, g, du, dG)
