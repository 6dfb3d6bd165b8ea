"""The user-facing model: a façade over the discrete problem that the lower layers build once
(``discretise``, ``assemble``, ``linear_solver``), whose solves, Jacobians and post-processing
are functions over (model, solution) in the modules beside it.
"""
from __future__ import annotations

from typing import Mapping

import jax.numpy as jnp
import numpy as np

from ..discretise.body import Body
from ..discretise.discretisation import check_options as check_discretisation, discretise
from ..mechanics.build import BUILT_IN, assemble, check_options as check_mechanics
from ..mechanics.constraint import Essential
from ..mechanics.loads import SpringTerm, Springs
from ..mechanics.materials import Material
from ..mechanics.problem import Problem
from ..solvers.implicit import solve_path_jit
from ..solvers.path import LoadPath
from ..solvers.results import Limits, Solution
from . import inputs, jacobian, post, solving
from .linear import SolverChoice, check_options as check_linear, linear_solver
from .solving import SolveError

__all__ = ["Model", "SolveError", "SolverChoice"]


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
                 springs: Springs | None = None, terms=(), solver="auto",
                 factorisation: str = "auto", precision: str = "auto", choice: SolverChoice = SolverChoice(),
                 anti_locking: bool | None = None):
        # every option is checked before the first table is built
        check_discretisation(body, integration, essential, support, order)
        check_mechanics(material, anti_locking, terms)
        check_linear(solver, factorisation, precision, choice)
        disc = discretise(body, integration, essential, support, order, cell_size)
        built = assemble(disc, material, anti_locking, springs, body_force, tractions, terms)
        self.body, self.material, self.integration, self.choice = body, material, integration, choice
        self.support, self.a, self.sets = disc.support, disc.a, disc.sets
        self.volume, self.surface = disc.volume, disc.surface
        self._problem = built.problem
        self.linear = linear_solver(disc, built, solver, factorisation, precision, choice)
        self.point_tables = post.PointTables(self.shape_functions)
        self.unconstrained = inputs.unconstrained(self)

    # ------------------------------------------------------------------ the problem
    @property
    def springs(self) -> SpringTerm:
        """The springs' term (its points' shape functions ``psi`` and stiffnesses ``k``)."""
        return self._problem.term_of(SpringTerm)

    @property
    def constraint(self) -> Essential:
        """The essential constraint d = T(u, g) (``jaxrkpm.internal.Essential``)."""
        return self._problem.constraint

    @property
    def params(self) -> dict:
        """The model's parameters: term name -> that term's (``Problem.params``)."""
        return self._problem.params

    def problem(self, params=None) -> Problem:
        """The discrete problem with parameter overrides ``params`` (see ``params_with``): a
        jit-friendly pytree (see jaxrkpm.mechanics.problem)."""
        return self._problem.replace(params=self.params_with(params)) if params else self._problem

    def params_with(self, overrides: Mapping | None = None) -> dict:
        """The problem's parameters (term name -> its parameters, ``Problem.params``) with
        overrides: a material parameter's name -> scalar, (Q,) array, or field X -> (Q,); a
        term's name (e.g. "springs", a pressure's) -> its value (see the term)."""
        return inputs.params_with(self, overrides)

    def springs_at(self, points, stiffness=None) -> dict:
        """``params={"springs": ...}`` for the model's springs moved to ``points`` (S, d)
        (and, optionally, new stiffnesses): JAX, so a solve is differentiable in both. The
        points must stay where the particles of the spring region cover them."""
        return inputs.springs_at(self, points, stiffness)

    @property
    def dim(self) -> int:
        return self.body.dim

    @property
    def set_names(self) -> tuple:
        return self.sets.names

    def set_indices(self, name: str) -> np.ndarray:
        inputs.check_set(self, name)
        return self.sets.bnd[self.sets.slices[name]]

    def check_solution(self, sol, what: str = "solution") -> Solution:
        """``sol`` if it is a Solution of this model's shapes (u (Nf, d), g (Nb, d)); a
        ValueError naming the mismatch for one of another model (or not a Solution)."""
        return inputs.check_solution(self, sol, what)

    def prescribed(self, values: Mapping | None = None, base=None):
        """(Nb, d) prescribed displacements from name -> (d,) rigid translation or (n_set, d);
        sets not named keep ``base`` (default: zero)."""
        return inputs.prescribed(self, values, base)

    def initial(self) -> Solution:
        """The undeformed, unloaded equilibrium."""
        return inputs.initial(self)

    def __repr__(self) -> str:
        sets = {name: len(self.sets.bnd[sl]) for name, sl in self.sets.slices.items()}
        terms = [t.name for t in self._problem.terms if not isinstance(t, BUILT_IN)]
        return (f"Model({self.body.dim}D, {self.body.n} particles, {self.material.name}, {self.integration}, "
                f"support {self.support:g}, essential {sets or 'none'}"
                + (f", terms {terms}" if terms else "") + f", {type(self.linear).__name__})")

    # ------------------------------------------------------------------------ solve
    def solver(self, **options) -> LoadPath:
        """The solver of this model's solves: a ``LoadPath`` (adaptive load stepping) over a
        ``Newton`` with the model's linear solver, from the ``solve`` options (each a field of
        the object it tunes): ``rtol`` (the residual tolerance, ``Tolerance``), ``line_search``,
        ``armijo``, ``reuse``, ``check_stability`` (``Newton``), ``easy``, ``growth``,
        ``locate`` (``LoadPath``) and ``stable_branch`` (True: a ``BranchSwitch`` past critical
        points)."""
        return solving.load_path(self.linear, **options)

    @property
    def newton_reuse(self) -> float:
        """The Newton ``reuse`` of an eager ``solve`` where none is given: the choice's
        ``newton_reuse`` (modified Newton) on the dense path; 0 (full Newton) on the sparse and
        Krylov paths, which already keep their factorisation or hierarchy as a preconditioner,
        and where a term's tangent changes too fast for a kept one (``Term.modified_newton``)."""
        smooth = all(t.modified_newton for t in self._problem.terms)
        return self.choice.newton_reuse if self.linear.modified_newton and smooth else 0.0

    def solve(self, prescribed: Mapping | None = None, *, loads: float = 1.0, params=None,
              steps: int = 1, initial: Solution | None = None, throw: bool = True,
              max_iter: int = 25, solver=None, **options) -> Solution:
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
        jit/vmap; a number sets the Newton solver's ``reuse``. ``solver``: instead of the
        options, a path solver of one's own (``jaxrkpm.model.solving``: its ``linear`` and
        ``solve``), or a plan (``Direct``, ``BranchOnDemand``), run as it is.

        Differentiable (jax.jacfwd / jax.grad) in the prescribed values, ``loads`` and
        ``params`` by implicit differentiation of the converged equilibrium. The derivative
        of a FAILED solve (``throw=False``, or inside jit) is NaN: the kept state is not the
        equilibrium asked for, so it has no derivative to give."""
        start = self.initial() if initial is None else self.check_solution(initial, "initial")
        return self.solve_g(self.prescribed(prescribed, base=start.g), loads=loads, params=params, steps=steps,
                            initial=start, throw=throw, max_iter=max_iter, solver=solver, **options)

    def solve_g(self, g, *, loads: float = 1.0, params=None, steps: int = 1,
                initial: Solution | None = None, throw: bool = True, max_iter: int = 25,
                max_cuts: int = 10, solver=None, **options) -> Solution:
        """``solve`` with all prescribed values as one (Nb, d) array (see ``prescribed``)."""
        inputs.check_constrained(self)
        start = self.initial() if initial is None else self.check_solution(initial, "initial")
        g = inputs.check_g(self, g)
        if inputs.is_concrete(loads) and not np.isfinite(loads):
            raise ValueError(f"loads must be finite, got {loads}")
        loads = jnp.asarray(loads, jnp.float64)
        mode = solving.mode_of(self.newton_reuse, g, loads, params, start)
        run = solving.plan(self.linear, options, mode, solver)
        request = solving.Request(self.problem(params), Limits.of(steps, max_iter, max_cuts), start, g, loads)
        # the path solve looked up here, where a test may record the solver it is given
        return solving.outcome(run.run(request, mode, solve_path_jit), request, mode, throw)

    # ------------------------------------------------------------ derivatives, output
    def directions(self, name: str, rigid: bool = True):
        """Unit prescribed-value directions (m, Nb, d) that drive set ``name``: d rigid
        translations, or one per particle and component (m = n_set * d)."""
        return jacobian.directions(self, name, rigid)

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
        return jacobian.jacobian(self, sol, driven, points, method, eps, scheme, rigid, params, rtol)

    def coefficients(self, sol: Solution):
        """(N, d) RK coefficients of a solution (essential ones by eq 3.22)."""
        return post.coefficients(self, sol)

    def shape_functions(self, points, gradients=True):
        P = self.body.check_inside(points)
        return self.body.shape_functions(P, self.a, gradients=gradients, support_factor=self.support)

    def displacement(self, sol: Solution, points):
        """u(X) at reference points (P, d)."""
        return post.displacement(self, sol, points)

    def particle_displacements(self, sol: Solution):
        """u at every particle (N, d) (RK coefficients are not displacements)."""
        return self.displacement(sol, self.body.X)

    def deformation_gradient(self, sol: Solution, points):
        return post.deformation_gradient(self, sol, points)

    def stress(self, sol: Solution, points, kind: str = "cauchy", params=None):
        """Stress at points (P, d, d): 'pk2' (S), 'pk1' (P = F S) or 'cauchy' (eq 3.5)."""
        return post.stress(self, sol, points, kind, params)

    def reactions(self, sol: Solution, params=None):
        """(Nb, d) generalized reaction at each essential particle: dPi/dg, the force the
        constraint exerts on the body (exact discrete reaction from the residual)."""
        return post.reactions(self, sol, params)

    def reaction(self, sol: Solution, name: str, params=None):
        """(d,) resultant force exerted on the body by the essential set ``name``."""
        return post.reaction(self, sol, name, params)

    def energy(self, sol: Solution, params=None):
        return post.energy(self, sol, params)
