"""The split tissue energies W = W_iso(C̄) + κ/2 (ln J)²: their small-strain limit is isotropic
linear elasticity with the stated μ and κ, the isochoric part ignores volume, uniaxial tension
in the incompressible limit follows each energy's closed form, fibres carry tension only, 2D is
plane strain, the barrier resists collapse, and bad parameters are named."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

import jaxrkpm as jr
from jaxrkpm.mechanics.tissue import cauchy_green_3d

MU = 1.3
OGDEN_MU, OGDEN_ALPHA = (0.63, 0.0012, -0.01), (1.3, 5.0, -2.0)
ENERGIES = {
    "neo_hookean": (jr.NearlyIncompressibleNeoHookean(MU, 50.0), MU),
    "mooney_rivlin": (jr.MooneyRivlin(0.4, 0.25, 50.0), 2 * (0.4 + 0.25)),
    "yeoh": (jr.Yeoh(0.5, 0.2, 0.05, 50.0), 1.0),
    "veronda_westmann": (jr.VerondaWestmann(0.8, 1.5, 50.0), 0.8 * 1.5),
    "hgo": (jr.HolzapfelGasserOgden(MU, 2.0, 0.8, [(1.0, 0.0, 0.0)], 50.0), MU),
    # three-term Ogden (rubber-like constants of Ogden 1972, scaled), μ = Σ μ_p α_p / 2
    "ogden": (jr.Ogden(OGDEN_MU, OGDEN_ALPHA, 50.0), 0.5 * float(np.dot(OGDEN_MU, OGDEN_ALPHA))),
}


def point(material, dim=3):
    """W(E) at one point with the material's plain parameters."""
    p = {k: jnp.asarray(float(np.asarray(v).reshape(-1)[0])) for k, v in material.params.items()}
    p.update({k: jnp.asarray(v) for k, v in material.global_params(dim).items()})
    return lambda E: material.W(E, p)


def strain_of(F):
    return 0.5 * (F.T @ F - jnp.eye(F.shape[0]))


def sym(rng, d):
    A = rng.standard_normal((d, d))
    return 0.5 * (A + A.T)


@pytest.mark.parametrize("name", ENERGIES)
def test_small_strain_limit_is_isotropic_linear_elasticity(name):
    """At E = 0: zero energy and stress, and d²W[δE, δE] = κ (tr δE)² + 2μ |dev δE|², in 3D
    and in 2D plane strain (δE33 = 0, dev taken in 3D). The HGO fibres are slack at rest (they
    engage in strict tension only)."""
    material, mu = ENERGIES[name]
    kappa = 50.0
    rng = np.random.default_rng(1)
    for d in (2, 3):
        W = point(material, d)
        E0 = jnp.zeros((d, d))
        assert abs(float(W(E0))) < 1e-14
        assert np.abs(np.asarray(jax.grad(W)(E0))).max() < 1e-13
        for _ in range(3):
            dE = jnp.asarray(sym(rng, d))
            second = float(jax.jvp(jax.grad(W), (E0,), (dE,))[1].ravel() @ dE.ravel())
            tr = float(jnp.trace(dE))
            dev2 = float(jnp.sum(dE * dE)) - tr ** 2 / 3.0
            expected = kappa * tr ** 2 + 2 * mu * dev2
            assert second == pytest.approx(expected, rel=1e-10), (d, second, expected)


@pytest.mark.parametrize("name", ENERGIES)
def test_the_isochoric_part_ignores_volume(name):
    """Under a pure dilation F = s I only U(J) = κ/2 (ln J)² remains (for the HGO energy in
    compression, where its fibres are slack; stretched, they carry load)."""
    material, _ = ENERGIES[name]
    W = point(material)
    for s in (0.7, 0.95) if name == "hgo" else (0.7, 0.95, 1.3):
        J = s ** 3
        assert float(W(strain_of(s * jnp.eye(3)))) == pytest.approx(25.0 * np.log(J) ** 2, rel=1e-12)
    if name == "hgo":
        assert float(W(strain_of(1.3 * jnp.eye(3)))) > 25.0 * np.log(1.3 ** 3) ** 2 * 1.01


