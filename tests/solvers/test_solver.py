"""Model and Newton solve: patch tests, convergence, reactions, statuses, errors."""
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.solvers.linalg import factorisations as jsparse
from jaxrkpm.solvers.linalg.base import Stability
from jaxrkpm.thesis.studies import cantilever

F0_2D = np.array([[1.1, 0.2], [-0.1, 0.95]])           # general, non-symmetric
F0_3D = np.array([[1.05, 0.1, -0.05], [0.02, 0.97, 0.08], [-0.06, 0.03, 1.1]])
MATERIALS = {
    "Fung": jr.Fung(alpha=1.0, beta=1.0),
    "NeoHookean": jr.NeoHookean(lam=2.0, mu=1.0),
    "SVK": jr.SaintVenantKirchhoff(lam=1.0, mu=1.0),
    "Quadratic": jr.Quadratic(alpha=3.0),
}


def counts(stats) -> dict:
    """A solve's LinearStats as plain counts (its host seconds left out)."""
    return {k: v for k, v in stats.as_dict().items() if not k.endswith("_s")}


def boundary_model(n, material, dim=2):
    body = jr.Body.grid((n,) * dim, 1.0 / (n - 1))
    bnd = body.select(lambda X: (X.min(1) < 1e-9) | (X.max(1) > 1 - 1e-9))
    return body, bnd, jr.Model(body, material, essential={"boundary": bnd})


def patch_error(n, material, F0):
    body, bnd, model = boundary_model(n, material, F0.shape[0])
    G = F0 - np.eye(F0.shape[0])
    sol = model.solve({"boundary": body.X[bnd] @ G.T})
    interior = np.setdiff1d(np.arange(body.n), bnd)
    u = np.asarray(model.particle_displacements(sol))
    err_u = np.abs(u[interior] - body.X[interior] @ G.T).max()
    err_F = np.abs(np.asarray(model.deformation_gradient(sol, body.X[interior])) - F0).max()
    err_bnd = np.abs(u[bnd] - body.X[bnd] @ G.T).max()
    return err_u, err_F, err_bnd


@pytest.mark.parametrize("name", MATERIALS)
def test_affine_patch_2d(name):
    err_u, err_F, err_bnd = patch_error(9, MATERIALS[name], F0_2D)
    print(f"patch 2D {name}: interior |u err| {err_u:.2e}, |F err| {err_F:.2e}")
    # Gauss quadrature of rational RK functions and the nodal (not edge-wise) essential BCs
    # of the transformation method leave a small, bounded interior error (O(h), see below).
    assert err_u < 5e-4 and err_F < 3e-3
    assert err_bnd < 1e-10                      # essential particles hit their values


def test_patch_error_falls_with_refinement():
    e5 = patch_error(5, MATERIALS["NeoHookean"], F0_2D)[0]
    e17 = patch_error(17, MATERIALS["NeoHookean"], F0_2D)[0]
    print(f"patch 2D: 5x5 {e5:.2e}, 17x17 {e17:.2e}")
    assert e17 < e5 / 3


def test_affine_patch_3d():
    err_u, err_F, err_bnd = patch_error(4, MATERIALS["NeoHookean"], F0_3D)
    print(f"patch 3D: interior |u err| {err_u:.2e}, |F err| {err_F:.2e}")
    assert err_u < 2e-3 and err_F < 1e-2 and err_bnd < 1e-10


def test_timoshenko_cantilever_converges():
    res = cantilever.convergence((1 / 4, 1 / 8, 1 / 16))
    print("cantilever", res)
    e = res["relative_l2_error"]
    assert e[0] < 5e-3 and e[2] < 1e-4
    assert e[0] > e[1] > e[2]
    assert min(res["rates"]) > 1.5


