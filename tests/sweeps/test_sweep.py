"""Sweeps to disk (``jaxrkpm.sweeps``): each configuration written exactly once, a rerun
after an interruption gives the same table, failures are rows, bad tables and foreign folders
are refused, and a two-worker Dask cluster (processes) writes the same table as the local run,
also when a worker is killed mid-chunk. The evaluators are tiny JAX programs (the needle
evaluator is tested in tests/thesis/test_sweeps.py)."""
import json
import os
import re
import shutil
import signal
import time

import numpy as np
import pyarrow as pa
import pytest

from jaxrkpm.sweeps.chunk_size import choose_chunk_size
from jaxrkpm.sweeps.executors import worker_settings
from jaxrkpm.sweeps.fingerprint import evaluator_key
from jaxrkpm.sweeps.limits import MAX_CHUNK
from jaxrkpm.sweeps.runner import sweep
from jaxrkpm.sweeps.storage import LEGACY_SWEEP_FILE, SWEEP_FILE, SweepFolderError, chunk_path, read_sweep
from tests.terminal import Terminal

N, CHUNK = 23, 5          # five chunks, the last one short
RAISES = 13               # the configuration whose evaluation raises


def configurations():
    x = np.linspace(-1.0, 3.0, N)
    return [{"x": float(v), "k": i % 4, "name": f"c{i}"} for i, v in enumerate(x)]


class Square:
    """y = x^2 + k and a (B, 3) vector, in JAX; a negative x is a NEGATIVE row with a reason;
    configuration RAISES raises (the chunk that holds it is split to find it); ``x64`` and
    ``env`` say what the process computing it was set to."""

    requires = {"x": "float", "k": "int"}
    sweep_key = "tests.sweeps.test_sweep.Square"
    sweep_version = "1"     # the subclasses below only watch or interrupt: the same sweep

    def __call__(self, chunk):
        import jax.numpy as jnp
        if np.any(chunk["id"] == RAISES):
            raise ValueError(f"configuration {RAISES} raises")
        x = jnp.asarray(chunk["x"])
        y = x * x + jnp.asarray(chunk["k"])
        neg = np.asarray(chunk["x"]) < 0
        return {"y": np.asarray(y), "vec": np.stack([np.asarray(x), np.asarray(y), np.asarray(x) * 0 + 1], 1),
                "x64": np.full(len(x), y.dtype == jnp.float64),
                "status": np.where(neg, "NEGATIVE", "OK"),
                "reason": np.where(neg, "x < 0", "")}


class InterruptAfter(Square):
    """Square, but Ctrl-C (KeyboardInterrupt) on its ``calls``-th call."""

    def __init__(self, calls):
        self.calls, self.seen = calls, []

    def __call__(self, chunk):
        self.seen.append(int(chunk["id"][0]))
        if len(self.seen) == self.calls:
            raise KeyboardInterrupt
        return super().__call__(chunk)


class Counting(Square):
    def __init__(self):
        self.seen = []

    def __call__(self, chunk):
        self.seen.append(int(chunk["id"][0]))
        return super().__call__(chunk)


