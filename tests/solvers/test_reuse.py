"""Modified Newton (Newton(reuse=...)): a kept factorisation serves later iterations and the next
load step while the residual contracts; the equilibrium is full Newton's to the tolerance,
and the solve still stops where full Newton's does at an instability. One small clamped
strip (experiments.elastica) serves both: its compiled solves are shared. Eager dense solves
use it by default (``Model.newton_reuse``), so full Newton is asked for by reuse=0."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.model import model as model_module
from tests.problems import L, strip_model


@pytest.fixture(scope="module")
def strip():
    return strip_model(21, 3)


def push(model, shortening, **options):
    return model.solve({"right": jnp.array([-shortening * L, 0.0])}, steps=10, throw=False, **options)


def test_reuse_reaches_full_newton_equilibrium(strip):
    full, kept = push(strip, 0.02, reuse=0), push(strip, 0.02, reuse=0.1)
    assert full.converged and kept.converged
    # chord steps converge linearly: more (cheap) iterations than full Newton's, but the one
    # factorisation a load step is made where a Newton step finishes it (measured: 30
    # iterations against full Newton's 20; 40 when it came after the chord had converged)
    assert int(full.iterations) < int(kept.iterations) < 4 * 10
    assert float(jnp.abs(kept.u - full.u).max()) < 1e-8 * float(jnp.abs(full.u).max())
    prob = strip.problem()
    assert float(jnp.linalg.norm(prob.residual(kept.u, kept.g))) <= \
        1e-10 * max(float(prob.force_scale(prob.energy_residual(kept.u, kept.g)[3])), 1.0)


def test_reuse_still_stops_at_the_instability(strip):
    """Pushed past its Euler load, the strip stops with UNSTABLE_TANGENT at the same load
    as full Newton, on a stable state (convergence is declared only on a step factorised at
    its start; with the factorisation of an earlier iterate, measured, the solve went on to
    t = 0.6875 and a K_ff with a negative eigenvalue)."""
    # stable_branch=False: the stop itself (by default the solve would go on past it)
    full, kept = push(strip, 0.05, reuse=0, stable_branch=False), push(strip, 0.05, reuse=0.1, stable_branch=False)
    assert full.outcome == jr.Status.UNSTABLE_TANGENT
    assert kept.outcome == full.outcome
    assert float(kept.t) == pytest.approx(float(full.t), abs=1e-12)
    K = np.asarray(strip.problem().tangent(kept.u, kept.g))
    assert np.linalg.eigvalsh(K)[0] > 0           # the state kept is stable


class Recorded(Exception):
    pass


def test_eager_dense_solves_default_to_modified_newton(strip, monkeypatch):
    """reuse=None (default): modified Newton in an eager solve on the dense path, full Newton
    under jit (and vmap, where a vmapped cond would run both branches) and on the sparse path."""
    assert strip.newton_reuse == strip.choice.newton_reuse > 0
    default = push(strip, 0.02)
    assert int(default.iterations) == int(push(strip, 0.02, reuse=strip.choice.newton_reuse).iterations)
    assert int(default.iterations) != int(push(strip, 0.02, reuse=0).iterations)
    seen = []

    def record(driver, *args):     # the solve's static settings, then stop
        seen.append(driver.newton.reuse)
        raise Recorded

    monkeypatch.setattr(model_module, "solve_path_jit", record)
    g = strip.prescribed({"right": jnp.array([-0.02 * L, 0.0])})
    for call in (lambda: strip.solve_g(g), lambda: jax.jit(lambda g: strip.solve_g(g, throw=False))(g),
                 lambda: jax.vmap(lambda g: strip.solve_g(g, throw=False))(g[None]),
                 lambda: strip.solve_g(g, reuse=0.3)):
        with pytest.raises(Recorded):
            call()
    assert seen == [strip.choice.newton_reuse, 0.0, 0.0, 0.3]
    sets = {name: strip.set_indices(name) for name in strip.set_names}
    assert jr.Model(strip.body, strip.material, essential=sets, solver="sparse").newton_reuse == 0.0


def test_reuse_must_lie_in_unit_interval(strip):
    with pytest.raises(ValueError, match="reuse"):
        strip.solver(reuse=1.5)


def test_preconditioned_cg_on_host_and_in_jit():
    """The one preconditioned CG (a kept factorisation as preconditioner): NumPy on the host
    and lax.while_loop inside jit give K^-1 b to the tolerance, column by column, and report
    a matrix that is not positive definite."""
    import jax
    from jaxrkpm.solvers.linalg.refinement import preconditioned_cg

    rng = np.random.default_rng(0)
    Q = np.linalg.qr(rng.standard_normal((40, 40)))[0]
    K = Q @ np.diag(np.linspace(1.0, 50.0, 40)) @ Q.T
    near = np.linalg.inv(K + 0.3 * np.diag(rng.uniform(0.0, 5.0, 40)))   # an earlier state's
    b = rng.standard_normal((40, 3)) * np.array([1.0, 1e-3, 1e3])         # columns of any size
    exact = np.linalg.solve(K, b)
    matvec, precondition = (lambda v: K @ v), (lambda r: near @ r)
    for j in range(3):
        x, its, ok = preconditioned_cg(matvec, precondition, b[:, j], 1e-10, 40)
        assert ok and 0 < its < 40
        assert np.abs(x - exact[:, j]).max() < 1e-8 * np.abs(exact[:, j]).max()
    run = jax.jit(lambda b: preconditioned_cg(lambda v: jnp.asarray(K) @ v, lambda r: jnp.asarray(near) @ r, b,
                                              1e-10, 40, columns=True, loop=jax.lax.while_loop))
    x, its, ok = run(jnp.asarray(b))
    assert bool(np.all(ok)) and np.allclose(np.asarray(x), exact, rtol=0, atol=1e-8 * np.abs(exact).max(0))
    # from a guess near the solution (a nearby system's): the same residual test, fewer iterations
    x0 = exact[:, 0] + 1e-4 * rng.standard_normal(40)
    cold = preconditioned_cg(matvec, precondition, b[:, 0], 1e-10, 40)
    warm = preconditioned_cg(matvec, precondition, b[:, 0], 1e-10, 40, x0=x0)
    assert warm[2] and warm[1] < cold[1]
    assert np.linalg.norm(b[:, 0] - K @ warm[0]) <= 1e-10 * np.linalg.norm(b[:, 0])
    # a zero right-hand side gives zero whatever the guess (a contact tool off the body has no response)
    rhs = b.copy()
    rhs[:, 0] = 0.0
    x, its, ok = preconditioned_cg(matvec, precondition, rhs, 1e-10, 40, columns=True, x0=exact)
    assert np.all(x[:, 0] == 0) and np.all(ok) and np.allclose(x[:, 1:], exact[:, 1:], rtol=0, atol=1e-8 * np.abs(exact).max())
    indefinite = K - 10.0 * np.eye(40)
    x, its, ok = preconditioned_cg(lambda v: indefinite @ v, precondition, b[:, 0], 1e-10, 40)
    assert not ok
