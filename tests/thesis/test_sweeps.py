"""The needle study's sweep to disk (``jaxrkpm.thesis.sweeps``, ``jaxrkpm sweep``): rows equal
the batched insertion of the same models (``needle.insert``, itself checked against the loop
of eager solves in tests/control/test_batching.py), an out-of-range configuration is an
INVALID row, every chunk runs one compiled program, and the command writes the same table
and resumes. Two small increments to 4% depth, where every solve converges."""
import json

import numpy as np
import pytest

from jaxrkpm.control.batching import stack_models
from jaxrkpm.sweeps.storage import read_sweep
from jaxrkpm.solvers.results import Status
from jaxrkpm.thesis import cli, needle as nd, sweeps

INCREMENTS, INSERTION, CHUNK = 2, 0.04, 4


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    cfg = sweeps.paddle_configurations(ratios=(100.0,), inclusions=("right",))
    cfg = {k: list(v) + [v[0]] for k, v in cfg.items()}
    cfg["paddle"][-1] = 9                                   # out of Table 6.2's range
    out = tmp_path_factory.mktemp("needle") / "table"
    summary = sweeps.needle_sweep(out, cfg, increments=INCREMENTS, chunk_size=CHUNK, progress=False,
                                  insertion=INSERTION)
    return out, summary, read_sweep(out)


def test_rows_are_the_batched_insertion(swept):
    out, summary, table = swept
    assert summary.chunks == 2 and summary.statuses == {"CONVERGED": 5, "INVALID": 1}
    ev = sweeps.NeedleSweep(INCREMENTS, insertion=INSERTION)
    ph = ev.phantom
    models = [nd.Model(ph.body, ev.material("right", 100.0, 1.0, 1.0), ph.integration, essential=ph.sets(p),
                       support=ph.support) for p in (1, 2, 3, 4)]
    run = nd.insert(models, ph.depths(INCREMENTS), ph.target, direction=ph.needle_direction, like=ev.like)
    dev = np.asarray(run.target_u)[..., 0]
    rows = table.to_pylist()
    for j in range(4):
        assert rows[j]["paddle"] == j + 1 and rows[j]["status"] == "CONVERGED" and rows[j]["reason"] == ""
        np.testing.assert_allclose(rows[j]["deviation"], dev[j], rtol=0, atol=1e-12)
        assert rows[j]["final_deviation"] == pytest.approx(dev[j, -1], abs=1e-12)
        assert rows[j]["increment_status"] == [Status.CONVERGED] * INCREMENTS
        assert rows[j]["controllability"] == pytest.approx(
            nd.controllability(np.asarray(run.jacobian)[j, 0], ph.lateral), rel=1e-10)
    devs = [r["final_deviation"] for r in rows[:5]]
    assert np.all(np.abs(devs) > 1e-3) and len(set(np.round(devs, 6))) == 5   # the target moved; the paddles differ
    bad = rows[5]
    assert bad["status"] == "INVALID" and "paddle 9 out of range 1..5" in bad["reason"]
    assert np.isnan(bad["final_deviation"]) and bad["iterations"] == -1


def test_like_pads_every_chunk_to_one_shape(swept):
    """``stack_models(like=)``: the members' leaves are those of the plain stack, zero-padded
    where ``like`` is larger, and the batched leaves are those that differ anywhere."""
    ev = sweeps.NeedleSweep(INCREMENTS, insertion=INSERTION)
    ph = ev.phantom
    models = [nd.Model(ph.body, ev.material("right", 100.0, 1.0, 1.0), ph.integration, essential=ph.sets(p),
                       support=ph.support) for p in (5, 5)]
    import jax
    plain, b0 = stack_models(models)
    padded, b1 = stack_models(models, ev.like)
    assert not any(b0) and all(b1[i] for i, b in enumerate(b0) if b)   # identical members: nothing batched alone
    assert any(b1)
    for x, y, b in zip(jax.tree.leaves(plain), jax.tree.leaves(padded), b1):
        x, y = np.asarray(x), np.asarray(y)
        if b:
            assert y.shape[0] == 2
            y = y[0]
        sl = tuple(slice(0, n) for n in x.shape)
        np.testing.assert_array_equal(y[sl], x)
        rest = y.copy()
        rest[sl] = 0
        assert not np.any(rest)