def compressed_block(n, material=MATERIALS["NeoHookean"], solver="auto"):
    body = jr.Body.grid((n, n), 1.0 / (n - 1))
    model = jr.Model(body, material, essential={"wall": body.select(lambda X: X[:, 0] < 1e-9),
                                                "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)},
                     solver=solver)
    sol = model.solve({"right": jnp.array([-0.3, 0.05])}, steps=5)
    probes = np.array([[0.5, 0.5], [0.5, 1.0], [0.25, 0.0]])
    return np.asarray(model.displacement(sol, probes))


@pytest.mark.slow(reason="a third convergence check, at large deformation against a 33x33 reference solve; the "
                         "default run checks convergence rates on Timoshenko's cantilever and a manufactured "
                         "solution (tests/discretise/test_mesh.py)")
def test_large_deformation_against_fine_reference():
    # the reference by the sparse solver: the same equilibrium (the dense one agrees to 1e-12 here)
    # for half the CPU time of 2178 dense unknowns
    ref = compressed_block(33, solver="sparse")
    errs = [np.abs(compressed_block(n) - ref).max() for n in (5, 9, 17)]
    print("30% compression, max probe error vs 33x33:", errs)
    assert errs[0] > errs[1] > errs[2]
    assert errs[2] < 2e-3 * np.abs(ref).max() * 10


@pytest.fixture(scope="module")
def stretched():
    """9x5 SVK block: homogeneous uniaxial stretch (lateral faces traction free)."""
    lam, mu, l1 = 1.0, 1.0, 1.2
    body = jr.Body.grid((9, 5), 0.125)
    left = body.select(lambda X: X[:, 0] < 1e-9)
    right = body.select(lambda X: X[:, 0] > 1 - 1e-9)
    model = jr.Model(body, jr.SaintVenantKirchhoff(lam, mu), essential={"left": left, "right": right})
    E11 = 0.5 * (l1**2 - 1)
    E22 = -lam * E11 / (lam + 2 * mu)           # S22 = 0
    l2 = np.sqrt(1 + 2 * E22)
    P11 = l1 * (lam * (E11 + E22) + 2 * mu * E11)

    def disp(X):
        return np.stack([(l1 - 1) * X[:, 0], (l2 - 1) * X[:, 1]], 1)

    sol = model.solve({"left": disp(body.X[left]), "right": disp(body.X[right])}, steps=2)
    return model, sol, P11 * 0.5, disp


def test_reaction_equals_analytic_resultant(stretched):
    model, sol, resultant, _ = stretched
    R = np.asarray(model.reaction(sol, "right"))
    print("uniaxial reaction", R, "analytic", resultant)
    assert R[0] == pytest.approx(resultant, rel=1e-4)
    assert abs(R[1]) < 1e-10
    assert np.asarray(model.reaction(sol, "left")) == pytest.approx(-R, abs=1e-12)


def test_essential_values_are_hit(stretched):
    model, sol, _, disp = stretched
    for name in ("left", "right"):
        X = model.body.X[model.set_indices(name)]
        assert np.abs(np.asarray(model.displacement(sol, X)) - disp(X)).max() < 1e-10


def test_body_force_balanced_by_reaction():
    body = jr.Body.polygon([[0.5, 0], [1, 0], [1, 1], [0, 1], [0, 0.5]], 0.1)
    top = body.select(lambda X: X[:, 1] > 1 - 1e-9)
    model = jr.Model(body, jr.NeoHookean(1.0, 1.0), essential={"top": top}, body_force=[0.05, -0.1])
    sol = model.solve()
    assert np.asarray(model.reaction(sol, "top")) == pytest.approx(-0.875 * np.array([0.05, -0.1]), abs=1e-12)
    assert np.abs(np.asarray(model.displacement(sol, body.X[top]))).max() < 1e-10


def assert_tangent_matches_central_differences(model, g):
    rng = np.random.default_rng(0)
    u = 0.05 * rng.standard_normal((len(model.sets.free), model.body.dim))
    prob = model.problem()
    K = np.asarray(prob.tangent(u, g))
    residual = jax.jit(prob.residual)
    n, eps = K.shape[0], 1e-6
    Kfd = np.empty_like(K)
    for i in range(n):
        e = np.zeros(n)
        e[i] = eps
        e = e.reshape(u.shape)
        Kfd[:, i] = (np.asarray(residual(u + e, g)) - np.asarray(residual(u - e, g))).ravel() / (2 * eps)
    assert np.abs(K - Kfd).max() < 1e-7 * np.abs(K).max()
    assert np.abs(K - K.T).max() < 1e-10 * np.abs(K).max()


def test_tangent_matches_central_differences():
    body, bnd, _ = boundary_model(4, MATERIALS["Fung"])
    model = jr.Model(body, MATERIALS["Fung"], essential={"wall": body.select(lambda X: X[:, 0] < 1e-9)})
    assert_tangent_matches_central_differences(model, jnp.zeros((len(model.sets.bnd), 2)))


@pytest.mark.parametrize("layout, components", [("opposite", 2), ("touching", 1)])
def test_tangent_eliminates_essential_components(layout, components):
    """K_ff eliminates the essential particles one component at a time (essential sets
    coupled to disjoint free particles apart, sets that touch together): the tangent still
    equals central differences of the residual."""
    body = jr.Body.grid((7, 7), 1.0 / 6)
    left, right, bottom = (body.select(f) for f in (lambda X: X[:, 0] < 1e-9, lambda X: X[:, 0] > 1 - 1e-9,
                                                     lambda X: X[:, 1] < 1e-9))
    sets = {"left": left, "right": right} if layout == "opposite" else \
        {"left": left, "bottom": np.setdiff1d(bottom, left)}
    model = jr.Model(body, MATERIALS["NeoHookean"], essential=sets)
    assert model.constraint.elim.A.shape[0] == components
    g = 0.03 * np.random.default_rng(1).standard_normal((len(model.sets.bnd), 2))
    assert_tangent_matches_central_differences(model, jnp.asarray(g))


@pytest.mark.parametrize("name", MATERIALS)
def test_pk2_and_material_tangent_match_central_differences(name):
    mat = MATERIALS[name]
    p = {k: jnp.asarray(v) for k, v in {**{k: np.asarray(v, float) for k, v in mat.params.items()},
                                        **mat.global_params(2)}.items()}
    E = np.array([[0.08, -0.05], [-0.05, -0.12]])
    S = np.asarray(jr.pk2(mat.W, jnp.asarray(E), p))
    C = np.asarray(jax.jacfwd(lambda e: jr.pk2(mat.W, e, p))(jnp.asarray(E)))
    eps = 1e-6
    for i in range(2):
        for j in range(2):
            dE = np.zeros((2, 2))
            dE[i, j] += eps / 2
            dE[j, i] += eps / 2            # a symmetric perturbation of the strain
            dW = (mat.W(jnp.asarray(E + dE), p) - mat.W(jnp.asarray(E - dE), p)) / (2 * eps)
            # dW along (e_ij + e_ji)/2 is S_ij (S symmetric)
            assert abs(dW - S[i, j]) < 1e-7 * max(1, np.abs(S).max())
            dS = (np.asarray(jr.pk2(mat.W, jnp.asarray(E + dE), p))
                  - np.asarray(jr.pk2(mat.W, jnp.asarray(E - dE), p))) / (2 * eps)
            assert np.abs(dS - 0.5 * (C[:, :, i, j] + C[:, :, j, i])).max() < 1e-6 * max(1, np.abs(C).max())
    assert np.allclose(S, S.T, atol=1e-14)


@pytest.fixture(scope="module")
def block9():
    body = jr.Body.grid((9, 9), 0.125)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    return body, sets, jr.Model(body, MATERIALS["NeoHookean"], essential=sets)


def test_tangent_chunked_assembly_matches_one_chunk(block9):
    """The pair-block assembly swept in windows of groups (large 3D tables) sums every group
    exactly once, also where the last window is shifted back to end at the last group: it
    equals the assembly of all groups in one piece, at a random deformed state."""
    prob = block9[2].problem()
    strain = prob.term("strain")
    rng = np.random.default_rng(3)
    u = 0.03 * rng.standard_normal((prob.n_free, 2))
    d = prob.coefficients(u, block9[2].prescribed({"right": jnp.array([0.1, 0.02])}))
    whole = np.asarray(strain.blocks(d, 1.0, prob.pairs))
    G, K = strain.groups.shape[0], strain.idx.shape[1]
    chunk = next(c for c in range(7, G) if G % c)     # a partial last window
    swept = np.asarray(replace(strain, block_budget=chunk * K * K * 4).blocks(d, 1.0, prob.pairs))
    assert G > 2 * chunk
    assert np.abs(swept - whole).max() < 1e-12 * np.abs(whole).max()


def test_det_by_cofactors_is_the_determinant():
    """jaxrkpm.det (cofactors up to 3x3, used by the log-det energies and the line search's
    det F) equals the LU determinant, and so do its first and second derivatives."""
    rng = np.random.default_rng(6)
    for d in (1, 2, 3, 4):
        A = jnp.asarray(np.eye(d) + 0.3 * rng.standard_normal((5, d, d)))
        assert np.abs(np.asarray(jr.det(A) - jnp.linalg.det(A))).max() < 1e-13
        f = lambda M: jnp.log(jnp.abs(jr.det(M)))
        g = lambda M: jnp.log(jnp.abs(jnp.linalg.det(M)))
        assert np.abs(np.asarray(jax.vmap(jax.hessian(f))(A) - jax.vmap(jax.hessian(g))(A))).max() < 1e-10


def test_3d_tangent_from_one_triangle_is_the_energy_hessian():
    """A 3D body's neighbour lists are long (K = 64 at a 5^3 cube): its pair blocks are formed
    for one triangle of each group's (K, K) blocks and completed by transposes. They equal
    the whole square's assembly, and the tangent equals the energy's Hessian (products with
    random vectors by autodiff), at a random deformed state."""
    body = jr.Body.grid((5, 5, 5), 0.25)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    model = jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets)
    prob = model.problem()
    strain = prob.term("strain")
    assert strain.idx.shape[1] // strain.half_part >= 2            # the triangle is taken
    rng = np.random.default_rng(4)
    u = 0.02 * rng.standard_normal((len(model.sets.free), 3))
    g = model.prescribed({"right": jnp.array([-0.1, 0.02, 0.0])})
    d = prob.coefficients(u, g)
    half = np.asarray(strain.blocks(d, 1.0, prob.pairs))
    whole = np.asarray(replace(strain, half_part=10**6).blocks(d, 1.0, prob.pairs))   # the whole square
    assert np.abs(half - whole).max() < 1e-12 * np.abs(whole).max()
    K = np.asarray(prob.tangent(jnp.asarray(u), g))
    grad = jax.grad(lambda v: prob.energy(v, g)[0])
    for v in rng.standard_normal((2,) + u.shape):
        Hv = np.asarray(jax.jvp(grad, (jnp.asarray(u),), (jnp.asarray(v),))[1]).ravel()
        assert np.abs(K @ v.ravel() - Hv).max() < 1e-10 * np.abs(Hv).max()