class KillOnce(Square):
    """Square, but the worker running the chunk of configuration 7 kills its own process the
    first time (a marker file remembers it)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __call__(self, chunk):
        if 7 in chunk["id"] and not os.path.exists(self.marker):
            open(self.marker, "w").close()
            os.kill(os.getpid(), signal.SIGKILL)
        return super().__call__(chunk)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "sweep"
    summary = sweep(configurations(), Square(), out, chunk_size=CHUNK, progress=False)
    return out, summary, read_sweep(out)


def test_every_configuration_once_with_results_and_failures(reference):
    out, summary, table = reference
    assert summary.chunks == 5 and summary.evaluated == 5 and summary.skipped == 0 and summary.complete
    assert table.column("id").to_pylist() == list(range(N))
    assert sorted(p.name for p in out.glob("chunk-*.parquet")) == [f"chunk-{k:07d}.parquet" for k in range(5)]
    rows = table.to_pylist()
    x = np.linspace(-1.0, 3.0, N)
    for i, row in enumerate(rows):
        assert row["x"] == x[i] and row["name"] == f"c{i}"
        if i == RAISES:   # the configuration that raised: a row, its results null
            assert row["status"] == "ERROR" and "ValueError: configuration 13 raises" in row["reason"]
            assert row["y"] is None and row["vec"] is None
            continue
        assert row["y"] == pytest.approx(x[i] ** 2 + i % 4, abs=1e-15)
        assert row["vec"] == pytest.approx([x[i], row["y"], 1.0])
        assert row["x64"] is True
        assert row["status"] == ("NEGATIVE" if x[i] < 0 else "OK")
    assert summary.statuses == {"ERROR": 1, "NEGATIVE": int(np.sum(x < 0)), "OK": N - 1 - int(np.sum(x < 0))}
    # the format is plain Parquet: a reader without jaxrkpm sees the same rows
    import pyarrow.dataset as ds
    assert ds.dataset(str(out), format="parquet", exclude_invalid_files=True).count_rows() == N


def test_rerun_after_interrupt_writes_the_rest_once(reference, tmp_path):
    _, _, expected = reference
    out = tmp_path / "sweep"
    stopped = InterruptAfter(3)
    with pytest.raises(KeyboardInterrupt):
        sweep(configurations(), stopped, out, chunk_size=CHUNK, progress=False)
    assert len(list(out.glob("chunk-*.parquet"))) == 2          # the two chunks finished before Ctrl-C
    (out / ".chunk-0000002.parquet.999.tmp").write_bytes(b"half a file")   # a write cut short
    again = Counting()
    summary = sweep(configurations(), again, out, progress=False)      # chunk size from the manifest
    assert summary.skipped == 2 and summary.evaluated == 3
    assert 0 not in again.seen and 5 not in again.seen                    # finished chunks not redone
    assert not list(out.glob(".*.tmp"))
    assert read_sweep(out).equals(expected)
    summary = sweep(configurations(), Counting(), out, progress=False)   # nothing left to do
    assert summary.evaluated == 0 and read_sweep(out).equals(expected)


def test_a_chunk_that_breaks_the_contract_is_error_rows(tmp_path):
    out = tmp_path / "s"
    summary = sweep({"x": [1.0, 2.0, 3.0]}, lambda chunk: {"y": np.zeros(len(chunk["x"]) + 1)}, out, chunk_size=3, progress=False)
    table = read_sweep(out)
    assert summary.statuses == {"ERROR": 3}
    assert all("shape (2,) for a chunk of 1 configurations" in r for r in table.column("reason").to_pylist())


@pytest.mark.parametrize("table, error, match", [
    ({"x": [1.0, 2.0]}, ValueError, r"lacks the column\(s\) \['k'\]"),
    ({"x": ["a", "b"], "k": [1, 2]}, TypeError, "'x' holds str values"),
    ({"x": [1.0, 2.0], "k": [1.5, 2.0]}, TypeError, "'k' holds float values"),
    ({"x": [1.0, None], "k": [1, 2]}, ValueError, "missing values"),
    ({"x": [1.0, 2.0], "k": [1, 2], "id": [3, 3]}, ValueError, "unique"),
    ({"x": [1.0, 2.0], "k": [1, 2], "status": ["a", "b"]}, ValueError, "name of the results"),
    ({"x": [1.0, 2.0], "k": [1]}, ValueError, "differ in length"),
    ([{"x": 1.0, "k": 1}, {"x": 2.0}], ValueError, "configuration 1 has columns"),
    ([], ValueError, "empty"),
    ("x", TypeError, "list of dicts"),
])
def test_bad_tables_are_refused_before_any_work(tmp_path, table, error, match):
    with pytest.raises(error, match=match):
        sweep(table, Square(), tmp_path / "s", progress=False)
    assert not (tmp_path / "s" / SWEEP_FILE).exists()


def test_sizes_are_bounded(tmp_path):
    with pytest.raises(ValueError, match="more than max_configurations = 10"):
        sweep({"x": np.zeros(11), "k": np.zeros(11, int)}, Square(), tmp_path / "s", max_configurations=10)
    for bad in (0, MAX_CHUNK + 1, 2.0):
        with pytest.raises(ValueError, match="chunk_size"):
            sweep({"x": [1.0], "k": [1]}, Square(), tmp_path / "s", chunk_size=bad)


def test_a_folder_of_another_sweep_is_refused(reference, tmp_path):
    out, _, _ = reference
    other = configurations()[:-1]
    with pytest.raises(SweepFolderError, match="another sweep.*differ in configurations"):
        sweep(other, Square(), out, progress=False)
    with pytest.raises(SweepFolderError, match="chunk_size"):
        sweep(configurations(), Square(), out, chunk_size=4, progress=False)
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(SweepFolderError, match="no sweep manifest"):
        sweep(other, Square(), tmp_path, progress=False)
    from filelock import FileLock
    with FileLock(str(out / ".sweep.lock")):
        with pytest.raises(SweepFolderError, match="another sweep is writing"):
            sweep(configurations(), Square(), out, progress=False)
    with pytest.raises(FileNotFoundError, match="holds no sweep.*give the folder a sweep wrote"):
        read_sweep(tmp_path)
    # the folder above a sweep (the CLI's --out above its table/) names where the sweep is
    (tmp_path / "run" / "table").mkdir(parents=True)
    shutil.copy(out / SWEEP_FILE, tmp_path / "run" / "table")
    with pytest.raises(FileNotFoundError, match=re.escape(f"the sweep is in {tmp_path / 'run' / 'table'}/")):
        read_sweep(tmp_path / "run")


# ------------------------------------------------------------------ the chunk size, measured
class Knee:
    """A batched evaluator whose call takes 0.1 s up to KNEE rows, then in proportion to them
    (a device that is busy from KNEE members on): its throughput doubles with the chunk up to
    KNEE and stays flat beyond."""

    KNEE = 32
    requires = {"x": "float"}
    sweep_key = "tests.sweeps.test_sweep.Knee"

    def __init__(self):
        self.calls = []

    def __call__(self, chunk):
        B = len(chunk["x"])
        self.calls.append(B)
        time.sleep(0.1 * max(1.0, B / self.KNEE))
        return {"y": np.asarray(chunk["x"]) ** 2}


def table_of(n):
    return {"x": np.arange(n, dtype=float)}


def test_the_chunk_size_is_where_the_throughput_stops_growing():
    knee = Knee()
    choice = choose_chunk_size(table_of(1000), knee, start=4, progress=False)
    assert choice.sizes == (4, 8, 16, 32, 64) and choice.chosen == Knee.KNEE
    assert "save less time" in choice.why            # flat from 32 to 64: a larger size saves nothing
    assert knee.calls == [4, 4, 8, 8, 16, 16, 32, 32, 64, 64]      # each size compiled, then timed
    rate = choice.throughput
    assert 1.6 < rate[1] / rate[0] < 2.1 and rate[4] / rate[3] < 1.1
    # bounded: by the table, by what an interruption may lose, by what measuring saves
    knee = Knee()
    whole = choose_chunk_size(table_of(12), knee, start=16, progress=False)
    assert whole.sizes == () and whole.chosen == 12 and "nothing to measure" in whole.why and knee.calls == []
    assert choose_chunk_size(table_of(20), Knee(), start=16, progress=False).sizes == (16, 20)
    short = choose_chunk_size(table_of(1000), Knee(), start=4, max_chunk_s=0.15, progress=False)
    assert short.sizes == (4,) and short.chosen == 4 and "twice the size" in short.why
    # 100 configurations: at 16 (0.6 s left), 32 would save 0.3 s and cost 0.4 s (compile, two calls)
    small = choose_chunk_size(table_of(100), Knee(), start=4, progress=False)
    assert small.sizes == (4, 8, 16) and small.chosen == 16 and "save less time" in small.why
    for bad in ({"start": 0}, {"tolerance": 1.0}, {"max_chunk_s": float("nan")}, {"tolerance": True}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            choose_chunk_size(table_of(10), Knee(), progress=False, **bad)


def test_an_auto_sweep_measures_once_and_resumes_with_its_size(tmp_path):
    out = tmp_path / "auto"
    knee = Knee()
    summary = sweep(table_of(200), knee, out, chunk_size="auto", progress=False,
                       settings=worker_settings())
    manifest = json.loads((out / SWEEP_FILE).read_text())
    measured = manifest["chunk_size_measured"]
    assert measured["sizes"] == [4, 8, 16, 32] and "save less time" in measured["why_stopped"]
    assert manifest["chunk_size"] == 32 and summary.chunks == 7
    assert read_sweep(out).num_rows == 200
    again = Knee()
    rerun = sweep(table_of(200), again, out, chunk_size="auto", progress=False)
    assert again.calls == [] and rerun.skipped == rerun.chunks       # the folder's size: nothing measured
    with pytest.raises(ValueError, match="chunk_size must be .* or 'auto'"):
        sweep(table_of(5), Knee(), tmp_path / "bad", chunk_size="fast", progress=False)


# ------------------------------------------------------------------ on a Dask cluster
@pytest.fixture(scope="module")
def client():
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=50)
    c = distributed.Client(cluster)
    yield c
    c.close()
    cluster.close()


def test_two_workers_write_the_local_table(reference, client, tmp_path):
    _, _, expected = reference
    out = tmp_path / "cluster"
    settings = worker_settings(env={"JAXRKPM_SWEEP_TEST": "set"})
    summary = sweep(configurations(), Square(), out, chunk_size=CHUNK, executor=client, progress=False,
                       settings=settings)
    assert summary.evaluated == 5 and summary.complete
    assert read_sweep(out).equals(expected)     # x64 column: float64 on the workers too
    seen = client.run(lambda: (os.environ.get("JAXRKPM_SWEEP_TEST"),
                               __import__("jax").config.read("jax_enable_x64")))
    assert len(seen) == 2 and set(seen.values()) == {("set", True)}


def test_a_killed_workers_chunk_is_redone(reference, client, tmp_path):
    _, _, expected = reference
    out, marker = tmp_path / "killed", tmp_path / "killed-once"
    summary = sweep(configurations(), KillOnce(marker), out, chunk_size=CHUNK, executor=client, progress=False)
    assert marker.exists()                          # a worker died running chunk 1
    assert summary.evaluated == 5 and summary.complete
    assert read_sweep(out).equals(expected)     # its chunk redone elsewhere, nothing lost or twice


def test_the_chunk_size_is_measured_on_a_worker(client):
    choice = choose_chunk_size(table_of(1000), Knee(), executor=client, start=8, progress=False)
    assert choice.sizes == (8, 16, 32, 64) and choice.chosen == Knee.KNEE


# ------------------------------------------------------------------ the folder is a Parquet dataset
def test_any_parquet_reader_opens_the_folder(reference, tmp_path):
    import pyarrow.dataset as ds
    import pyarrow.parquet as pq
    out, _, table = reference
    assert (out / SWEEP_FILE).exists() and SWEEP_FILE.startswith("_")
    for read in (lambda d: pq.read_table(d), lambda d: ds.dataset(d, format="parquet").to_table()):
        got = read(out).sort_by("id")
        assert got.num_rows == N
        np.testing.assert_array_equal(got.column("y").to_numpy(), table.column("y").to_numpy())
    pd = pytest.importorskip("pandas")
    frame = pd.read_parquet(out).sort_values("id")
    np.testing.assert_allclose(frame["y"].to_numpy(), table.column("y").to_numpy())
    # a folder of an earlier version (its manifest named sweep.json) still reads and resumes,
    # and is renamed so that other readers open it too
    old = tmp_path / "old"
    shutil.copytree(out, old)
    os.replace(old / SWEEP_FILE, old / LEGACY_SWEEP_FILE)
    assert read_sweep(old).num_rows == N
    again = sweep(configurations(), Square(), old, chunk_size=CHUNK, progress=False)
    assert again.evaluated == 0 and (old / SWEEP_FILE).exists() and not (old / LEGACY_SWEEP_FILE).exists()


# ------------------------------------------------------------------ chunks carry the sweep's fingerprint
def _y_plus_one(chunk):
    return {"y": np.asarray(chunk["x"]) + 1.0}


def _y_plus_two(chunk):      # the same function edited: renamed below to _y_plus_one
    return {"y": np.asarray(chunk["x"]) + 2.0}


_y_plus_two.__qualname__ = _y_plus_two.__name__ = "_y_plus_one"


def test_an_edited_evaluator_or_a_foreign_chunk_is_refused_by_name(reference, tmp_path):
    table = {"x": np.arange(6.0)}
    out = tmp_path / "edited"
    sweep(table, _y_plus_one, out, chunk_size=2, progress=False)
    assert evaluator_key(_y_plus_one) == evaluator_key(_y_plus_two)
    with pytest.raises(SweepFolderError, match=r"another sweep \(they differ in the evaluator's code"):
        sweep(table, _y_plus_two, out, chunk_size=2, progress=False)
    # an evaluator that declares its version is the same sweep while the version stays
    for f in (_y_plus_one, _y_plus_two):
        f.sweep_version = "1"
    try:
        v = tmp_path / "versioned"
        sweep(table, _y_plus_one, v, chunk_size=2, progress=False)
        assert sweep(table, _y_plus_two, v, chunk_size=2, progress=False).evaluated == 0
    finally:
        del _y_plus_one.sweep_version, _y_plus_two.sweep_version
    # a chunk copied from another sweep (same file name) is refused on resume and on read
    mixed = tmp_path / "mixed"
    shutil.copytree(reference[0], mixed)
    other = tmp_path / "other"
    sweep([{**c, "x": c["x"] + 1} for c in configurations()], Square(), other, chunk_size=CHUNK, progress=False)
    shutil.copy(chunk_path(other, 1), chunk_path(mixed, 1))
    name = re.escape(str(chunk_path(mixed, 1)))
    with pytest.raises(SweepFolderError, match=f"{name} was not written by the sweep.*redo chunk 1"):
        read_sweep(mixed)
    with pytest.raises(SweepFolderError, match=f"{name} was not written by the sweep"):
        sweep(configurations(), Square(), mixed, chunk_size=CHUNK, progress=False)
    # a chunk of this sweep under another chunk's name
    shutil.copy(chunk_path(mixed, 2), chunk_path(mixed, 1))
    with pytest.raises(SweepFolderError, match="holds chunk 2 of this sweep, not chunk 1"):
        read_sweep(mixed)


def test_a_truncated_chunk_is_named_and_redone_once_deleted(reference, tmp_path):
    cut = tmp_path / "cut"
    shutil.copytree(reference[0], cut)
    path = chunk_path(cut, 3)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    match = re.escape(str(path)) + r" is unreadable .*delete it and run the same sweep again to redo chunk 3"
    with pytest.raises(SweepFolderError, match=match):
        read_sweep(cut)
    with pytest.raises(SweepFolderError, match=match):
        sweep(configurations(), Square(), cut, chunk_size=CHUNK, progress=False)
    path.unlink()
    again = sweep(configurations(), Square(), cut, chunk_size=CHUNK, progress=False)
    assert again.evaluated == 1 and read_sweep(cut).equals(reference[2])


# ------------------------------------------------------------------ progress


def test_the_bar_is_drawn_on_a_terminal_only_and_can_be_silenced(tmp_path, monkeypatch, capsys):
    import sys
    for tty, progress, shown in ((True, True, True), (False, True, False), (True, False, False)):
        err = Terminal(tty)
        monkeypatch.setattr(sys, "stderr", err)
        out = tmp_path / f"p{tty}{progress}"
        sweep(configurations(), Square(), out, chunk_size=CHUNK, progress=progress)
        monkeypatch.undo()
        assert ("sweep: 100%" in err.text and f"{N}/{N}" in err.text) == shown, (tty, progress, err.text)
        assert err.text.count("\n") <= 1                   # drawn in place, left once
        assert capsys.readouterr().out == ""