def uniaxial_nominal_stress(material, lam):
    """Stretch lam along x, the lateral stretch t free (energy minimised over t): P11 = dW/dλ."""
    W = jax.jit(point(material))
    energy = lambda lam, t: W(strain_of(jnp.diag(jnp.array([lam, t, t]))))
    t = minimize_scalar(lambda t: float(energy(lam, t)), bracket=(0.9 / np.sqrt(lam), 1.1 / np.sqrt(lam)),
                        tol=1e-14).x
    return float(jax.grad(energy)(jnp.asarray(lam), jnp.asarray(t))), t


INCOMPRESSIBLE = {   # closed forms of P11 in incompressible uniaxial tension, I1 = λ² + 2/λ
    "neo_hookean": (jr.NearlyIncompressibleNeoHookean(MU, 1e4 * MU), lambda l: MU * (l - l ** -2)),
    "mooney_rivlin": (jr.MooneyRivlin(0.4, 0.25, 1e4), lambda l: 2 * (l - l ** -2) * (0.4 + 0.25 / l)),
    "yeoh": (jr.Yeoh(0.5, 0.2, 0.05, 1e4), lambda l: 2 * (l - l ** -2) * (
        0.5 + 2 * 0.2 * (l ** 2 + 2 / l - 3) + 3 * 0.05 * (l ** 2 + 2 / l - 3) ** 2)),
    "veronda_westmann": (jr.VerondaWestmann(0.8, 1.5, 1e4), lambda l: 2 * (l - l ** -2) * (
        0.8 * 1.5 * np.exp(1.5 * (l ** 2 + 2 / l - 3)) - 0.5 * 0.8 * 1.5 / l)),
    "hgo_along_fibre": (jr.HolzapfelGasserOgden(MU, 2.0, 0.8, [(1.0, 0.0, 0.0)], 1e4 * MU),
                        lambda l: MU * (l - l ** -2) + 2 * 2.0 * l * (l * l - 1) * np.exp(0.8 * (l * l - 1) ** 2)),
    "hgo_across_fibre": (jr.HolzapfelGasserOgden(MU, 2.0, 0.8, [(0.0, 1.0, 0.0)], 1e4 * MU),
                         lambda l: MU * (l - l ** -2)),
    "ogden": (jr.Ogden(OGDEN_MU, OGDEN_ALPHA, 1e4), lambda l: sum(
        m * (l ** (a - 1) - l ** (-a / 2 - 1)) for m, a in zip(OGDEN_MU, OGDEN_ALPHA))),
}


@pytest.mark.parametrize("name", INCOMPRESSIBLE)
def test_uniaxial_tension_in_the_incompressible_limit(name):
    """With κ = 10⁴ μ the body keeps its volume (t = λ^-1/2) and the stress is the energy's
    incompressible closed form, to O(μ/κ); across the fibres, the fibres (shortened) add nothing."""
    material, closed_form = INCOMPRESSIBLE[name]
    for lam in (1.1, 1.4):
        P, t = uniaxial_nominal_stress(material, lam)
        assert abs(t - lam ** -0.5) < 1e-3
        assert P == pytest.approx(closed_form(lam), rel=2e-3), (lam, P, closed_form(lam))