def test_jit_and_eager_agree():
    """The jitted residual, tangent and (test_jit_and_eager_solves_agree) Newton solve agree with
    eager (un-jitted) execution (a 3x3 block: eager execution dispatches every operation on its own)."""
    small = jr.Model(jr.Body.grid((3, 3), 0.5), MATERIALS["Fung"],
                     essential={"l": [0, 1, 2], "r": [6, 7, 8]})
    prob = small.problem()
    rng = np.random.default_rng(5)
    u = 0.02 * rng.standard_normal((len(small.sets.free), 2))
    g = small.prescribed({"r": jnp.array([-0.05, 0.02])})
    r_jit = jax.jit(lambda p, u, g: p.residual(u, g))(prob, u, g)
    K_jit = jax.jit(lambda p, u, g: p.tangent(u, g))(prob, u, g)
    with jax.disable_jit():
        r_eager = prob.residual(u, g)
        K_eager = prob.tangent(u, g)
    assert np.abs(np.asarray(r_jit) - np.asarray(r_eager)).max() < 1e-12 * np.abs(np.asarray(r_eager)).max()
    assert np.abs(np.asarray(K_jit) - np.asarray(K_eager)).max() < 1e-12 * np.abs(np.asarray(K_eager)).max()


@pytest.mark.slow(reason="the whole Newton solve executed eagerly, operation by operation")
def test_jit_and_eager_solves_agree():
    small = jr.Model(jr.Body.grid((3, 3), 0.5), MATERIALS["Fung"],
                     essential={"l": [0, 1, 2], "r": [6, 7, 8]})
    s_jit = small.solve({"r": jnp.array([-0.1, 0.05])}, steps=1)
    with jax.disable_jit():
        s_eager = small.solve({"r": jnp.array([-0.1, 0.05])}, steps=1)
    assert np.abs(np.asarray(s_jit.u) - np.asarray(s_eager.u)).max() < 1e-12
    assert int(s_jit.iterations) == int(s_eager.iterations)


