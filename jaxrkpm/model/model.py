"""The user-facing model: builds every table once, then solves and post-processes.
"""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ..discretise import quadrature as integ
from ..discretise import scni
from ..discretise.body import Body
from ..discretise.constraints import EssentialSets, Transformation
from ..mechanics.constraint import Essential, essential as essential_constraint, held_components
from ..mechanics.contact import ContactPenetrationWarning, ContactTerm, penetration
from ..mechanics.loads import SpringTerm, Springs, dead_load, spring_psi, spring_term
from ..mechanics.materials import Material, det, green_lagrange, pk2
from ..mechanics.problem import Problem
from ..mechanics.strain import deformation_gradients, strain_energy
from ..mechanics.term import Context, TermSpec, on_pattern
from ..solvers.branch import BranchSwitch, StableDescent
from ..solvers.implicit import implicit_jacobian, solve_path_jit
from ..solvers.linalg.base import LinearSolver
from ..solvers.linalg.dense import DenseSolver
from ..solvers.linalg.factorisations import SaddlePointSystem, factoriser
from ..solvers.linalg.krylov import KrylovSolver
from ..solvers.linalg.multigrid import KrylovSystem
from ..solvers.linalg.sparse import SparseSolver
from ..solvers.newton import Newton, Tolerance
from ..solvers.path import LoadPath
from ..solvers.results import Critical, Limits, Solution, Status, joined


# FD evaluates it per re-solve: one dispatch, not ~10 eager ops
_point_values_jit = jax.jit(lambda constraint, idx, psi, u, g: constraint.point_values(idx, psi, u, g))

MAX_SUPPORT_DIAMETERS = 2.0   # kernel support (support x spacing) allowed, in body diameters
SOLVERS = ("auto", "dense", "sparse", "krylov")   # Model(solver=...)
PRECISIONS = ("auto", "double", "mixed")          # Model(precision=...): dense and PARDISO factorisations
# the options of ``Model.solve``: fields of the solver objects (``Model.solver``)
NEWTON_OPTIONS = ("line_search", "armijo", "reuse", "check_stability")
SOLVER_OPTIONS = ("rtol", *NEWTON_OPTIONS, "easy", "growth", "locate", "stable_branch")


@dataclass(frozen=True)
class SolverChoice:
    """How a Model chooses its solvers where the user leaves it to it (``solver="auto"``,
    ``precision="auto"``, ``reuse=None``), each choice a field (a test or a user gives
    another value by passing ``Model(..., choice=SolverChoice(...))``).

    dense_2d, dense_3d   free DOFs up to which "auto" takes the dense factorisation on a CPU.
                         3D: where one Newton iteration's linear work (assemble, factorise,
                         solve) costs the same dense and sparse (PARDISO)
                         (``experiments/bench_cube3d.py --only-crossover``). 2D stays higher
                         although sparse wins earlier there, because the stable-branch and
                         modified-Newton options are dense-only.
    mixed_min            free DOFs from which "auto" factorises dense K_ff in single precision
                         and refines its solves in double: where the Cholesky factorisation is
                         most of a Newton iteration (``experiments/bench_cube3d.py --precision``);
                         below it the 2D models and their stability studies stay in double.
    dense_copies, accelerator_dense
                         on an accelerator the sparse paths are host callbacks and the dense one
                         runs on the device, so "auto" goes dense while about ``dense_copies``
                         n^2 doubles fit in its memory (``accelerator_dense`` free DOFs where the
                         device does not report it).
    newton_reuse         modified Newton's ``reuse`` for an eager solve on the dense path: a
                         kept factorisation while each step cuts |r| by this factor (same
                         residual tolerance, fewer factorisations:
                         ``experiments/bench_cube3d.py``). Not under jit/vmap: a vmapped
                         lax.cond evaluates both branches, so lock-step members would assemble
                         at every iteration and iterate more."""

    dense_2d: int = 2500
    dense_3d: int = 4400
    mixed_min: int = 1000
    dense_copies: int = 4
    accelerator_dense: int = 20_000
    newton_reuse: float = 0.1

    def dense_limit(self, dim: int, device=None) -> int:
        """Free DOFs up to which ``solver="auto"`` takes the dense path on ``device`` (default:
        JAX's first device): ``dense_2d``/``dense_3d`` on a CPU; on a GPU/TPU as many as
        ``dense_copies`` dense n x n float64 matrices fit in its memory."""
        cpu = self.dense_2d if dim == 2 else self.dense_3d
        device = jax.devices()[0] if device is None else device
        if device.platform == "cpu":
            return cpu
        try:
            memory = (device.memory_stats() or {}).get("bytes_limit")
        except (AttributeError, NotImplementedError, RuntimeError):   # no memory statistics there
            memory = None
        if not memory:
            return max(self.accelerator_dense, cpu)
        return max(int((memory / (8 * self.dense_copies)) ** 0.5), cpu)


class SolveError(RuntimeError):
    """A solve did not converge; ``.solution`` holds the last converged state."""

    def __init__(self, solution: Solution):
        super().__init__(solution.message)
        self.solution = solution


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _concrete(x):
    """x as a NumPy array, or None where its value is not known (inside jit or vmap). Under
    jax.jacfwd / jax.grad outside jit the value is known: the tracer carries it."""
    while isinstance(x, jax.core.Tracer):
        value = getattr(x, "to_concrete_value", lambda: None)()
        if value is None:
            return None
        x = value
    return np.asarray(x)


