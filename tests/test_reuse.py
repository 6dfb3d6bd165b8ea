"""Modified Newton (Config.reuse): a kept factorisation serves later iterations and the next
load step while the residual contracts; the equilibrium is full Newton's to the tolerance."""
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr


def block():
    body = jr.Body.grid((5, 5), 1.0 / 4)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    return jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets)


def test_reuse_reaches_full_newton_equilibrium():
    model = block()
    g = {"right": jnp.array([-0.3, 0.2])}
    full = model.solve(g, steps=3)
    kept = model.solve(g, steps=3, reuse=0.5)
    assert full.converged and kept.converged
    # chord steps converge linearly: more (cheap) iterations than full Newton's
    assert int(kept.iterations) > int(full.iterations)
    scale = float(jnp.abs(full.u).max())
    assert float(jnp.abs(kept.u - full.u).max()) < 1e-8 * scale
    r = model.problem().residual(kept.u, kept.g)
    assert float(jnp.linalg.norm(r)) <= 1e-10 * max(float(model.problem().force_scale(kept.u, kept.g)), 1.0)


def test_reuse_must_lie_in_unit_interval():
    with pytest.raises(ValueError, match="reuse"):
        block().config(reuse=1.5)