def test_warm_start_continues_the_path(block9):
    _, _, model = block9
    direct = model.solve({"right": jnp.array([-0.2, 0.0])}, steps=2)
    half = model.solve({"right": jnp.array([-0.1, 0.0])})
    warm = model.solve({"right": jnp.array([-0.2, 0.0])}, initial=half)
    assert np.abs(np.asarray(direct.u) - np.asarray(warm.u)).max() < 1e-9
    assert int(warm.steps) == 1


@pytest.mark.parametrize("factorisation", ["pardiso", "superlu"])
def test_sparse_path_matches_dense(block9, factorisation):
    body, sets, dense = block9
    sparse = jr.Model(body, MATERIALS["NeoHookean"], essential=sets, solver="sparse",
                      factorisation=factorisation)
    assert sparse.linear.system.factorisation == factorisation
    a = dense.solve({"right": jnp.array([-0.2, 0.1])}, steps=2)
    b = sparse.solve({"right": jnp.array([-0.2, 0.1])}, steps=2)
    assert np.abs(np.asarray(a.u) - np.asarray(b.u)).max() < 1e-10
    # one factorisation, reused as the CG preconditioner by the later Newton iterations (the
    # solve's own statistics, returned with it)
    stats = counts(b.stats)
    assert stats["factorisations"] == 1 and stats["cg_solves"] == int(b.iterations) - 1
    assert stats["solves"] == int(b.iterations) and b.stats.factorise_s > 0
    # the factorisation is explicit solver state: the same solve again (the host holds
    # factorisations from the first) does the same work and gives the same result
    c = sparse.solve({"right": jnp.array([-0.2, 0.1])}, steps=2)
    assert counts(c.stats) == stats
    assert np.array_equal(np.asarray(b.u), np.asarray(c.u))


