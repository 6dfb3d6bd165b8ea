"""Batched needle insertion (``needle.insert``, both batchings) equals the loop of the same
solves (``model.solve`` warm-started per increment, ``model.jacobian``)."""
import numpy as np
import pytest

from jaxrkpm.control import batching
from jaxrkpm.thesis import needle as nd
from jaxrkpm.solvers.results import Status


# per member: two needle increments; the second member's load is zero (it converges at once),
# the fourth's second increment inverts the material (its solve fails after step cuts)
PADDLES = (4, 5, 5, 4)


@pytest.fixture(scope="module")
def setup():
    ph = nd.Phantom()
    models = [ph.model("none", p) for p in PADDLES]
    d = ph.depths(4)[:2]           # two small increments (every solve converges)
    depths = np.array([d, [0.0, 0.0], d, [d[0], 0.5]])
    return ph, models, depths


def loop(ph, models, depths, reuse):
    """The same solves one call at a time: ``model.solve`` per increment, warm-started, and
    ``model.jacobian`` where it converged."""
    target = np.atleast_2d(ph.target)
    u, J, st, its = [], [], [], []
    for m, row in zip(models, depths):
        sol = m.initial()
        for depth in row:
            sol = m.solve({"needle": ph.needle_at(depth)}, initial=sol, throw=False, reuse=reuse)
            st.append(int(sol.status))
            its.append(int(sol.iterations))
            u.append(np.asarray(m.displacement(sol, target)[0]))
            J.append(np.asarray(m.jacobian(sol, "paddle", target)) if st[-1] == Status.CONVERGED
                     else np.full((2, 2), np.nan))
    n = depths.shape
    return np.reshape(u, n + (2,)), np.reshape(J, n + (2, 2)), np.reshape(st, n), np.reshape(its, n)


@pytest.mark.parametrize("batching", batching.BATCHING)
def test_batched_equals_loop(setup, batching):
    """Every member as solved alone, iterations included, also beside a member whose load is
    zero and one that fails: in lock step (vmap) the failing member leaves the lock step and
    is solved again with the step cuts of an unbatched solve."""
    ph, models, depths = setup
    reuse = models[0].newton_reuse if batching == "map" else 0.0    # what insert solves with
    u, J, st, its = loop(ph, models, depths, reuse)
    out = nd.insert(models, depths, ph.target, direction=ph.needle_direction, batching=batching)
    assert st[3, 1] == Status.INVERTED and np.all(np.delete(st.ravel(), 7) == Status.CONVERGED)
    assert its[1].max() < its[0].min() and its[3, 1] > 3 * its[0, 1]   # at once; the failure cut its step
    np.testing.assert_array_equal(np.asarray(out.status), st)
    ok = st == Status.CONVERGED
    # "map" (modified Newton) starts each increment from the kept Jacobian factorisation,
    # which the loop has not made after a failed increment: the failing attempts differ there
    same = np.ones_like(ok) if batching == "vmap" else ok
    np.testing.assert_array_equal(np.asarray(out.iterations)[same], its[same])
    np.testing.assert_allclose(np.asarray(out.target_u), u, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.jacobian)[ok], J[ok], rtol=0, atol=1e-10)
    assert np.max(np.abs(u)) > 1e-3 and np.all(u[1] == 0)   # the needle moved the target; zero load: none


def test_unknown_batching(setup):
    ph, models, depths = setup
    with pytest.raises(ValueError, match="batching"):
        nd.insert(models, depths, ph.target, batching="pmap")


def test_bad_depths_and_sets_are_named(setup):
    ph, models, depths = setup
    with pytest.raises(ValueError, match="3 rows for 4 models"):
        nd.insert(models, depths[:3], ph.target)
    with pytest.raises(ValueError, match="no essential set 'paddle'"):
        nd.insert([ph.model("none", None)], depths[0], ph.target)


def test_shared_arrays_stay_unbatched(setup):
    """What every configuration shares (integration table, pair structure) is kept once and
    vmapped as an unbatched operand; what differs (essential partition, material) is stacked."""
    ph, models, depths = setup
    prob, batched = batching.stack_models(models)
    one = models[0].problem()
    assert prob.term("strain").idx.shape == one.term("strain").idx.shape
    assert prob.term("strain").pair_id.shape == one.term("strain").pair_id.shape
    assert prob.constraint.free.shape == (len(models),) + one.constraint.free.shape
    axes = batching.batch_axes(prob, batched)
    assert axes.term("strain").idx is None and axes.constraint.free == 0
