"""Past the first instability (issue 19): the stable-branch solve against the elastica, the
compressed square on stable states, and failure in bounded time.

The strip: 1 x 0.05, 81 x 5 particles (spacing 0.0125), neo-Hookean lam = mu = 1 (plane
strain: E' = 4 mu (lam + mu) / (lam + 2 mu) = 8/3), both ends clamped (every particle of an
end edge prescribed), the right end pushed along the axis with NO imperfection. Continuum
Euler load of the clamped-clamped strip: P_E = 4 pi^2 E' I / L^2 (effective length L / 2,
I = h^3 / 12 per unit thickness) = 1.0966e-3, at an axial strain P_E / (E' h) = 0.82%.
Post-buckling: the clamped-clamped elastica is four quarter waves, so with the parameter m =
k^2 of the pinned elastica of length L / 2: P / P_E = (2 K(m) / pi)^2 and the bending end
shortening is L (2 - 2 E(m) / K(m)); the strip also shortens axially by P L / (E' h)
(extensible correction, cos(theta) ~ 1 in it).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import ellipe, ellipk

import jaxrkpm as jr
from tests.problems import E_PLANE, EULER, H, L, elastica_force, path, strip_model

_TANGENT = jax.jit(lambda prob, u, g: prob.tangent(u, g))


def min_eig(model, sol) -> float:
    """Smallest eigenvalue of the dense K_ff at a solution."""
    return float(np.linalg.eigvalsh(np.asarray(_TANGENT(model.problem(), sol.u, sol.g)))[0])


@pytest.fixture(scope="module")
def strip():
    return strip_model()


@pytest.fixture(scope="module")
def strip_path(strip):
    """Warm-started solves to each end shortening: [(shortening, solution)]."""
    return path(strip)


def test_the_elastica_reference_is_the_textbook_one():
    """At vanishing amplitude the reference starts at Euler's load (after the axial strain)."""
    assert elastica_force(EULER / (E_PLANE * H) + 1e-7) == pytest.approx(EULER, rel=1e-4)
    # inextensible limit for a 10% shortening: P / P_E = 1.05299 (m from E/K = 0.95)
    m = brentq(lambda m: 2 - 2 * ellipe(m) / ellipk(m) - 0.1, 1e-14, 0.999)
    assert (2 * ellipk(m) / np.pi) ** 2 == pytest.approx(1.05299, rel=1e-4)


def test_strip_buckles_at_euler_load(strip, strip_path):
    """The solve passes the bifurcation of the perfect strip once, records it, and the force
    there is Euler's load within 2%."""
    (c0, below), (c1, through) = strip_path[:2]
    assert below.branch == 0 and through.branch == 1
    assert through.outcome == jr.Status.CONVERGED and "secondary branch" in through.message
    lo, hi = float(through.critical.t_stable[0]), float(through.critical.t_unstable[0])
    assert 0 < hi - lo <= 1 / 2 ** strip.solver().locate + 1e-12
    assert np.isnan(np.asarray(through.critical.t_stable[1:])).all()   # one critical point only
    eig = np.asarray(through.critical.eigenvalues[0])
    assert eig[0] < 0 < eig[1]                     # one eigenvalue crossed: a simple bifurcation
    # the critical mode: the strip's transverse (y) deflection, symmetric about mid-span
    mode = np.asarray(through.critical.mode[0])
    assert np.linalg.norm(mode[:, 1]) > 5 * np.linalg.norm(mode[:, 0])
    # the force at the last stable state before the bifurcation
    c_crit = c0 + lo * (c1 - c0)
    at = strip.solve({"right": jnp.array([-c_crit * L, 0.0])}, initial=below, stable_branch=True)
    force = -float(strip.reaction(at, "right")[0])
    print(f"bifurcation at shortening {100 * c_crit:.3f}%: P = {force:.5e}, Euler {EULER:.5e} "
          f"({100 * (force / EULER - 1):+.2f}%)")
    assert force == pytest.approx(EULER, rel=0.02)