@pytest.mark.parametrize("copying", [False, True])
def test_host_callback_in_jit_and_vmap(copying, monkeypatch):
    """The host callback of the sparse and Krylov solvers: the same results through
    buffer_callback (XLA's buffers, read-only views) and the pure_callback fallback, under
    jit and vmap (one member at a time)."""
    from jaxrkpm.solvers.linalg import host as linear
    if copying:
        monkeypatch.setattr(linear, "buffer_callback", None)
    elif linear.buffer_callback is None:
        pytest.skip("this JAX has no buffer_callback")
    calls = []

    def host(a, b):
        calls.append(a.shape)
        return np.asarray(a) * 2 + np.asarray(b).sum(), np.int64(a.shape[0])

    out = (jax.ShapeDtypeStruct((3,), jnp.float64), jax.ShapeDtypeStruct((), jnp.int64))
    f = jax.jit(lambda a, b: linear.host_callback(host, out, a, b))
    a, b = jnp.arange(6.0).reshape(2, 3), jnp.ones((2, 4))
    x, n = jax.vmap(f)(a, b)
    assert np.array_equal(np.asarray(x), np.asarray(a) * 2 + 4) and np.array_equal(np.asarray(n), [3, 3])
    assert calls == [(3,), (3,)]
    if not copying:     # the views are XLA's own buffers: writing to them must fail
        def writes(a):
            a[0] = 1.0
            return a

        with pytest.raises(Exception, match="read-only"):
            jax.block_until_ready(jax.jit(lambda a: linear.host_callback(
                writes, jax.ShapeDtypeStruct((3,), jnp.float64), a))(a[0]))


