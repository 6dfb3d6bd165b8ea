"""The Newton-Krylov path (solver="krylov": CG preconditioned by algebraic multigrid) against
the direct one, and its failure reported as a status."""
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

import jaxrkpm as jr
from jaxrkpm.solvers.linalg import multigrid as krylov
from jaxrkpm.solvers.linalg.base import Stability
from tests.problems import unit_grid

PUSH = {"right": jnp.array([-0.2, 0.05, 0.0])}


@pytest.fixture(scope="module")
def cube5():
    """5^3 neo-Hookean cube, left face held, right face pushed 20% and sheared: the dense
    solution and a Krylov model."""
    body = unit_grid(5, 3)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    material = jr.NeoHookean(lam=1.0, mu=1.0)
    dense = jr.Model(body, material, essential=sets, solver="dense")
    model = jr.Model(body, material, essential=sets, solver="krylov")
    return dense, dense.solve(PUSH, steps=2), model


def test_krylov_solution_equals_the_direct_one(cube5):
    dense, ref, model = cube5
    assert model.linear.name == "krylov"
    sol = model.solve(PUSH, steps=2)
    assert sol.outcome == jr.Status.CONVERGED
    # both meet the Newton tolerance |r| <= 1e-10 x the force scale: the states agree to it
    u, u_ref = np.asarray(sol.u), np.asarray(ref.u)
    assert np.abs(u - u_ref).max() < 1e-9 * np.abs(u_ref).max()
    assert float(sol.residual_norm) <= 1e-9 * float(np.abs(np.asarray(ref.residual_norm)).max() + 1)
    # CG did the solves, and the hierarchy was built once for all of them (reused): the
    # solve's own statistics, returned with it
    assert int(sol.stats.cg_solves) == int(sol.iterations)
    assert int(sol.stats.factorisations) == 1 and int(sol.stats.cg_iterations) > 0
    # a linear solve with the state of a converged tangent (as implicit Jacobians use it)
    # solves K_ff x = r: checked with the dense K_ff of the state's own tangent blocks
    prob, linear = model.problem(), model.linear
    state = linear.state_at(prob, sol.u, sol.g)
    assert Stability.of(linear.stability(state)) == Stability.STABLE
    r = jnp.asarray(np.random.default_rng(0).standard_normal(sol.u.shape))
    x = np.asarray(linear.solve(state, r)).ravel()
    K = np.asarray(prob.dense_tangent(state.blocks))
    assert np.abs(K @ x - np.asarray(r).ravel()).max() < 1e-8 * np.abs(np.asarray(r)).max()


def test_krylov_not_converged_is_a_status(cube5, monkeypatch):
    _, _, model = cube5
    # two CG iterations cannot solve a 3D tangent to 1e-10: every Newton attempt's linear solve
    # fails, and the solve says so instead of taking the untrusted steps. (The host reads
    # maxiter at each call: the compiled solve of the test above serves, no new compile)
    monkeypatch.setattr(model.linear.system, "maxiter", 2)
    krylov.pool(model.linear.system).clear()
    sol = model.solve(PUSH, steps=2, throw=False, max_cuts=1)
    assert sol.outcome == jr.Status.LINEAR_SOLVE
    assert float(sol.t) == 0.0
    with pytest.raises(jr.SolveError, match="iterative linear solver"):
        model.solve(PUSH, steps=2, max_cuts=1)
    assert model.linear.system.replace(maxiter=7).maxiter == 7
    with pytest.raises(ValueError, match="maxiter must be a positive integer"):
        model.linear.system.replace(maxiter=0)
    with pytest.raises(ValueError, match="unknown solver 'amg': choose 'auto', 'dense', 'sparse', 'krylov'"):
        jr.Model(model.body, model.material, solver="amg")