def test_the_command_writes_and_resumes(swept, tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["sweep", "--out", str(out), "--increments", str(INCREMENTS), "--insertion", str(INSERTION),
            "--chunk-size", str(CHUNK), "--paddles", "1", "2", "3", "4", "5"]
    assert cli.main(argv) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith(f"wrote {out}/: run.json, summary.json, table/; 5/5 configurations") and "5 CONVERGED" in line
    _, _, expected = swept
    assert read_sweep(out / "table").equals(expected.slice(0, 5))     # the same rows as the API's
    (out / "table" / "chunk-0000001.parquet").unlink()                 # as if stopped before the last chunk
    assert cli.main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["skipped_chunks"] == 1 and summary["evaluated_chunks"] == 1
    assert read_sweep(out / "table").equals(expected.slice(0, 5))
    assert cli.main(argv[:-1]) == 3                                     # other options: another run's folder
    assert "holds the results of another run" in capsys.readouterr().err
    # --overwrite with other options starts afresh (it raised on the other sweep's table/)
    assert cli.main(argv[:-1] + ["--overwrite"]) == 0
    assert read_sweep(out / "table").equals(expected.slice(0, 4))


def test_the_evaluator_travels_without_its_phantom(swept):
    """What a cluster worker receives: the numbers, not the phantom's models and arrays."""
    import pickle
    ev = sweeps.NeedleSweep(INCREMENTS, insertion=INSERTION)
    ev.like                                                     # built: models, arrays
    copy = pickle.loads(pickle.dumps(ev))
    assert len(pickle.dumps(ev)) < 2000 and copy._phantom is None and copy._like is None
    assert copy.sweep_key == ev.sweep_key and copy.phantom.insertion == INSERTION


def test_the_sweep_sets_the_batch_to_its_chunk_size():
    """A sweep pads every batch to its chunk size (one program for the last, short chunk too),
    unless the evaluator was given a batch of its own."""
    ev = sweeps.NeedleSweep(INCREMENTS, insertion=INSERTION)
    assert ev.for_chunk_size(8).batch == 8 and ev.batch is None
    mine = sweeps.NeedleSweep(INCREMENTS, insertion=INSERTION, batch=3)
    assert mine.for_chunk_size(8) is mine and mine.batch == 3


# ------------------------------------------------------------------ the 3D phantom
SPACING_3D = 0.3        # the coarse phantom of tests/thesis/test_needle3d.py


@pytest.fixture(scope="module")
def sweep3d():
    return sweeps.NeedleSweep3D(1, spacing=SPACING_3D)


def test_3d_rows_that_cannot_run_are_named(sweep3d):
    """Rows that cannot run are INVALID with the reason, before any solve (no row here runs):
    a patch out of range, an unknown inclusion, a constant of another material law, a Poisson's
    ratio of 0.5 or more."""
    P = len(sweep3d.phantom.paddles)
    chunk = {"id": np.arange(4), "paddle": np.array([P + 1, 1, 1, 1]),
             "inclusion": np.array(["none", "right", "none", "none"], object),
             "stiffness_ratio": np.array([10.0, 10.0, -1.0, 10.0]), "nu": np.array([0.45, 0.45, 0.45, 0.5])}
    r = sweep3d(chunk)
    assert list(r["status"]) == ["INVALID"] * 4
    assert f"paddle {P + 1} out of range 1..{P}" in r["reason"][0]
    assert "unknown inclusion 'right'" in r["reason"][1] and "'side'" in r["reason"][1]
    assert "stiffness_ratio must be positive" in r["reason"][2]
    assert "nu must be a Poisson's ratio below 0.5" in r["reason"][3]
    r = sweep3d({**chunk, "lam": np.full(4, 4.0)})
    assert all("['lam'] are not constants of this phantom's material" in why for why in r["reason"][2:])
    assert sweep3d.values == ("mu", "nu") and r["target_u"].shape == (4, 3)
    with pytest.raises(TypeError, match="unknown phantom option"):
        sweeps.NeedleSweep3D(1, immobile=("bottom",))


def test_3d_models_are_the_phantoms_with_the_rows_constants(sweep3d):
    """A row's model is the phantom's with the row's constants; without an inclusion its
    material is a field of ones times the constants (so that every row batches together),
    which gives the phantom's own model's residual."""
    import jax
    ph = sweep3d.phantom
    mine = sweep3d.model(2, "none", {"stiffness_ratio": 5.0, "mu": 1.0, "nu": 0.45})
    own = ph.model("none", 2)
    u = 1e-3 * jax.random.normal(jax.random.PRNGKey(0), (own.problem().n_free, 3))
    g = own.prescribed({"needle": ph.needle_at(0.01)})
    r_mine, r_own = mine.problem().residual(u, g, 1.0), own.problem().residual(u, g, 1.0)
    np.testing.assert_allclose(r_mine, r_own, rtol=1e-12, atol=1e-12 * float(np.abs(r_own).max()))
    stiffer = sweep3d.model(2, "side", {"stiffness_ratio": 10.0, "mu": 2.0, "nu": 0.45})
    assert not np.allclose(stiffer.problem().residual(u, g, 1.0), r_own)


@pytest.mark.slow(reason="a 3D needle sweep to disk: its rows against the batched insertion of the phantom's "
                         "models (the evaluator's rows and models are checked in the default run)")
def test_3d_sweep_rows_are_the_batched_insertion(sweep3d, tmp_path):
    ph = sweep3d.phantom
    table = {"paddle": [1, 2, 3], "inclusion": ["none", "side", "above"], "stiffness_ratio": [1.0, 10.0, 100.0],
             "mu": [1.0, 1.0, 2.0]}
    from jaxrkpm.sweeps.runner import sweep
    summary = sweep(table, sweep3d, tmp_path / "s3", chunk_size=3, progress=False)
    assert summary.complete and summary.statuses == {"CONVERGED": 3}
    rows = read_sweep(tmp_path / "s3")
    models = [ph.model(i, p, stiffness_ratio=r, mu=m) for p, i, r, m in
              zip(table["paddle"], table["inclusion"], table["stiffness_ratio"], table["mu"])]
    ref = nd.insert(models, ph.depths(1), ph.target, direction=ph.needle_direction)
    got = np.asarray(rows.column("target_u").to_pylist())
    np.testing.assert_allclose(got, np.asarray(ref.target_u)[:, -1], rtol=0, atol=1e-10)
    assert rows.column("iterations").to_pylist() == list(np.asarray(ref.iterations).sum(axis=1))


# ------------------------------------------------------------------ tracking over materials
def test_track_sweep_over_the_objects_material(tmp_path):
    """Rows track the set point with the nominal model's Jacobian moving a plant of the row's
    material: a plant with both Fung constants scaled tracks exactly as the nominal one (a
    displacement-driven paddle does not see a uniform stiffness scale); another ratio of the
    constants is another object, tracked as ``jaxrkpm.track`` tracks it; a bad value is an
    INVALID row."""
    import jaxrkpm as jr
    from jaxrkpm.thesis.data import CP_2D, PATHS
    ev = sweeps.TrackSweep("setpoint", n=5)
    table = {"alpha": [1.0, 3.0, 1.0, -1.0], "beta": [1.0, 3.0, 4.0, 1.0]}
    jr.sweep(table, ev, tmp_path / "track", chunk_size=2, progress=False)
    rows = read_sweep(tmp_path / "track").to_pylist()
    assert [r["status"] for r in rows] == ["DONE", "DONE", "DONE", "INVALID"]
    assert "alpha must be positive" in rows[3]["reason"]
    same, scaled, other = rows[:3]
    assert scaled["iterations"] == same["iterations"] and scaled["waypoints_reached"] == same["waypoints"] == 2
    np.testing.assert_allclose(scaled["final_cp"], same["final_cp"], rtol=0, atol=1e-9)
    direct = jr.track(ev.controller, PATHS["setpoint"], "paddle", CP_2D, plant=ev.plant(1.0, 4.0))
    assert other["iterations"] == len(direct.error) - 1
    np.testing.assert_allclose(other["final_cp"], direct.cp[-1], rtol=0, atol=1e-12)
    assert np.abs(np.subtract(other["final_cp"], same["final_cp"])).max() > 1e-8     # another object
    assert other["max_waypoint_error"] == pytest.approx(direct.max_waypoint_error, rel=1e-12)
    with pytest.raises(ValueError, match="unknown path 'circle'"):
        sweeps.TrackSweep("circle")