def test_sparse_path_factorises_again_when_cg_slows(block9, monkeypatch):
    """A kept factorisation whose CG solves slow down (more than ``growth`` x the iterations
    per decade of its first) is replaced by the current tangent's after the solve: with
    growth 0 every CG solve is followed by a factorisation, and the path is the same."""
    body, sets, dense = block9
    sparse = jr.Model(body, MATERIALS["NeoHookean"], essential=sets, solver="sparse")
    monkeypatch.setattr(sparse.linear.system, "growth", 0.0)
    a = dense.solve({"right": jnp.array([-0.2, 0.1])}, steps=2)
    b = sparse.solve({"right": jnp.array([-0.2, 0.1])}, steps=2)
    assert np.abs(np.asarray(a.u) - np.asarray(b.u)).max() < 1e-10
    stats = counts(b.stats)
    assert stats["cg_solves"] >= 2 and stats["factorisations"] == 1 + stats["cg_solves"]
    assert b.outcome == jr.Status.CONVERGED    # stable: the new factorisations' inertia says so


@pytest.fixture(scope="module")
def block3d():
    """5x4x4 neo-Hookean block pushed and sheared, solved on the dense path with full Newton
    (reuse=0: the sparse path's iterations are full Newton's)."""
    body = jr.Body.grid((5, 4, 4), 0.25)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    push = {"right": jnp.array([-0.15, 0.05, -0.05])}
    return body, sets, push, jr.Model(body, MATERIALS["NeoHookean"], essential=sets).solve(push, steps=2, reuse=0)


@pytest.mark.parametrize("factorisation", ["pardiso", "superlu"])
def test_sparse_path_matches_dense_3d(block3d, factorisation, monkeypatch):
    """The sparse path solves as the dense one; PARDISO factorises in single precision by
    default (precision="auto") and its direct solves are refined to double accuracy."""
    body, sets, push, a = block3d
    sparse = jr.Model(body, MATERIALS["NeoHookean"], essential=sets, solver="sparse",
                      factorisation=factorisation)
    assert sparse.linear.system.single == (factorisation == "pardiso")
    assert not jr.Model(body, MATERIALS["NeoHookean"], essential=sets, solver="sparse",
                        factorisation=factorisation, precision="double").linear.system.single
    b = sparse.solve(push, steps=2)
    assert np.abs(np.asarray(a.u) - np.asarray(b.u)).max() < 1e-10
    assert int(a.iterations) == int(b.iterations)
    # the factorisation's inertia: K_ff has as many positive eigenvalues as free dofs
    prob, linear = sparse.problem(), sparse.linear
    state = jax.jit(lambda p, u, g: linear.state_at(p, u, g))(prob, b.u, b.g)
    assert int(state.inertia) == 0 and Stability.of(linear.stability(state)) == Stability.STABLE
    # a solve with the factorisation = the dense solve of K_ff
    r = jnp.asarray(np.random.default_rng(0).standard_normal(b.u.shape))
    x = np.asarray(linear.solve(state, r)).ravel()
    K = np.asarray(prob.tangent(b.u, b.g))
    assert np.abs(K @ x - np.asarray(r).ravel()).max() < 1e-9 * np.abs(np.asarray(r)).max()
    # an evicted factorisation is made again from the blocks the state carries: same result
    jsparse.pool(sparse.linear.system).clear()
    assert np.abs(np.asarray(linear.solve(state, r)).ravel() - x).max() < 1e-12 * np.abs(x).max()
    if factorisation == "pardiso":     # unrefined, the single-precision solve is far less exact
        monkeypatch.setattr(sparse.linear.system, "refinements", 0)
        x0 = np.asarray(linear.solve(state, r)).ravel()
        assert np.abs(K @ x0 - np.asarray(r).ravel()).max() > 1e-9 * np.abs(np.asarray(r)).max()