def test_dispersed_fibres_and_fibre_fields():
    """κ_d = 1/3 (fully dispersed) makes the fibre term isotropic: the same energy for a
    stretch along x and along y; a fibre field equals the constant direction it returns, and is evaluated once."""
    iso = point(jr.HolzapfelGasserOgden(MU, 2.0, 0.8, [(1.0, 0.0, 0.0)], 50.0, dispersion=1 / 3))
    Ex, Ey = strain_of(jnp.diag(jnp.array([1.2, 1.0, 1.0]))), strain_of(jnp.diag(jnp.array([1.0, 1.2, 1.0])))
    assert float(iso(Ex)) == pytest.approx(float(iso(Ey)), rel=1e-13)
    calls = []

    def fibre(X):
        calls.append(len(X))
        return np.tile([0.0, 2.0, 0.0], (len(X), 1))
    field = jr.HolzapfelGasserOgden(MU, 2.0, 0.8, fibre, 50.0)
    X = np.zeros((4, 3))
    params = field.point_params(X)
    assert calls == [4]                                   # one evaluation for the three components
    assert np.allclose(params["fibre0_y"], 2.0) and np.allclose(params["fibre0_x"], 0.0)
    p = {k: jnp.asarray(v[0]) for k, v in params.items()}
    const = point(jr.HolzapfelGasserOgden(MU, 2.0, 0.8, [(0.0, 1.0, 0.0)], 50.0))
    assert float(field.W(Ey, p)) == pytest.approx(float(const(Ey)), rel=1e-13)   # normalised


@pytest.mark.parametrize("name", ENERGIES)
def test_2d_is_plane_strain(name):
    """A 2D strain's energy is the 3D energy of the same strain with E33 = 0."""
    material, _ = ENERGIES[name]
    rng = np.random.default_rng(2)
    E2 = jnp.asarray(0.1 * sym(rng, 2))
    E3 = jnp.zeros((3, 3)).at[:2, :2].set(E2)
    assert float(point(material, 2)(E2)) == pytest.approx(float(point(material, 3)(E3)), rel=1e-13)
    assert np.allclose(np.asarray(cauchy_green_3d(E2)), np.asarray(jnp.eye(3) + 2 * E3))


def test_the_barrier_resists_collapse():
    """The thesis' Fung energy stays bounded as J → 0 (a compressed point can fold flat); with
    the barrier its energy grows without bound, adding exactly κ/2 (ln J)²."""
    fung = jr.Fung()
    walled = jr.with_barrier(fung, 10.0)
    W, Wb = point(fung, 2), point(walled, 2)
    energies = []
    for s in (0.5, 1e-2, 1e-4):
        E = strain_of(jnp.diag(jnp.array([1.0, s])))
        # (C = I + 2E loses C22 = s² to round-off relative to 1: ~1e-8 relative at s = 1e-4)
        assert float(Wb(E)) - float(W(E)) == pytest.approx(5.0 * np.log(s) ** 2, rel=1e-7)
        energies.append((float(W(E)), float(Wb(E))))
    assert energies[-1][0] - energies[-2][0] < 1e-3 * energies[-2][0]     # Fung: flat
    assert energies[-1][1] > 1.5 * energies[-2][1]                         # barrier: growing
    assert walled.name == "Fung+barrier" and walled.tensors is fung.tensors
    k = jr.bulk_modulus(1.0, 0.45)
    assert jr.with_barrier(fung, nu=0.45, mu=1.0).params["kappa"] == pytest.approx(k)


def test_parameters_by_name_and_checked():
    assert jr.NearlyIncompressibleNeoHookean(1.0, nu=0.499).params["kappa"] == pytest.approx(
        2 * 1.499 / (3 * 0.002))
    young = jr.NearlyIncompressibleNeoHookean.from_young(3.0, 0.25)
    assert young.params["mu"] == pytest.approx(1.2) and young.params["kappa"] == pytest.approx(2.0)
    field = jr.NearlyIncompressibleNeoHookean(lambda X: 1.0 + X[:, 0], nu=0.45)
    k = field.point_params(np.array([[0.0, 0.0], [1.0, 0.0]]))["kappa"]
    assert np.allclose(k, jr.bulk_modulus(1.0, 0.45) * np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match=r"nu must lie in \(-1, 0.5\), got 0.5"):
        jr.NearlyIncompressibleNeoHookean(1.0, nu=0.5)
    with pytest.raises(TypeError, match="kappa or Poisson's ratio nu"):
        jr.MooneyRivlin(0.4, 0.1, 10.0, nu=0.45)
    with pytest.raises(TypeError, match="kappa or Poisson's ratio nu"):
        jr.Yeoh(0.4)
    with pytest.raises(ValueError, match=r"MooneyRivlin: the small-strain shear modulus 2\(c10 \+ c01\)"):
        jr.MooneyRivlin(0.1, -0.3, 10.0)
    with pytest.raises(ValueError, match="'kappa' must be positive"):
        jr.VerondaWestmann(1.0, 1.0, -1.0)
    with pytest.raises(ValueError, match="fibre 0 must be a nonzero"):
        jr.HolzapfelGasserOgden(1.0, 1.0, 1.0, [(0.0, 0.0, 0.0)], 10.0)
    with pytest.raises(ValueError, match="one or two directions"):
        jr.HolzapfelGasserOgden(1.0, 1.0, 1.0, [(1.0, 0, 0)] * 3, 10.0)
    with pytest.raises(ValueError, match="dispersion must lie in"):
        jr.HolzapfelGasserOgden(1.0, 1.0, 1.0, (1.0, 0, 0), 10.0, dispersion=0.5)
    with pytest.raises(ValueError, match="already has a parameter 'kappa'"):
        jr.with_barrier(jr.NearlyIncompressibleNeoHookean(1.0, 10.0), 5.0)
    with pytest.raises(TypeError, match="nu needs the shear modulus"):
        jr.with_barrier(jr.Fung(), nu=0.45)