def test_strip_follows_the_elastica(strip, strip_path):
    """Past Euler's load the end force follows the elastica within 3% up to a 10% end
    shortening, the strip deflects sideways, and every state is stable."""
    for c, sol in strip_path:
        assert sol.outcome == jr.Status.CONVERGED
        assert min_eig(strip, sol) > 0                       # K_ff positive definite
        force = -float(strip.reaction(sol, "right")[0])
        if c * L > EULER / (E_PLANE * H):
            ref = elastica_force(c)
            print(f"shortening {100 * c:4.1f}%: P / P_E = {force / EULER:.4f}, elastica {ref / EULER:.4f}")
            assert force == pytest.approx(ref, rel=0.03)
        else:
            assert force == pytest.approx(E_PLANE * H * c, rel=0.02)   # straight: axial stiffness
    sol = strip_path[-1][1]
    mid = np.asarray(strip.displacement(sol, [[0.5 * L, 0.5 * H]]))[0]
    # the clamped elastica's mid-span deflection at 10% shortening is about 0.2 L
    assert 0.1 * L < abs(mid[1]) < 0.3 * L


# ---------------------------------------------------- the compressed square, failure in bounded time
def block_model(n: int, material, integration: str = "gauss") -> jr.Model:
    """Unit square, n x n particles: "wall" (x = 0) held, "edge" (x = 1) moved rigidly
    (the set-up of experiments/compress_block.py, which runs the issue's 33x33 cases)."""
    body = jr.Body.grid((n, n), 1.0 / (n - 1))
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "edge": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    return jr.Model(body, material, integration=integration, essential=sets)


@pytest.fixture(scope="module")
def fung_block():
    return block_model(9, jr.Fung(alpha=1.0, beta=1.0))


@pytest.mark.parametrize("case", ["compression", "compression_shear"])
def test_square_reaches_full_load_on_stable_states(fung_block, case):
    """20% compression (Fung) and 20% compression + 10% shear (Quadratic) between a fixed and
    a rigidly moved edge reach the full load, on a stable state (9x9 Gauss here; 33x33 and
    SCNI/MSCNI in experiments/compress_block.py)."""
    model = fung_block if case == "compression" else block_model(9, jr.Quadratic(alpha=1.0))
    push = [-0.2, 0.0] if case == "compression" else [-0.2, 0.1]
    sol = model.solve({"edge": jnp.array(push)}, steps=10)
    assert sol.outcome == jr.Status.CONVERGED and float(sol.t) == 1.0
    assert min_eig(model, sol) > 0


def test_failure_costs_a_small_multiple_of_a_converging_solve(fung_block):
    """A solve that cannot proceed (60% compression: the path stops near 31%, where the Fung
    square's tangent loses positive definiteness and no stable state is found) gives up after
    a bounded amount of work (the load path's budget: failed attempts may cost failed_work x
    the larger of its useful work and steps x easy, plus 2 x max_iter): its Newton iterations
    at most 4x those of a converging solve of the same model, steps and size (work is counted
    in iterations, not timed: no test asserts a wall-clock time)."""
    good = fung_block.solve({"edge": jnp.array([-0.2, 0.0])}, steps=10, throw=False)
    bad = fung_block.solve({"edge": jnp.array([-0.6, 0.0])}, steps=10, throw=False)
    assert good.converged and not bad.converged and 0.3 < 0.6 * float(bad.t) < 0.4
    print(f"converging: {int(good.iterations)} iterations; failing ({bad.outcome.name} at "
          f"{60 * float(bad.t):.1f}%): {int(bad.iterations)} iterations, {int(bad.cuts)} cuts")
    # without the budget and the stop after a failed switch the failing solve took about twice
    # the iterations it takes now
    assert int(bad.iterations) <= 4 * int(good.iterations)


