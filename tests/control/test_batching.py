"""Batched needle insertion (``needle.insert``, both batchings) equals the loop of the same
solves (``model.solve`` warm-started per increment, ``model.jacobian``)."""
import numpy as np
import pytest

from jaxrkpm.control import batching
from jaxrkpm.thesis import needle as nd
from jaxrkpm.solvers.results import Status


@pytest.fixture(scope="module")
def setup():
    ph = nd.Phantom()
    models = [ph.model("none", p) for p in (4, 5)]
    depths = ph.depths(4)[:2]      # two small increments (every solve converges)
    return ph, models, depths, loop(ph, models, depths)


def loop(ph, models, depths):
    target = np.atleast_2d(ph.target)
    u, J, st = [], [], []
    for m in models:
        sol = m.initial()
        for depth in depths:
            sol = m.solve({"needle": ph.needle_at(depth)}, initial=sol, throw=False)
            st.append(int(sol.status))
            u.append(np.asarray(m.displacement(sol, target)[0]))
            J.append(np.asarray(m.jacobian(sol, "paddle", target)))
    n = (len(models), len(depths))
    return np.reshape(u, n + (2,)), np.reshape(J, n + (2, 2)), np.reshape(st, n)


@pytest.mark.parametrize("batching", batching.BATCHING)
def test_batched_equals_loop(setup, batching):
    ph, models, depths, (u, J, st) = setup
    out = nd.insert(models, depths, ph.target, direction=ph.needle_direction, batching=batching)
    assert np.all(st == Status.CONVERGED)
    np.testing.assert_array_equal(np.asarray(out.status), st)
    np.testing.assert_allclose(np.asarray(out.target_u), u, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.jacobian), J, rtol=0, atol=1e-10)
    assert np.max(np.abs(u)) > 1e-3    # the needle moved the target: not a trivial zero


def test_unknown_batching(setup):
    ph, models, depths, _ = setup
    with pytest.raises(ValueError, match="batching"):
        nd.insert(models, depths, ph.target, batching="pmap")


def test_shared_arrays_stay_unbatched(setup):
    """What every configuration shares (integration table, pair structure) is kept once and
    vmapped as an unbatched operand; what differs (essential partition, material) is stacked."""
    ph, models, depths, _ = setup
    prob, batched = batching.stack_models(models)
    one = models[0].problem()
    assert prob.term("strain").idx.shape == one.term("strain").idx.shape
    assert prob.term("strain").pair_id.shape == one.term("strain").pair_id.shape
    assert prob.constraint.free.shape == (len(models),) + one.constraint.free.shape
    axes = batching.batch_axes(prob, batched)
    assert axes.term("strain").idx is None and axes.constraint.free == 0