def test_ogden_is_exact_at_equal_stretches():
    """Ogden's stretch powers go through no eigenvector derivative: stress and tangent are
    finite at the undeformed state and at equi-biaxial stretch (repeated eigenvalues), the
    tangent there matches finite differences of the stress, α = 2 is the neo-Hookean energy
    (stress and tangent), the small-strain shear modulus is Σ μ_p α_p / 2, and the energy is
    objective."""
    ogden = point(jr.Ogden(OGDEN_MU, OGDEN_ALPHA, kappa=40.0))
    two = point(jr.Ogden([MU], [2.0], nu=0.45))
    neo = point(jr.NearlyIncompressibleNeoHookean(MU, nu=0.45))
    stress, tangent = jax.jit(jax.grad(ogden)), jax.jit(jax.hessian(ogden))
    stress2, tangent2 = jax.jit(jax.grad(two)), jax.jit(jax.hessian(two))
    stress_nh, tangent_nh = jax.jit(jax.grad(neo)), jax.jit(jax.hessian(neo))
    rng = np.random.default_rng(5)
    for F in (jnp.eye(3), jnp.diag(jnp.array([1.2, 1.2, 0.7])), jnp.diag(jnp.array([0.8, 1.1, 1.1])),
              jnp.eye(3) + 0.1 * jnp.asarray(rng.standard_normal((3, 3)))):
        E = strain_of(F)
        S, D = stress(E), tangent(E)
        assert np.all(np.isfinite(np.asarray(S))) and np.all(np.isfinite(np.asarray(D)))
        dE = jnp.asarray(sym(rng, 3))
        h = 1e-6
        fd = (stress(E + h * dE) - stress(E - h * dE)) / (2 * h)
        assert np.abs(np.asarray(fd - jnp.einsum("ijkl,kl->ij", D, dE))).max() < 1e-7
        assert np.abs(np.asarray(stress2(E) - stress_nh(E))).max() < 1e-13
        assert np.abs(np.asarray(tangent2(E) - tangent_nh(E))).max() < 1e-12
    # shear modulus: d²W/dγ² of simple shear at γ = 0 (J = 1: no volumetric part)
    shear = jax.grad(jax.grad(lambda g: ogden(strain_of(jnp.eye(3).at[0, 1].set(g)))))(0.0)
    assert float(shear) == pytest.approx(0.5 * np.dot(OGDEN_MU, OGDEN_ALPHA), rel=1e-12)
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    Q = jnp.asarray(Q * np.sign(np.linalg.det(Q)))
    F = jnp.eye(3) + 0.2 * jnp.asarray(rng.standard_normal((3, 3)))
    assert float(ogden(strain_of(Q @ F))) == pytest.approx(float(ogden(strain_of(F))), rel=1e-12)
    with pytest.raises(ValueError, match=r"Ogden: term 2 needs a nonzero alpha and mu \* alpha > 0"):
        jr.Ogden([1.0, 1.0], [2.0, -1.0], 10.0)
    with pytest.raises(ValueError, match="same length"):
        jr.Ogden([1.0, 1.0], [2.0], 10.0)