def test_unknown_factorisation_is_named(block9):
    body, sets, _ = block9
    with pytest.raises(ValueError, match="unknown factorisation 'cholmod'"):
        jr.Model(body, MATERIALS["NeoHookean"], essential=sets, factorisation="cholmod")


def test_failed_solve_reports_status_and_keeps_last_state(block9):
    _, _, model = block9
    sol = model.solve({"right": jnp.array([-1.3, 0.0])}, steps=2, throw=False, max_cuts=4)
    assert int(sol.status) != jr.Status.CONVERGED
    assert 0 < float(sol.t) < 1
    assert "last converged state is kept" in sol.message
    # the kept state is a genuine equilibrium at the reached load
    assert float(sol.residual_norm) < 1e-6
    with pytest.raises(jr.SolveError, match=r"stopped at \d+\.\d% of the increment") as info:
        model.solve({"right": jnp.array([-1.3, 0.0])}, steps=2, max_cuts=4)
    assert float(info.value.solution.t) == pytest.approx(float(sol.t))


def test_a_stopped_path_says_which_of_its_limits_stopped_it(block9):
    """A failed attempt is cut and retried until the path stops on the smallest load step
    allowed or once the failed attempts have spent their work budget: ``Solution.stopped``
    and the message name the one that happened (both were one status message, "... on the
    smallest step allowed (or once ... their work budget)")."""
    _, _, model = block9
    crush = {"right": jnp.array([-1.3, 0.0])}
    smallest = model.solve(crush, max_iter=1, max_cuts=0, stable_branch=False, throw=False)
    spent = model.solve(crush, steps=2, max_cuts=50, stable_branch=False, throw=False)
    assert smallest.stopped == jr.Stop.SMALLEST_STEP and int(smallest.cuts) == 1
    assert "on the smallest load step allowed" in smallest.message and "budget" not in smallest.message
    # 50 halvings are never reached: the failed attempts' work ends the path first
    assert spent.stopped == jr.Stop.WORK_BUDGET
    assert "spent their work budget" in spent.message and "smallest" not in spent.message
    good = model.solve({"right": jnp.array([-0.05, 0.0])})
    assert good.stopped == model.initial().stopped == jr.Stop.NONE


def test_bad_input_gives_clear_errors(block9):
    body, sets, model = block9
    with pytest.raises(ValueError, match="unknown essential set 'paddle'"):
        model.solve({"paddle": jnp.zeros(2)})
    with pytest.raises(ValueError, match="'right' is not finite"):
        model.solve({"right": jnp.array([np.nan, 0.0])})
    with pytest.raises(ValueError, match=r"must have shape \(2,\) \(rigid\) or \(9, 2\)"):
        model.solve({"right": jnp.zeros(3)})
    with pytest.raises(ValueError, match="essential set 'e' is empty"):
        jr.Model(body, MATERIALS["SVK"], essential={"e": body.select(lambda X: X[:, 0] > 5)})
    with pytest.raises(ValueError, match="essential sets 'wall' and 'again' overlap"):
        jr.Model(body, MATERIALS["SVK"], essential={**sets, "again": sets["wall"][:2]})
    with pytest.raises(ValueError, match="'beta' must be positive"):
        jr.Fung(alpha=1.0, beta=0.0)
    with pytest.raises(ValueError, match="'mu' must be positive"):
        jr.NeoHookean(lam=1.0, mu=-1.0)
    with pytest.raises(ValueError, match="'beta' must be positive"):
        jr.Model(body, jr.Fung(beta=lambda X: np.where(X[:, 0] > 0.5, -1.0, 1.0)))
    with pytest.raises(ValueError, match=r"outside the body"):
        model.displacement(model.initial(), [[0.5, 1.5]])
    with pytest.raises(ValueError, match="moment matrix is singular.*larger support"):
        jr.Model(body, MATERIALS["SVK"], support=0.6)
    with pytest.raises(ValueError, match="unknown material parameter 'gamma'"):
        model.solve({}, params={"gamma": 1.0})


