"""Modified Newton (Config.reuse): a kept factorisation serves later iterations and the next
load step while the residual contracts; the equilibrium is full Newton's to the tolerance,
and the solve still stops where full Newton's does at an instability. One small clamped
strip (experiments.elastica) serves both: its compiled solves are shared."""
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from experiments.elastica import L, strip_model


@pytest.fixture(scope="module")
def strip():
    return strip_model(21, 3)


def push(model, shortening, **options):
    return model.solve({"right": jnp.array([-shortening * L, 0.0])}, steps=10, throw=False, **options)


def test_reuse_reaches_full_newton_equilibrium(strip):
    full, kept = push(strip, 0.02), push(strip, 0.02, reuse=0.1)
    assert full.converged and kept.converged
    # chord steps converge linearly: more (cheap) iterations than full Newton's
    assert int(kept.iterations) > int(full.iterations)
    assert float(jnp.abs(kept.u - full.u).max()) < 1e-8 * float(jnp.abs(full.u).max())
    prob = strip.problem()
    assert float(jnp.linalg.norm(prob.residual(kept.u, kept.g))) <= \
        1e-10 * max(float(prob.force_scale(kept.u, kept.g)), 1.0)


def test_reuse_still_stops_at_the_instability(strip):
    """Pushed past its Euler load, the strip stops with UNSTABLE_TANGENT at the same load
    as full Newton, on a stable state (convergence is declared only on a step factorised at
    its start; with the factorisation of an earlier iterate, measured, the solve went on to
    t = 0.6875 and a K_ff with a negative eigenvalue)."""
    # stable_branch=False: the stop itself (by default the solve would go on past it)
    full, kept = push(strip, 0.05, stable_branch=False), push(strip, 0.05, reuse=0.1, stable_branch=False)
    assert full.outcome == jr.Status.UNSTABLE_TANGENT
    assert kept.outcome == full.outcome
    assert float(kept.t) == pytest.approx(float(full.t), abs=1e-12)
    K = np.asarray(strip.problem().tangent(kept.u, kept.g))
    assert np.linalg.eigvalsh(K)[0] > 0           # the state kept is stable


def test_reuse_must_lie_in_unit_interval(strip):
    with pytest.raises(ValueError, match="reuse"):
        strip.config(reuse=1.5)