def test_affine_patch_with_scni_at_nu_049():
    """Through a Model: SCNI reproduces an affine deformation of a nearly incompressible
    (ν = 0.49) neo-Hookean square exactly, as for every other energy."""
    body = jr.Body.grid((5, 5), 0.25)
    boundary = body.select(lambda X: (X.min(1) < 1e-9) | (X.max(1) > 1 - 1e-9))
    model = jr.Model(body, jr.NearlyIncompressibleNeoHookean(1.0, nu=0.49), integration="scni",
                     essential={"boundary": boundary})
    F0 = np.array([[1.08, 0.15], [-0.05, 0.93]])
    sol = model.solve({"boundary": body.X[boundary] @ (F0 - np.eye(2)).T})
    inner = np.setdiff1d(np.arange(body.n), boundary)
    u = np.asarray(model.particle_displacements(sol))
    assert np.abs(u[inner] - body.X[inner] @ (F0 - np.eye(2)).T).max() < 1e-10
    assert np.abs(np.asarray(model.deformation_gradient(sol, body.X[inner])) - F0).max() < 1e-10


def test_the_barrier_carries_the_compressed_square_past_the_fold():
    """The 9x9 square (left edge held, right edge moved rigidly) in Fung with the barrier
    (kappa = Fung's shear modulus 509) reaches 40% compression on a stable state, far from
    collapse; the plain Fung square stops near 31% (tests/solvers/test_stability.py), the 33x33
    one at 19.6% (experiments/compress_block.py, where the barrier reaches the full 20%)."""
    body = jr.Body.grid((9, 9), 0.125)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "edge": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    model = jr.Model(body, jr.with_barrier(jr.Fung(alpha=1.0, beta=1.0), kappa=509.0), essential=sets)
    sol = model.solve({"edge": jnp.array([-0.4, 0.0])}, steps=10, throw=False, stable_branch=True)
    assert sol.outcome == jr.Status.CONVERGED and float(sol.t) == 1.0
    prob = model.problem()
    assert float(np.linalg.eigvalsh(np.asarray(jax.jit(prob.tangent)(sol.u, sol.g)))[0]) > 0
    assert float(prob.energy(sol.u, sol.g)[1]) > 0.3               # smallest det F: no corner folds


def test_hostile_constants_and_fields_are_named():
    """Constants and fields that were accepted silently, or failed with a raw error, are
    ValueErrors naming the bad thing."""
    for mu in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="bulk_modulus: the shear modulus mu must be positive and finite"):
            jr.bulk_modulus(mu, 0.3)
    with pytest.raises(ValueError, match="dispersion must lie in"):
        jr.HolzapfelGasserOgden(1.0, 1.0, 1.0, (1.0, 0, 0), 10.0, dispersion="0.1")
    body = jr.Body.grid((3, 3), 0.5)
    wall = {"w": body.select(lambda X: X[:, 0] < 1e-9)}
    flat = jr.HolzapfelGasserOgden(1.0, 1.0, 1.0, lambda X: np.stack([np.ones(len(X)), 0 * X[:, 0]], 1), 10.0)
    with pytest.raises(ValueError, match=r"fibre 0's field must return \(n, 3\) directions .* got shape \(\d+, 2\)"):
        jr.Model(body, flat, essential=wall)
    # an energy that reads E[2, 2] works in 3D; on a 2D body JAX would clamp the index
    reads_3d = jr.Material(lambda E, p: jnp.sum(E * E) + E[2, 2] ** 2, name="reads_3d")
    with pytest.raises(ValueError, match=r"reads_3d: the strain energy W\(E, params\) reads outside the 2x2 strain"):
        jr.Model(body, reads_3d, essential=wall)
    with pytest.raises(ValueError, match=r"order must be a whole number of integration points .* got 0"):
        jr.Model(body, jr.Fung(), essential=wall, order=0)