def test_pardiso_pattern_holds_the_lower_saddle_point_matrix():
    """The saddle-point matrix PARDISO factorises (lower triangle, built from the pairs by
    ``sparse.lower_pattern``) equals the lower triangle of [K C^T; C 0] made densely, for
    tangent blocks that are not even symmetric (so a block taken transposed would show)."""
    from jaxrkpm.solvers.linalg import factorisations as sparse
    try:
        sparse.factoriser("pardiso")
    except ValueError:
        pytest.skip("Intel MKL (PARDISO) is not installed")
    body = jr.Body.grid((4, 3, 3), 0.5)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1.5 - 1e-9)}
    model = jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets, solver="sparse", factorisation="pardiso")
    S = model.linear.system
    pi, pj = np.asarray(model.problem().pairs.i), np.asarray(model.problem().pairs.j)
    blocks = np.random.default_rng(1).standard_normal((len(pi), 3, 3))
    K = np.zeros((body.n * 3, body.n * 3))
    for p in range(len(pi)):
        K[pi[p] * 3:pi[p] * 3 + 3, pj[p] * 3:pj[p] * 3 + 3] = blocks[p]
    C = np.zeros((S.nc, S.n_dof))
    Cf = S.elimination.Cf.toarray()
    C[:, S.elimination.free_dofs] = Cf
    Cb = S.elimination.Cb_lu.solve(np.eye(S.nc))          # C_b^-1: C_b is its inverse's inverse
    C[:, S.elimination.bnd_dofs] = np.linalg.inv(Cb)
    full = np.block([[K, C.T], [C, np.zeros((S.nc, S.nc))]])
    A = S.matrix(blocks).toarray()
    assert np.abs(A - np.tril(full)).max() < 1e-12 * np.abs(full).max()


def test_cg_that_stagnates_is_not_negative_curvature(cube5):
    """Host CG on K_ff: asked for a tolerance it cannot reach (1e-19, below round-off), it
    stops as MAX_ITERATIONS, never as negative curvature (which would report a stable state
    as UNSTABLE_TANGENT); on a K with a resolved negative eigenvalue it reports the curvature;
    and a solve whose CG cannot reach its tolerance says so instead of blaming pivots."""
    dense, ref, model = cube5
    system = model.linear.system.replace(maxiter=200)
    pool = krylov.pool(system)
    blocks = dense.problem().tangent_blocks(ref.u, ref.g)
    K = system.matrix(np.asarray(blocks))
    ml = system.hierarchy(np.asarray(blocks))
    b = np.random.default_rng(2).standard_normal(system.n_free)
    x, status, its, _ = system.cg(ml, K, b, rtol=1e-19)
    assert status == krylov.KrylovStatus.MAX_ITERATIONS and np.all(np.isfinite(x))
    x, status, its, _ = system.cg(ml, K, b, rtol=1e-8)
    assert status == krylov.KrylovStatus.CONVERGED
    # no curvature at all (p.Kp = 0: a singular or vanishing product) is not negative curvature
    _, status, _, _ = system.cg(ml, 0.0 * K, b, rtol=1e-8)
    assert status == krylov.KrylovStatus.MAX_ITERATIONS
    # the same K shifted by more than its lowest eigenvalue: a resolved negative curvature
    lam_max = np.abs(K.diagonal()).max()
    shifted = K - 1e-1 * lam_max * sp.eye(K.shape[0], format="bsr")
    _, status, _, _ = system.cg(ml, shifted.tobsr(blocksize=(3, 3)), b, rtol=1e-8)
    assert status == krylov.KrylovStatus.NEGATIVE_CURVATURE
    pool.clear()
    assert "Krylov solve that did not reach its tolerance" in jr.Status.STABILITY_UNKNOWN.message


def test_a_solution_prints_its_outcome_not_its_arrays(cube5):
    dense, ref, _ = cube5
    text = repr(ref)
    assert text.startswith("Solution(CONVERGED: converged in") and "nan" not in text.lower()
    assert len(text) < 300