def test_parameter_field_changes_the_answer():
    """A stiff inclusion is data: a field for mu."""
    body = jr.Body.grid((5, 5), 0.25)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9)}
    pull = [(lambda X: X[:, 0] > 1 - 1e-9, [0.02, 0.0])]
    soft = jr.Model(body, jr.NeoHookean(1.0, 1.0), essential=sets, tractions=pull)
    stiff = jr.Model(body, jr.NeoHookean(1.0, lambda X: np.where(X[:, 0] > 0.5, 100.0, 1.0)),
                     essential=sets, tractions=pull)
    us = np.asarray(soft.displacement(soft.solve(), [[1.0, 0.5]]))[0, 0]
    uf = np.asarray(stiff.displacement(stiff.solve(), [[1.0, 0.5]]))[0, 0]
    assert 0 < uf < 0.7 * us
    # and overriding the field at solve time reproduces the homogeneous answer
    back = np.asarray(stiff.displacement(stiff.solve(params={"mu": 1.0}), [[1.0, 0.5]]))[0, 0]
    assert back == pytest.approx(us, rel=1e-10)


@pytest.fixture(scope="module")
def column():
    """Slender clamped neo-Hookean column (width 0.1, length 1) for axial compression: Euler
    buckling (clamped-clamped) at the axial strain pi^2 w^2 / (3 L^2) = 3.29%."""
    body = jr.Body.grid((5, 41), 0.025)
    sets = {"bottom": body.select(lambda X: X[:, 1] < 1e-9), "top": body.select(lambda X: X[:, 1] > 1 - 1e-9)}
    return body, sets, jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets)


def _min_eig(model, sol):
    K = np.asarray(model.problem().tangent(sol.u, sol.g))
    return np.linalg.eigvalsh(K)[0], np.linalg.eigvalsh(K)[-1]


@pytest.mark.parametrize("solver", ["dense", "pardiso", "superlu"])
def test_buckling_column_reports_unstable_tangent(column, solver):
    body, sets, dense = column
    model = dense if solver == "dense" else jr.Model(body, dense.material, essential=sets,
                                                     solver="sparse", factorisation=solver)
    push = {"top": jnp.array([0.0, -0.1])}                     # 10% axial compression
    # the stop at the critical point (the stable-branch solve, the dense default, goes on:
    # tests/test_stability.py)
    sol = model.solve(push, steps=5, throw=False, max_cuts=6, stable_branch=False)
    assert int(sol.status) == jr.Status.UNSTABLE_TANGENT
    strain = 0.1 * float(sol.t)
    euler = np.pi**2 * 0.1**2 / 3
    print(f"{solver}: stopped at {100 * strain:.2f}% strain, Euler {100 * euler:.2f}%")
    assert strain == pytest.approx(euler, rel=0.05)
    lo, hi = _min_eig(dense, sol)
    assert 0 < lo < 1e-3 * hi                                   # last stable state: at the bifurcation
    if solver == "dense":
        with pytest.raises(jr.SolveError, match="UNSTABLE_TANGENT: the tangent K_ff is not positive definite"):
            model.solve(push, steps=5, max_cuts=2, stable_branch=False)
        # without the check Newton converges to the symmetric (saddle) branch: really unstable
        through = model.solve(push, steps=5, check_stability=False)
        assert _min_eig(dense, through)[0] < 0
    # below the buckling strain the same column is stable and converges
    assert int(model.solve({"top": jnp.array([0.0, -0.02])}, steps=2, throw=False).status) == jr.Status.CONVERGED