# ------------------------------------------- the stable-branch solve on one small critical point
def test_small_strip_passes_its_bifurcation_in_one_solve():
    """A coarse strip (41 x 3 particles, same 1 x 0.05 strip) shortened by 2% in one solve:
    the stable-branch solve brackets the bifurcation (one eigenvalue crossing, at Euler's
    axial strain), leaves along the transverse mode and ends CONVERGED on a stable buckled
    state whose end force is the elastica's; the same solve without it stops there with
    UNSTABLE_TANGENT. Fails if locating, the mode kick, the descent or the bookkeeping break."""
    strip = strip_model(41, 3)
    push = {"right": jnp.array([-0.02 * L, 0.0])}
    sol = strip.solve(push, steps=4, stable_branch=True, throw=False)
    assert sol.outcome == jr.Status.CONVERGED and float(sol.t) == 1.0 and int(sol.branch) == 1
    eig = np.asarray(sol.critical.eigenvalues[0])
    assert eig[0] < 0 < eig[1]
    lo, hi = (0.02 * float(sol.critical.t_stable[0]), 0.02 * float(sol.critical.t_unstable[0]))
    axial = EULER / (E_PLANE * H)                  # the shortening at Euler's load, 0.82%
    assert lo <= axial * 1.05 and hi >= axial * 0.95 and hi - lo <= 0.02 / 4 / 2 ** strip.solver().locate + 1e-12
    mode = np.asarray(sol.critical.mode[0])
    assert np.linalg.norm(mode[:, 1]) > 5 * np.linalg.norm(mode[:, 0])
    assert min_eig(strip, sol) > 0
    assert -float(strip.reaction(sol, "right")[0]) == pytest.approx(elastica_force(0.02), rel=0.03)
    plain = strip.solve(push, steps=4, throw=False, stable_branch=False)
    assert plain.outcome == jr.Status.UNSTABLE_TANGENT and 0.02 * float(plain.t) <= axial * 1.05
    # the default (stable_branch None): the plain solve, then from its last stable state the
    # stable-branch solve, one Solution whose fractions are of the whole path
    auto = strip.solve(push, steps=4, throw=False)
    assert auto.outcome == jr.Status.CONVERGED and float(auto.t) == 1.0 and int(auto.branch) == 1
    assert int(auto.iterations) > int(plain.iterations) and int(auto.steps) > int(plain.steps)
    assert float(auto.critical.t_stable[0]) >= float(plain.t) - 1e-12
    assert 0.02 * float(auto.critical.t_stable[0]) <= axial * 1.05 <= 0.02 * float(auto.critical.t_unstable[0]) * 1.1
    np.testing.assert_allclose(np.asarray(strip.reaction(auto, "right")), np.asarray(strip.reaction(sol, "right")),
                               rtol=1e-6, atol=1e-12)


def test_branch_switch_gives_up_at_once_where_the_square_collapses(fung_block):
    """Past the 9x9 Fung square's last stable state under 60% compression (near 31%) the
    energy has no minimum with det F > 0: an exact trust-region minimisation 0.12% further
    (``jaxrkpm.solvers.minimise.stable_beyond``) drives det F to ~0 with |r| = O(1). The solve stops at
    that last stable state, and its branch switch, whose descent runs into det F = 0, gives up
    at once (``COLLAPSE_DET``) instead of spending its iteration cap: the stable-branch solve
    costs no more Newton iterations than the plain one (82 against 63 without the stop)."""
    from jaxrkpm.solvers.minimise import minimise, stable_beyond

    push = {"edge": jnp.array([-0.6, 0.0])}
    plain = fung_block.solve(push, steps=10, throw=False, stable_branch=False)
    sol = fung_block.solve(push, steps=10, throw=False, stable_branch=True)
    assert sol.outcome == jr.Status.UNSTABLE_TANGENT and float(sol.t) == pytest.approx(float(plain.t))
    assert 0.3 < 0.6 * float(sol.t) < 0.32 and min_eig(fung_block, sol) > 0
    assert int(sol.iterations) <= int(plain.iterations) + 2
    # minima every 0.2% of the load (the solve stopped on a step of 1/(10 x 2**cuts))
    past = stable_beyond(fung_block.problem(), sol, fung_block.prescribed(push), fraction=0.002 / (1 - float(sol.t)))
    assert past["reached"] == 0.0 and past["failed_at"] > 0   # the solve stopped at the end of the stable path
    assert past["collapse"] and past["min_detF"] < 1e-6 and past["residual"] > 1e-4 * past["force_scale"]
    # the check is not blind: it finds the stable states of the 0.6% before the end
    near = fung_block.solve({"edge": jnp.array([-0.6 * (float(sol.t) - 0.01), 0.0])}, steps=10)
    back = stable_beyond(fung_block.problem(), near, sol.g, fraction=0.5)
    assert back["full"] and "failed_at" not in back
    with pytest.raises(ValueError, match="fraction"):
        stable_beyond(fung_block.problem(), near, sol.g, fraction=0.0)
    with pytest.raises(ValueError, match="inverts the material"):   # the undeformed state at 18% compression
        minimise(fung_block.problem(), np.zeros(sol.u.shape), sol.g, radius=0.01)