def _params_at(p0, p1, t):
    """The parameters at the fraction t of a path that ramps them from p0 to p1 (None: p0 None)."""
    if p0 is None:
        return None
    t = float(t)
    return jax.tree.map(lambda a, b: b if t >= 1.0 or not jnp.issubdtype(jnp.result_type(b), jnp.inexact)
                        else a + t * (b - a), p0, p1)


class Model:
    """Total-Lagrangian RKPM hyperelastic model.

    body        the reference Body
    material    a Material (strain energy W(E, p))
    integration "gauss" (background cells, ``order`` points per direction) | "scni" (stabilized
                conforming nodal integration, ``order`` points per cell facet) | "mscni"
                (SCNI + sub-cell stabilisation); see jaxrkpm.discretise.scni. "gauss" is the
                default for mesh bodies too (points in each tetrahedron / triangle): on a
                tetrahedral box it is the most accurate per unit of solve time, where SCNI
                solves faster but is exact only for affine fields and far less accurate for a
                smooth large deformation, at every refinement measured
                (experiments/bench_mesh_integration.py)
    anti_locking  None (default): on where the material is nearly incompressible (an energy
                with a volumetric-deviatoric split, or Lame constants with lam >= 9 mu, Poisson's
                ratio 0.45); True / False: on / off. On, every integration point's energy is
                taken at F-bar, its volume change averaged over the points of a background
                cell (Gauss and MSCNI; on a mesh body, the points nearest one particle; SCNI
                is left as it is), which removes
                volumetric locking as nu -> 1/2 (jaxrkpm.discretise.quadrature.dilatation_patches,
                ``docs/guide/models.md``). Stresses at arbitrary points (``stress``) are the
                point's own.
    essential   name -> particle indices (or boolean mask) of each essential set, or a
                ``Roller`` (a set that holds only some components: a symmetry plane; dense solver)
    support     kernel dilation a = support x spacing (eq 3.20)
    body_force  (d,) or X -> (Q, d): dead load per unit reference volume
    tractions   [(predicate, h0), ...]: dead load per unit reference area on the boundary
                points where predicate(X) holds (the points of the integration's own boundary
                rule: under SCNI/MSCNI its smoothing cells' boundary facets, so that a uniform
                traction passes the patch test)
    springs     Springs(points, stiffness, region): zero-length springs holding material
                points (elastic supports, penalty paddles; movable, see ``springs_at``)
    terms       [spec, ...]: further terms of the total potential energy, each a
                ``TermSpec`` with a name of its own that keys its parameters in
                ``solve(params=...)``, e.g. ``Pressure(where, p)``, a follower pressure on a
                boundary part (see jaxrkpm.mechanics.term for writing one)
    solver      "auto" (dense up to ``choice.dense_limit(dim)`` free DOFs on a CPU, as many as
                the device memory holds on a GPU; else sparse) | "dense" | "sparse"
                | "krylov" (CG preconditioned by algebraic multigrid, no factorisation: large 3D
                models; see jaxrkpm.solvers.linalg.multigrid) | a ``LinearSolver`` instance,
                used as given (``jaxrkpm.internal.DenseSolver(mixed=True)``, or one written
                outside the package to the contract of ``jaxrkpm.internal.LinearSolver``)
    factorisation  of the sparse path: "auto" (PARDISO where Intel MKL is installed, else
                SuperLU) | "pardiso" | "superlu"; see jaxrkpm.solvers.linalg.factorisations
    precision   of the factorisation: "auto" (dense: mixed from ``choice.mixed_min`` free
                DOFs, else double; PARDISO: mixed) | "double" | "mixed" (single-precision
                factorisation, solves refined to double accuracy: about half the factorisation
                time; see ``DenseSolver`` and ``SaddlePointSystem``; SuperLU is double only)
    choice      a ``SolverChoice``: how "auto" chooses (its fields)
    """

    def __init__(self, body: Body, material: Material, integration: str = "gauss",
                 essential: Mapping | None = None, support: float = 2.01, order: int = 2,
                 cell_size: float | None = None, body_force=None, tractions=(),
                 springs: Springs | None = None, terms=(), solver: str = "auto",
                 factorisation: str = "auto", precision: str = "auto", choice: SolverChoice = SolverChoice(),
                 anti_locking: bool | None = None):
        if not isinstance(body, Body):
            raise ValueError(f"body must be a jaxrkpm Body, got {type(body).__name__}")
        if not isinstance(material, Material):
            raise ValueError(f"material must be a jaxrkpm Material, got {type(material).__name__}")
        if essential is not None and not isinstance(essential, Mapping):
            raise TypeError(f"essential must be a dict name -> particle indices (e.g. "
                            f"{{'wall': body.select(...)}}), got {type(essential).__name__}")
        if not (np.isfinite(support) and support > 0):
            raise ValueError(f"support must be a positive number (x spacing), got {support}")
        diameter = float(np.linalg.norm(body.upper - body.lower))
        if support * body.spacing > MAX_SUPPORT_DIAMETERS * diameter:
            # every window covers the whole body many times over: the shape functions
            # degenerate towards the global linear basis and K_ff towards singular (the
            # solve then fails with MAX_ITERATIONS or LINE_SEARCH at 0%, naming neither)
            raise ValueError(f"support {support:g} x spacing {body.spacing:g} = {support * body.spacing:g} "
                             f"exceeds {MAX_SUPPORT_DIAMETERS:g} x the body's diameter {diameter:.3g}: "
                             "every shape function would cover the whole body; use a support of a "
                             "few spacings (e.g. 2.01 .. 4)")
        # checked before any rule is built from it (the boundary rule is built first)
        if isinstance(order, (bool, np.bool_)) or not isinstance(order, (int, np.integer)) or not 1 <= order <= 20:
            raise ValueError(f"order must be a whole number of integration points per direction in 1..20 "
                             f"(2 is the default), got {order!r}")
        if integration not in ("gauss", *scni.SCHEMES):
            raise ValueError(f"unknown integration {integration!r}: choose 'gauss', "
                             + ", ".join(repr(k) for k in scni.SCHEMES))
        if not isinstance(solver, LinearSolver) and solver not in SOLVERS:
            raise ValueError(f"unknown solver {solver!r}: choose " + ", ".join(repr(k) for k in SOLVERS)
                             + ", or pass a jaxrkpm.internal.LinearSolver instance")
        factoriser(factorisation)   # a clear error now, even where the dense path is chosen
        if precision not in PRECISIONS:
            raise ValueError(f"unknown precision {precision!r}: choose "
                             + ", ".join(repr(k) for k in PRECISIONS))
        self.body, self.material, self.integration = body, material, integration
        self.support = float(support)
        self.a = self.support * body.spacing
        d = body.dim

        bp, bw, bn = integ.boundary_points(body, order)
        self.surface = integ.table(body, bp, bw, self.a, normals=bn, support_factor=self.support)
        if integration == "gauss":
            self.volume = integ.gauss_table(body, self.a, order, cell_size, support_factor=self.support)
            balanced = self.surface
        else:
            smooth = scni.smoothing(body, self.a, integration, order, support_factor=self.support)
            self.volume, balanced = smooth.table, smooth.boundary

        self.sets = EssentialSets.build(body, dict(essential or {}))
        partial = self.sets.partial
        if partial and solver in ("sparse", "krylov"):
            raise ValueError(f"solver {solver!r} does not take Roller sets (held components) yet: use "
                             "solver='dense' or 'auto'")
        trans = (Transformation.build(body, self.sets, self.a, self.support)
                 if len(self.sets.bnd) and not partial else None)
        ctx = Context(body, self.a, self.support, self.volume, self.surface, self.sets, balanced)
        if anti_locking not in (None, True, False):
            raise ValueError(f"anti_locking must be None (where the material needs it), True or False, "
                             f"got {anti_locking!r}")
        strain = strain_energy(ctx, material, anti_locking,
                               integ.dilatation_patches(body, self.volume, integration, cell_size))
        built = (strain, self._springs(springs, ctx), dead_load(ctx, body_force, tractions),
                 *self._terms(terms, ctx, {*strain.point, *strain.tensors}))
        pairs, built, pair_i, pair_j = on_pattern(built, body.n, d)
        constraint = (held_components(body, self.sets, self.a, self.support, body.n, d) if partial
                      else essential_constraint(self.sets, trans, body.n, d, pair_i, pair_j))
        self._problem = Problem(constraint, pairs, built, jnp.asarray(body.spacing))

        n_free = len(self.sets.free) * d
        if not isinstance(choice, SolverChoice):
            raise ValueError(f"choice must be a SolverChoice, got {type(choice).__name__}")
        self.choice = choice
        use_dense = solver == "dense" or (solver == "auto" and (partial or n_free <= choice.dense_limit(d)))
        if isinstance(solver, LinearSolver):   # the user's own, used as given
            self.linear = solver
        elif use_dense:
            self.linear = DenseSolver(mixed=precision == "mixed" or (precision == "auto" and n_free >= choice.mixed_min))
        elif solver == "krylov":
            self.linear = KrylovSolver(KrylovSystem(body.X, pair_i, pair_j, self._constraints(trans),
                                                    self.sets.free, self.sets.bnd))
        else:
            self.linear = self._sparse_solver(trans, pair_i, pair_j, factorisation, precision)
        # no essential set and no springs: the body may translate and rotate freely. Such a
        # model is fine for its tangent (its rigid-body modes) and energy; a solve is refused
        self.unconstrained = len(self.sets.bnd) == 0 and not np.any(np.asarray(self.springs.k) > 0)

    # ----------------------------------------------------------------------- internals
    def _springs(self, springs, ctx):
        """The springs' term (an empty one where there are none)."""
        return spring_term(ctx, springs)

    def _terms(self, specs, ctx, material_names) -> list:
        """The terms built from ``Model(terms=...)``: each a ``TermSpec`` whose name is free
        (not a material parameter, not another term's)."""
        if isinstance(specs, TermSpec) or not isinstance(specs, (list, tuple)):
            raise TypeError(f"terms must be a list of term specifications (e.g. [jaxrkpm.Pressure(...)]), "
                            f"got {type(specs).__name__}")
        taken = {"strain", "springs", "dead_load", *material_names}
        out = []
        for spec in specs:
            if not isinstance(spec, TermSpec):
                raise TypeError(f"each of terms must be a term specification (e.g. jaxrkpm.Pressure), "
                                f"got {type(spec).__name__}")
            if not isinstance(spec.name, str) or spec.name in taken:
                raise ValueError(f"term name {spec.name!r} is taken (by a term or a material parameter): "
                                 f"give it another name=...")
            taken.add(spec.name)
            out.append(spec.build(ctx))
        return out

    @property
    def springs(self) -> SpringTerm:
        """The springs' term (its points' shape functions ``psi`` and stiffnesses ``k``)."""
        return self._problem.term("springs")

    @property
    def constraint(self) -> Essential:
        """The essential constraint d = T(u, g) (``jaxrkpm.internal.Essential``)."""
        return self._problem.constraint

    @property
    def params(self) -> dict:
        """The model's parameters: term name -> that term's (``Problem.params``)."""
        return self._problem.params

    def springs_at(self, points, stiffness=None) -> dict:
        """``params={"springs": ...}`` for the model's springs moved to ``points`` (S, d)
        (and, optionally, new stiffnesses): JAX, so a solve is differentiable in both. The
        points must stay where the particles of the spring region cover them."""
        S = self.springs.idx.shape[0]
        if S == 0:
            raise ValueError("this model has no springs (Model(..., springs=Springs(...)))")
        points = jnp.asarray(points, jnp.float64)
        if points.shape != (S, self.dim):
            raise ValueError(f"spring points must have shape ({S}, {self.dim}), got {points.shape}")
        psi = spring_psi(self.body, self.a, points, np.asarray(self.springs.idx))
        if _is_concrete(psi) and not np.allclose(np.asarray(psi).sum(1), 1.0, atol=1e-8):
            raise ValueError("a spring point left its region (its shape functions no longer sum "
                             "to 1): widen Springs(region=...)")
        k = self.springs.k if stiffness is None else jnp.broadcast_to(
            jnp.asarray(stiffness, jnp.float64), (S,))
        return {"psi": psi, "k": k}

    def _sparse_solver(self, trans, pair_i, pair_j, factorisation, precision) -> SparseSolver:
        d = self.body.dim
        a, b = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
        rows = (pair_i[:, None, None] * d + a[None]).ravel()
        cols = (pair_j[:, None, None] * d + b[None]).ravel()
        free_dofs = (self.sets.free[:, None] * d + np.arange(d)[None]).ravel()
        return SparseSolver(SaddlePointSystem(self.body.X, rows, cols, self._constraints(trans), free_dofs,
                                              self.sets.bnd, d, factorisation, precision))

    def _constraints(self, trans) -> sp.csr_matrix:
        """C = [D^nb D^b] (x) I (Nb d, N d): C d = 0 where the essential particles hold (the
        sparse form of the transformation)."""
        d, N = self.body.dim, self.body.n
        Nb = len(self.sets.bnd)
        if trans is not None:
            Kb = trans.nb_idx.shape[1]
            r = (np.arange(Nb)[:, None, None] * d + np.arange(d)[None, None, :]).repeat(Kb, 1)
            c = trans.nb_idx[:, :, None] * d + np.arange(d)[None, None, :]
            v = np.repeat(trans.rows_psi[:, :, None], d, axis=2)
            return sp.csr_matrix((v.ravel(), (r.ravel(), c.ravel())), shape=(Nb * d, N * d))
        return sp.csr_matrix((0, N * d))

    def solver(self, **options) -> LoadPath:
        """The solver of this model's solves: a ``LoadPath`` (adaptive load stepping) over a
        ``Newton`` with the model's linear solver, from the ``solve`` options (each a field of
        the object it tunes): ``rtol`` (the residual tolerance, ``Tolerance``), ``line_search``,
        ``armijo``, ``reuse``, ``check_stability`` (``Newton``), ``easy``, ``growth``,
        ``locate`` (``LoadPath``) and ``stable_branch`` (True: a ``BranchSwitch`` past critical
        points)."""
        unknown = set(options) - set(SOLVER_OPTIONS)
        if unknown:
            raise ValueError(f"unknown solver option(s) {sorted(unknown)}; the options are {list(SOLVER_OPTIONS)}")
        options = dict(options)
        stable_branch = options.pop("stable_branch", False)
        if not isinstance(stable_branch, (bool, np.bool_)):
            raise ValueError(f"stable_branch must be True, False or None (automatic), got {stable_branch!r}")
        tolerance = Tolerance(options.pop("rtol")) if "rtol" in options else Tolerance()
        newton = Newton(self.linear, tolerance, **{k: options.pop(k) for k in NEWTON_OPTIONS if k in options})
        branch = None
        if stable_branch:
            branch = BranchSwitch(StableDescent(tolerance, newton.line_search, newton.armijo))
        return LoadPath(newton, branch=branch, **options)

    def problem(self, params=None) -> Problem:
        """The discrete problem with parameter overrides ``params`` (see ``params_with``): a
        jit-friendly pytree (see jaxrkpm.mechanics.problem)."""
        return self._problem.replace(params=self.params_with(params)) if params else self._problem

    @property
    def dim(self) -> int:
        return self.body.dim

    @property
    def set_names(self) -> tuple:
        return self.sets.names

    def set_indices(self, name: str) -> np.ndarray:
        self._check_set(name)
        return self.sets.bnd[self.sets.slices[name]]

    def _check_set(self, name):
        if name not in self.sets.slices:
            raise ValueError(f"unknown essential set {name!r}; this model has {list(self.sets.names)}")

    def _check_g(self, g, what: str = "g"):
        """All prescribed values (Nb, d) as a float array: the right shape for THIS model
        (a g of another model is named, not a broadcasting error) and finite."""
        shape = (len(self.sets.bnd), self.dim)
        try:
            g = jnp.asarray(g, jnp.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{what} must be a {shape} array of prescribed values") from None
        if g.shape != shape:
            raise ValueError(f"{what} has shape {g.shape}, but this model has {shape[0]} essential "
                             f"particles in {shape[1]}D: shape {shape} (from model.prescribed(...) of "
                             "this model)")
        if _is_concrete(g) and not np.all(np.isfinite(np.asarray(g))):
            raise ValueError(f"{what} has non-finite prescribed values (NaN/inf) at essential "
                             f"particles {np.flatnonzero(~np.isfinite(np.asarray(g)).all(1))[:5].tolist()}")
        return g

    def check_solution(self, sol, what: str = "solution") -> Solution:
        """``sol`` if it is a Solution of this model's shapes (u (Nf, d), g (Nb, d)); a
        ValueError naming the mismatch for one of another model (or not a Solution)."""
        if not isinstance(sol, Solution):
            raise TypeError(f"{what} must be a jaxrkpm Solution (from model.solve), got {type(sol).__name__}")
        want_u, want_g = (len(self.sets.free), self.dim), (len(self.sets.bnd), self.dim)
        if jnp.shape(sol.u) != want_u or jnp.shape(sol.g) != want_g:
            raise ValueError(f"{what} does not belong to this model: its u, g have shapes "
                             f"{jnp.shape(sol.u)}, {jnp.shape(sol.g)}; this model's are {want_u}, "
                             f"{want_g} (a Solution of another model, or a batched one: index it)")
        return sol

    def prescribed(self, values: Mapping | None = None, base=None):
        """(Nb, d) prescribed displacements from name -> (d,) rigid translation or (n_set, d);
        sets not named keep ``base`` (default: zero)."""
        d = self.dim
        g = jnp.zeros((len(self.sets.bnd), d)) if base is None else self._check_g(base, "base")
        if values is not None and not isinstance(values, Mapping):
            raise TypeError(f"prescribed values must be a dict set name -> value, got {type(values).__name__}")
        for name, v in (values or {}).items():
            self._check_set(name)
            sl = self.sets.slices[name]
            n = sl.stop - sl.start
            try:
                v = jnp.asarray(v, dtype=jnp.float64)
            except (TypeError, ValueError):
                raise ValueError(f"prescribed value for {name!r} must be numbers of shape ({d},) (rigid) "
                                 f"or ({n}, {d}) (per particle), got {v!r}") from None
            if v.shape == (d,):
                v = jnp.broadcast_to(v, (n, d))
            elif v.shape != (n, d):
                raise ValueError(f"prescribed value for {name!r} must have shape ({d},) (rigid) "
                                 f"or ({n}, {d}) (per particle), got {v.shape}")
            if _is_concrete(v) and not np.all(np.isfinite(np.asarray(v))):
                raise ValueError(f"prescribed value for {name!r} is not finite")
            g = g.at[sl].set(v)
        return g

    def params_with(self, overrides: Mapping | None = None) -> dict:
        """The problem's parameters (term name -> its parameters, ``Problem.params``) with
        overrides: a material parameter's name -> scalar, (Q,) array, or field X -> (Q,); a
        term's name (e.g. "springs", a pressure's) -> its value (see the term)."""
        if not overrides:
            return self.params
        if not isinstance(overrides, Mapping):
            raise TypeError(f"params must be a dict name -> value, got {type(overrides).__name__}")
        params = dict(self.params)
        strain = self._problem.term("strain")
        point, tensors = dict(strain.point), dict(strain.tensors)
        Q = strain.w.shape[0]
        terms = {t.name: t for t in self._problem.terms if t.name != "strain"}
        for k, v in overrides.items():
            if k in point:
                if callable(v):
                    v = np.asarray(v(self.volume.points), float)
                v = jnp.asarray(v, jnp.float64)
                if v.ndim == 0:
                    v = jnp.broadcast_to(v, (Q,))
                if v.shape != (Q,):
                    raise ValueError(f"parameter {k!r} must be a scalar or ({Q},) values, got {v.shape}")
                if _is_concrete(v):
                    arr = np.asarray(v)
                    if not np.all(np.isfinite(arr)):
                        raise ValueError(f"parameter {k!r} is not finite")
                    self.material._check_sign(k, arr)
                point[k] = v
            elif k in tensors:
                tensors[k] = jnp.asarray(v, jnp.float64)
            elif k in terms:
                params[k] = terms[k].check_params(v)
            else:
                raise ValueError(f"unknown material parameter {k!r}; {self.material.name} has "
                                 f"{sorted(point) + sorted(tensors)}, and the model's terms "
                                 f"{sorted(terms)}")
        params["strain"] = {"point": point, "tensors": tensors}
        return params

    # -------------------------------------------------------------------------- solve
    def initial(self) -> Solution:
        """The undeformed, unloaded equilibrium."""
        z = jnp.zeros((), jnp.int32)
        f = jnp.zeros((), jnp.float64)  # not weak-typed: the same jit signature as a solve's output
        u = jnp.zeros((len(self.sets.free), self.dim))
        return Solution(u, jnp.zeros((len(self.sets.bnd), self.dim)), f, z, f + 1.0, z, z, z, f, z,
                        Critical.empty(u))

    def __repr__(self) -> str:
        sets = {name: len(self.sets.bnd[sl]) for name, sl in self.sets.slices.items()}
        terms = [t.name for t in self._problem.terms if t.name not in ("strain", "springs", "dead_load")]
        return (f"Model({self.body.dim}D, {self.body.n} particles, {self.material.name}, {self.integration}, "
                f"support {self.support:g}, essential {sets or 'none'}"
                + (f", terms {terms}" if terms else "") + f", {type(self.linear).__name__})")

    def solve(self, prescribed: Mapping | None = None, *, loads: float = 1.0, params=None,
              steps: int = 1, initial: Solution | None = None, throw: bool = True,
              max_iter: int = 25, **options) -> Solution:
        """Equilibrium under the prescribed displacements and load scale ``loads``.

        ``prescribed``: set name -> (d,) rigid translation or (n_set, d) values; sets not
        named keep the values of ``initial`` (default: zero).
        ``params``: parameter overrides (``params_with``): a material parameter by its name,
        a term's parameters by the term's name ("springs", a pressure's p by its name).
        ``initial`` warm-starts from a previous Solution (the path starts at its prescribed
        values and load). ``steps`` is the initial number of load steps (halved on failure,
        grown when easy; at most jaxrkpm.solvers.results.Limits.most_steps). With ``throw`` a failed solve raises
        SolveError (carrying the last converged state), also under jax.jacfwd / jax.grad;
        under jit/vmap the status is returned instead.

        ``options``: solver settings (``solver``). ``stable_branch`` None (default): where the solve
        stops at a critical point (UNSTABLE_TANGENT, dense solver), the rest of the path is
        solved with ``stable_branch=True`` from the last stable state (on to a stable state
        of a bifurcated branch; ``Solution.critical`` records the point); its compile is paid
        only then, and only in eager calls. False: stop there; True: always (also under jit).
        ``reuse`` None (default): ``newton_reuse`` in eager calls (modified Newton on the dense
        path: fewer factorisations, the same residual tolerance), 0 (full Newton) under
        jit/vmap; a number sets the Newton solver's ``reuse``.

        Differentiable (jax.jacfwd / jax.grad) in the prescribed values, ``loads`` and
        ``params`` by implicit differentiation of the converged equilibrium. The derivative
        of a FAILED solve (``throw=False``, or inside jit) is NaN: the kept state is not the
        equilibrium asked for, so it has no derivative to give."""
        start = self.initial() if initial is None else self.check_solution(initial, "initial")
        return self.solve_g(self.prescribed(prescribed, base=start.g), loads=loads, params=params,
                            steps=steps, initial=start, throw=throw, max_iter=max_iter, **options)

    def solve_g(self, g, *, loads: float = 1.0, params=None, steps: int = 1,
                initial: Solution | None = None, throw: bool = True, max_iter: int = 25,
                max_cuts: int = 10, **options) -> Solution:
        """``solve`` with all prescribed values as one (Nb, d) array (see ``prescribed``)."""
        if self.unconstrained:
            raise ValueError("unconstrained: rigid-body modes. The model has no essential set and no "
                             "springs, so it can translate and rotate freely and no solve has a unique "
                             "equilibrium; hold part of it (essential={'wall': body.select(...)}) or "
                             "add Springs")
        start = self.initial() if initial is None else self.check_solution(initial, "initial")
        g = self._check_g(g)
        if _is_concrete(loads) and not np.isfinite(loads):
            raise ValueError(f"loads must be finite, got {loads}")
        # stable_branch None (default): the plain solve, and only where it stops at a critical
        # point does the rest of the path run with the stable-branch solve, so its longer
        # compile is paid on first need (eager calls only: under jit the status is a tracer)
        auto = options.get("stable_branch") is None
        lim = Limits.of(steps, max_iter, max_cuts)
        loads = jnp.asarray(loads, jnp.float64)
        eager = all(map(_is_concrete, jax.tree.leaves((g, loads, params, start))))
        if options.get("reuse") is None:
            options["reuse"] = self.newton_reuse if eager else 0.0
        options = {k: v for k, v in options.items() if not (k == "stable_branch" and v is None)}
        problem = self.problem(params)
        # eager solves keep the linear solver's last state in the Solution, and start from the
        # one the initial Solution kept: the predictor (modified Newton) or the preconditioner
        # (sparse) of the first step, and the implicit Jacobian at the new state, need no
        # factorisation of their own (``experiments/bench_cube3d.py``'s public-API control step)
        # (an empty state where none is kept: the first solve and the warm-started ones then
        # share one compiled program)
        kept = None
        if eager:
            kept = self._kept_linear(start, problem)
            kept = self.linear.empty(problem, jnp.float64) if kept is None else kept
        params0 = self._ramped_from(start, problem) if eager else None
        sol = solve_path_jit(self._driver(options, eager), problem, lim, start.u, start.g, g,
                             jnp.asarray(start.load, jnp.float64), loads, kept, params0)
        status = _concrete(sol.status)
        if auto and status == Status.UNSTABLE_TANGENT and (
                branching := self._driver({**options, "stable_branch": True}, eager)).switches:
            rest = solve_path_jit(branching, problem, lim, sol.u, sol.g, g, sol.load, loads, None,
                                  _params_at(params0, problem.params, sol.t))
            sol = joined(sol, rest)
            status = _concrete(sol.status)
        if eager:   # the parameters where the path stopped: the start of the next solve's ramp
            sol = sol._replace(params=_params_at(params0, problem.params, sol.t) or problem.params)
        if throw and status is not None and not Status.of(status).equilibrium:
            # under jax.jacfwd / jax.grad the fields are tracers: the error carries their values
            raise SolveError(Solution(*jax.tree.map(_concrete, tuple(sol))))
        if eager and status is not None and Status.of(status).equilibrium:
            self._check_penetration(problem, sol)
        return sol

    def _check_penetration(self, problem, sol) -> None:
        """Warn where a converged solve left contact points inside a tool: its status says
        CONVERGED, but the contact it describes is not what the tool allows."""
        terms = [t for t in problem.terms if isinstance(t, ContactTerm)]
        if not terms:
            return
        d = self.constraint.coefficients(sol.u, sol.g)
        for t in terms:
            gap = penetration(t, d, sol.load)
            if gap < 0:
                warnings.warn(f"the solve converged with points of contact {t.name!r} inside the tool (min gap "
                              f"{gap:.3g} < 0): raise Contact.pressure, or take more load steps (steps=...), "
                              "and check contact_forces(...).min_gap", ContactPenetrationWarning, stacklevel=4)

    def _ramped_from(self, start: Solution, problem):
        """The parameters that ``start`` was solved with where they differ from ``problem``'s
        (then the path ramps them, so that step cutting shrinks a pose change made at a
        converged state); None where they are the same, unknown or of another model."""
        p0 = start.params
        if p0 is None or jax.tree.structure(p0) != jax.tree.structure(problem.params):
            return None
        pairs = list(zip(jax.tree.leaves(p0), jax.tree.leaves(problem.params)))
        if any(np.shape(a) != np.shape(b) for a, b in pairs):
            return None
        if all(a is b or np.array_equal(np.asarray(a), np.asarray(b)) for a, b in pairs):
            return None
        return p0

    def _driver(self, options, eager: bool) -> LoadPath:
        """``solver(**options)``, keeping the linear state in the Solution where ``eager``."""
        driver = self.solver(**options)
        return dataclasses.replace(driver, keep_linear=True) if eager else driver

    def _kept_linear(self, sol: Solution, problem):
        """``sol.linear`` where it is a state of this model's linear solver (a Solution of
        another model, or one that kept none: None)."""
        state = sol.linear
        if state is None:
            return None
        want = jax.eval_shape(lambda: self.linear.empty(problem, jnp.float64))
        if jax.tree.structure(state) != jax.tree.structure(want):
            return None
        same = all(np.shape(a) == b.shape and jnp.result_type(a) == b.dtype
                   for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(want)))
        return state if same else None

    @property
    def newton_reuse(self) -> float:
        """The Newton ``reuse`` of an eager ``solve`` where none is given: the choice's
        ``newton_reuse`` (modified Newton) on the dense path; 0 (full Newton) on the sparse and
        Krylov paths, which already keep their factorisation or hierarchy as a preconditioner,
        and where a term's tangent changes too fast for a kept one (``Term.modified_newton``)."""
        smooth = all(t.modified_newton for t in self._problem.terms)
        return self.choice.newton_reuse if self.linear.modified_newton and smooth else 0.0

    def directions(self, name: str, rigid: bool = True):
        """Unit prescribed-value directions (m, Nb, d) that drive set ``name``: d rigid
        translations, or one per particle and component (m = n_set * d)."""
        self._check_set(name)
        sl = self.sets.slices[name]
        Nb, d = len(self.sets.bnd), self.dim
        if rigid:
            G = np.zeros((d, Nb, d))
            for a in range(d):
                G[a, sl, a] = 1.0
            return jnp.asarray(G)
        n = sl.stop - sl.start
        G = np.zeros((n * d, Nb, d))
        for i in range(n):
            for a in range(d):
                G[i * d + a, sl.start + i, a] = 1.0
        return jnp.asarray(G)

    def _point_tables(self, points):
        """Device arrays (idx, psi) of the shape functions at ``points``, cached per point
        set: a repeated ``displacement`` or ``jacobian`` at the same points would otherwise
        re-evaluate the RK shape functions (a KD-tree query and moment matrices in NumPy)
        each call, a large share of a needle-loop increment (``experiments/bench_sweep.py``)."""
        X = np.asarray(points, np.float64)
        key = (X.shape, X.tobytes())
        cache = self.__dict__.setdefault("_point_cache", {})
        if key not in cache:
            sf = self.shape_functions(X, gradients=False)
            if len(cache) >= 64:
                cache.clear()
            cache[key] = (jnp.asarray(sf.idx), jnp.asarray(sf.psi))
        return cache[key]

    def _jacobian_tables(self, points, driven: str, rigid: bool):
        """Device arrays (idx, psi, G) for ``jacobian`` (shape functions cached per point
        set, ``_point_tables``)."""
        return (*self._point_tables(points), self.directions(driven, rigid))

    def jacobian(self, sol: Solution, driven: str, points, method: str = "implicit",
                 eps: float = 1e-6, scheme: str = "central", rigid: bool = True, params=None,
                 rtol: float = 1e-12):
        """J = d(displacement at points)/d(displacement of the driven set): (P*d, m), m = d for
        a rigidly driven set (else n_set*d, per particle and component).

        "implicit": m solves K_ff du_f = -K_fg dg at the converged state (no re-solve), with a
        factorisation of K_ff there; where the Solution kept its solve's last factorisation
        (``Solution.linear``, of an iterate next to it), conjugate gradients with the exact
        Hessian-vector products, preconditioned by it, to the relative residual ``rtol``
        instead (no factorisation). "fd": the thesis' Algorithm 4: perturb each direction by
        eps, re-solve from the converged state, restore (``scheme`` "forward" or
        "central")."""
        if method not in ("implicit", "fd"):
            raise ValueError(f"unknown Jacobian method {method!r}: choose 'implicit' or 'fd'")
        if scheme not in ("forward", "central"):
            raise ValueError(f"unknown difference scheme {scheme!r}: choose 'forward' or 'central'")
        self.check_solution(sol)
        idx, psi, G = self._jacobian_tables(points, driven, rigid)
        P = idx.shape[0]
        if method == "implicit":
            if not (isinstance(rtol, (int, float)) and 0 < rtol < 1):
                raise ValueError(f"rtol must be a number in (0, 1), got {rtol!r}")
            problem = self.problem(params)
            kept = self._kept_linear(sol, problem)
            J = implicit_jacobian(problem, self.linear, sol.u, sol.g, sol.load, G, idx, psi, kept,
                                  refine=0.0 if kept is None else float(rtol))
            return J.reshape(P * self.dim, -1)
        if not (np.isfinite(eps) and eps > 0):
            raise ValueError(f"eps must be positive, got {eps}")

        def at(g):  # Algorithm 4: solve from the saved state; ``sol`` itself is never modified
            s = self.solve_g(g, initial=sol, params=params, loads=sol.load)
            return _point_values_jit(self.constraint, idx, psi, s.u, s.g).ravel()

        base = _point_values_jit(self.constraint, idx, psi, sol.u, sol.g).ravel()
        cols = []
        for dg in G:
            if scheme == "forward":
                cols.append((at(sol.g + eps * dg) - base) / eps)
            else:
                cols.append((at(sol.g + eps * dg) - at(sol.g - eps * dg)) / (2 * eps))
        return jnp.stack(cols, axis=1)

    # ------------------------------------------------------------------ post-processing
    def coefficients(self, sol: Solution):
        """(N, d) RK coefficients of a solution (essential ones by eq 3.22)."""
        self.check_solution(sol)
        return self.constraint.coefficients(sol.u, sol.g)

    def shape_functions(self, points, gradients=True):
        P = self.body.check_inside(points)
        return self.body.shape_functions(P, self.a, gradients=gradients, support_factor=self.support)

    def displacement(self, sol: Solution, points):
        """u(X) at reference points (P, d)."""
        self.check_solution(sol)
        idx, psi = self._point_tables(points)
        return _point_values_jit(self.constraint, idx, psi, sol.u, sol.g)

    def particle_displacements(self, sol: Solution):
        """u at every particle (N, d) (RK coefficients are not displacements)."""
        return self.displacement(sol, self.body.X)

    def deformation_gradient(self, sol: Solution, points):
        sf = self.shape_functions(points)
        return deformation_gradients(sf.idx, jnp.asarray(sf.dpsi), self.coefficients(sol))

    def stress(self, sol: Solution, points, kind: str = "cauchy", params=None):
        """Stress at points (P, d, d): 'pk2' (S), 'pk1' (P = F S) or 'cauchy' (eq 3.5)."""
        if kind not in ("pk2", "pk1", "cauchy"):
            raise ValueError(f"unknown stress kind {kind!r}: choose 'pk2', 'pk1' or 'cauchy'")
        P_ = self.body.check_inside(points)
        F = self.deformation_gradient(sol, P_)
        prm = self.material.point_params(P_)
        tensors = self.params_with(params)["strain"]["tensors"]
        prm = {k: jnp.asarray(v) for k, v in prm.items()}
        if params:
            prm.update({k: jnp.broadcast_to(jnp.asarray(v), (len(P_),)) for k, v in params.items()
                        if k in prm and not callable(v) and jnp.ndim(v) == 0})
        axes = {**{k: 0 for k in prm}, **{k: None for k in tensors}}
        S = jax.vmap(lambda E, p: pk2(self.material.W, E, p), in_axes=(0, axes))(
            green_lagrange(F), {**prm, **tensors})
        if kind == "pk2":
            return S
        if kind == "pk1":
            return F @ S
        J = det(F)
        return F @ S @ jnp.swapaxes(F, -1, -2) / J[:, None, None]

    def reactions(self, sol: Solution, params=None):
        """(Nb, d) generalized reaction at each essential particle: dPi/dg, the force the
        constraint exerts on the body (exact discrete reaction from the residual)."""
        self.check_solution(sol)
        return self.problem(params).reactions(sol.u, sol.g, sol.load)

    def reaction(self, sol: Solution, name: str, params=None):
        """(d,) resultant force exerted on the body by the essential set ``name``."""
        self._check_set(name)
        return jnp.sum(self.reactions(sol, params)[self.sets.slices[name]], axis=0)

    def energy(self, sol: Solution, params=None):
        return self.problem(params).energy_full(self.coefficients(sol), sol.load)[0]
