"""Where a sweep's chunks run, and what a failure of one becomes.

**Failures are rows.** A configuration the evaluator reports as failed (a solve that did
not converge) is a row with its status and reason. A chunk whose evaluation raises an
exception is split in halves and retried until the configurations that raise are found
alone; each becomes a row with status ``ERROR`` and the exception as its reason. On a
cluster, a chunk whose worker died ``allowed-failures`` times (Dask's default 3) is written
as ``ERROR`` rows too. Only an interrupt (``KeyboardInterrupt``) or a failure to write stops
the sweep; the rerun goes on from there.

**Executors.** In process by default (``executor=None``). ``executor=`` a
``distributed.Client`` or a scheduler address (``"tcp://host:8786"``) runs the chunks on a
Dask cluster: Dask because its ``distributed`` package is a pip install, its
``LocalCluster`` runs worker processes on one machine with no set-up (what the tests use),
the same ``Client`` connects to a cluster across machines (SSH, Kubernetes, SLURM through
``dask-jobqueue``), and its scheduler reschedules the tasks of a worker that dies (Ray does
as much but brings its own object store and daemons, a heavier dependency for chunks that
are independent tasks). Workers return their chunk's rows and the driver writes them, so
no shared file system is needed. JAX's settings reach the workers through a worker plugin
and again in each task (``settings``: float64, the driver's XLA optimisation level, and
environment variables such as thread limits, set before a worker first imports JAX).
"""
from __future__ import annotations

import os
import sys
from collections.abc import Mapping

from .schema import columns_of, failed_rows, result_table

# the JAX settings the driver passes on to the workers where it has them (``worker_settings``)
FORWARDED_CONFIG = ("jax_enable_x64", "jax_disable_most_optimizations", "jax_default_matmul_precision")

_EVALUATORS: dict = {}    # per process: evaluators by key (a worker builds one once, not per chunk)


# ------------------------------------------------------------------ one chunk
def evaluate_isolating(evaluate, chunk):
    """evaluate the chunk; where it raises, split it in halves until the configurations that
    raise are alone (each an ``ERROR`` row); the rest keep their results."""
    import pyarrow as pa
    try:
        return result_table(chunk, evaluate(columns_of(chunk)))
    except Exception as e:            # noqa: BLE001 (a failed configuration is a row, not a crash)
        if chunk.num_rows == 1:
            return failed_rows(chunk, f"{type(e).__name__}: {e}")
    half = chunk.num_rows // 2
    parts = [evaluate_isolating(evaluate, chunk.slice(0, half)),
             evaluate_isolating(evaluate, chunk.slice(half))]
    return pa.concat_tables(parts, promote_options="permissive")


def apply_settings(settings: Mapping | None) -> None:
    """Set ``settings`` in this process: ``{"env": {name: value}, "jax": {option: value}}``;
    the environment first (read by JAX when it starts), then ``jax.config``."""
    if not settings:
        return
    for name, value in (settings.get("env") or {}).items():
        os.environ[str(name)] = str(value)
    if settings.get("jax"):
        import jax
        for name, value in settings["jax"].items():
            jax.config.update(name, value)


def run_chunk(evaluate, chunk, settings=None, reuse: bool = False):
    """One chunk, where it runs (in process or on a worker): settings, then the evaluation
    (failures isolated to rows); returns the chunk's results as a ``pyarrow.Table``.
    ``reuse`` (on workers, where every task brings its own unpickled copy of the
    evaluator): the first evaluator of each class and ``sweep_key`` in this process
    evaluates, with what it built and compiled for earlier chunks."""
    # float64 and single-threaded BLAS come with the package, imported with this module
    apply_settings(settings)
    key = getattr(evaluate, "sweep_key", None)
    if reuse and key is not None:
        kind = type(evaluate)
        evaluate = _EVALUATORS.setdefault((kind.__module__, kind.__qualname__, str(key)), evaluate)
    return evaluate_isolating(evaluate, chunk)


def worker_settings(env: Mapping | None = None, jax_options: Mapping | None = None) -> dict:
    """The settings a sweep passes to its workers: float64 and the driver's values of
    ``FORWARDED_CONFIG`` (where JAX is imported), ``jax_options`` over them, and ``env``
    (e.g. ``{"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}``
    to keep each worker on one core)."""
    options = {"jax_enable_x64": True}
    if "jax" in sys.modules:
        cfg = sys.modules["jax"].config
        for name in FORWARDED_CONFIG:
            try:
                options[name] = cfg.read(name)
            except (AttributeError, KeyError):
                pass
    options.update(jax_options or {})
    return {"env": dict(env or {}), "jax": options}


# ------------------------------------------------------------------ the executors
def dask_client(executor):
    """(client, owned) for a ``distributed.Client`` or a scheduler address (``owned``: made
    here, to be closed by the caller)."""
    try:
        import distributed
    except ImportError:
        raise ImportError("executor= needs Dask distributed: pip install 'jaxrkpm[cluster]' "
                          "(or pip install 'dask[distributed]')") from None
    if isinstance(executor, distributed.Client):
        return executor, False
    if isinstance(executor, str):
        return distributed.Client(executor), True
    raise TypeError(f"executor must be None (in process), a distributed.Client or a Dask scheduler address "
                    f"('tcp://host:8786'), got {type(executor).__name__}")


def _settings_plugin(settings):
    """A Dask worker plugin that applies ``settings`` when a worker starts (before its first
    task imports JAX), on the workers there now and on any that join or replace one later."""
    import distributed

    class JaxSettings(distributed.WorkerPlugin):
        name = "jaxrkpm-settings"

        def __init__(self, settings):
            self.settings = settings

        def setup(self, worker):
            apply_settings(self.settings)

    return JaxSettings(settings)


def run_chunks(executor, todo, chunks, evaluate, settings, done) -> None:
    """Evaluate the chunks ``todo`` (numbers; ``chunks(k)``: chunk ``k``'s table) where
    ``executor`` says (None: in this process), calling ``done(k, results)`` in this process
    as each finishes."""
    if executor is None:
        run_local(todo, chunks, evaluate, done)
    else:
        run_dask(executor, todo, chunks, evaluate, settings, done)


def run_local(todo, chunks, evaluate, done) -> None:
    """The chunks one after the other in this process (whose settings are the sweep's)."""
    for k in todo:
        done(k, run_chunk(evaluate, chunks(k), None))


def run_dask(executor, todo, chunks, evaluate, settings, done) -> None:
    """Chunks as Dask tasks, at most two per worker thread in flight (plus a few): the
    scheduler holds a window, not the whole sweep, and an interrupted driver loses at most
    the window's work."""
    import distributed
    client, owned = dask_client(executor)
    inflight = {}
    try:
        client.register_plugin(_settings_plugin(settings))
        pending = iter(todo)
        window = max(4, 2 * sum(client.nthreads().values()))
        running = distributed.as_completed()

        def submit_next():
            k = next(pending, None)
            if k is not None:
                fut = client.submit(run_chunk, evaluate, chunks(k), settings, True, pure=False)
                inflight[fut] = k
                running.add(fut)
        for _ in range(window):
            submit_next()
        for fut in running:
            k = inflight.pop(fut)
            try:
                table = fut.result()
            except Exception as e:   # noqa: BLE001 (KilledWorker: the chunk killed its worker again and again)
                table = failed_rows(chunks(k), f"{type(e).__name__}: {e}")
            fut.release()
            done(k, table)
            submit_next()
    finally:
        for fut in inflight:
            fut.cancel()
        if owned:
            client.close()
