"""Sweeps at scale: a table of configurations in, a results table on disk out, written chunk
by chunk so that an interrupted sweep loses nothing it finished and a rerun of the same call
does only what is left.

**The call.** ``sweep(configurations, evaluate, out)``: ``configurations`` is a table (a list
of dicts, a dict of columns, or a ``pyarrow.Table``) with one row per configuration (paddle
placement, material parameters, inclusion stiffness, ...). The rows are cut into chunks of
``chunk_size``; ``evaluate(chunk) -> dict of columns`` computes one chunk (``chunk``: a dict
of NumPy arrays, one per configuration column, plus ``"id"``) and returns one value per row
for each of its result columns (an array of shape (B, ...) becomes a column of fixed-size
lists), optionally with ``"status"`` (one name per row, "OK" where not given) and
``"reason"`` (words, "" where not given). A batched solver evaluates a whole chunk in one
compiled call (:class:`jaxrkpm.thesis.sweeps.NeedleSweep` is the needle study's evaluator);
one with a ``for_chunk_size(size)`` method is replaced by what it returns once the chunk size
is known (an evaluator that pads each batch to that size, so that every chunk, the last and
short one too, runs one compiled program).

**Chunk size.** Given, or ``"auto"``: measured on the first configurations by
:func:`choose_chunk_size` (the throughput of a batched solver grows with its batch until the
device is busy, which on a GPU is thousands of configurations and on a CPU a few).

**Format: Parquet** (through pyarrow), one file per finished chunk. Parquet is columnar
(a column of a million rows reads without the others), typed (floats stay float64, lists
stay lists), compressed, and a folder of Parquet files *is* a table: results are appended by
adding files, never by rewriting one, and pandas, polars, DuckDB or Spark read the folder
without jaxrkpm (``pandas.read_parquet(out)``, ``pyarrow.dataset.dataset(out)``: the
manifest's name begins with ``_``, which Parquet readers skip). Zarr/xarray suit dense N-dimensional grids;
a sweep's results are rows with mixed types and ragged failures, which is a table.

**Resume.** The folder holds ``_sweep.json`` (the manifest: a fingerprint of the configuration
table, the chunk size, the evaluator's key and its code or declared ``sweep_version``) and
``chunk-NNNNNNN.parquet``, named by chunk number, each carrying the fingerprint in its
Parquet metadata (a chunk of another sweep, or one cut short, is refused by name). A chunk file is written to a temporary name and renamed into place (atomic on one
file system), so a chunk file exists only whole; a rerun skips the chunks whose files exist
and evaluates the others, so each configuration is written exactly once whatever stopped the
sweep (Ctrl-C, a killed process, a full disk). A folder whose manifest describes another
sweep (other configurations, chunk size or evaluator) is refused, never mixed.

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

import hashlib
import inspect
import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numpy as np

from ..base.progress import progress_bar

# the manifest's name begins with "_": Parquet readers (pyarrow, pandas, polars) skip such
# names, so the folder is a dataset any of them opens; folders of earlier versions hold
# LEGACY_SWEEP_FILE, read as before and renamed when the sweep resumes
SWEEP_FILE = "_sweep.json"
LEGACY_SWEEP_FILE = "sweep.json"
FORMAT = "jaxrkpm-sweep"
VERSION = 2                         # 2: the fingerprint covers the evaluator's code; chunks carry it
META_KEY = b"jaxrkpm.sweep"         # a chunk file's Parquet metadata: {"fingerprint", "chunk"}
ID, STATUS, REASON = "id", "status", "reason"
OK, ERROR = "OK", "ERROR"
CHUNK_DIGITS = 7
MAX_CONFIGURATIONS = 10_000_000     # bounds the table checked before anything is allocated
MAX_CHUNK = 65_536                  # configurations in one chunk (one evaluate call)
DEFAULT_CHUNK = 64
AUTO = "auto"                       # chunk_size: measured (``choose_chunk_size``)
KINDS = ("int", "float", "bool", "str")
# the JAX settings the driver passes on to the workers where it has them (``worker_settings``)
FORWARDED_CONFIG = ("jax_enable_x64", "jax_disable_most_optimizations", "jax_default_matmul_precision")


class SweepFolderError(ValueError):
    """The output folder holds another sweep's results, or is in use by a running sweep."""


class SweepInUseError(SweepFolderError):
    """Another sweep is writing into the output folder (its lock is held)."""


class SweepSummary(NamedTuple):
    """What :func:`sweep` did: ``out`` the folder, ``configurations`` and ``chunks`` in the
    sweep, ``skipped`` chunks already on disk, ``evaluated`` chunks this call wrote,
    ``statuses`` rows per status over the whole table (every chunk on disk)."""

    out: Path
    configurations: int
    chunks: int
    skipped: int
    evaluated: int
    statuses: dict

    @property
    def complete(self) -> bool:
        return self.skipped + self.evaluated == self.chunks


# ------------------------------------------------------------------ the configuration table
def _pa():
    import pyarrow as pa
    return pa


def _kind_of(kind) -> str:
    names = {int: "int", float: "float", bool: "bool", str: "str"}
    k = names.get(kind, kind)
    if k not in KINDS:
        raise ValueError(f"unknown column kind {kind!r}: choose one of {list(KINDS)} (or int, float, bool, str)")
    return k


def _type_kind(t) -> str | None:
    import pyarrow.types as pt
    if pt.is_boolean(t):
        return "bool"
    if pt.is_integer(t):
        return "int"
    if pt.is_floating(t):
        return "float"
    if pt.is_string(t) or pt.is_large_string(t):
        return "str"
    if (pt.is_list(t) or pt.is_fixed_size_list(t) or pt.is_large_list(t)) and _type_kind(t.value_type) in ("int", "float", "bool"):
        return "list"
    return None


def configuration_table(configurations, requires: Mapping | None = None,
                        max_configurations: int = MAX_CONFIGURATIONS):
    """The configurations as a ``pyarrow.Table`` with an ``id`` column, checked: at most
    ``max_configurations`` rows (counted before anything is built), columns of numbers,
    booleans, strings or lists of numbers, no missing values, ``id`` (when given) unique
    non-negative integers, no column named ``status`` or ``reason`` (result columns), and
    the columns ``requires`` names ({name: "int" | "float" | "bool" | "str"}) present with
    those kinds (an int column where a float is required is converted)."""
    pa = _pa()
    if isinstance(configurations, pa.Table):
        n = configurations.num_rows
    elif isinstance(configurations, Mapping):
        lengths = {k: len(v) for k, v in configurations.items()}
        if len(set(lengths.values())) > 1:
            raise ValueError(f"the configuration columns differ in length: {lengths}")
        n = next(iter(lengths.values()), 0)
    elif isinstance(configurations, Sequence) and not isinstance(configurations, (str, bytes)):
        n = len(configurations)
    else:
        raise TypeError("configurations must be a list of dicts (one per configuration), a dict of columns "
                        f"or a pyarrow.Table, got {type(configurations).__name__}")
    if n > max_configurations:
        raise ValueError(f"{n:,} configurations, more than max_configurations = {max_configurations:,}: "
                         "split the sweep or raise the bound")
    if n == 0:
        raise ValueError("the configuration table is empty: give at least one configuration")
    if isinstance(configurations, pa.Table):
        table = configurations
    elif isinstance(configurations, Mapping):
        table = pa.table({str(k): (np.asarray(v) if isinstance(v, np.ndarray) and v.ndim == 1 else v)
                          for k, v in configurations.items()})
    else:
        first = configurations[0]
        if not isinstance(first, Mapping):
            raise TypeError(f"configuration 0 is a {type(first).__name__}, not a dict of column values")
        keys = list(first)
        for i, row in enumerate(configurations):
            if not isinstance(row, Mapping) or set(row) != set(keys):
                got = sorted(row) if isinstance(row, Mapping) else type(row).__name__
                raise ValueError(f"configuration {i} has columns {got}, configuration 0 has {sorted(keys)}: "
                                 "every configuration must give the same columns")
        table = pa.Table.from_pylist(list(configurations))
    for name in (STATUS, REASON):
        if name in table.column_names:
            raise ValueError(f"a configuration column is named {name!r}, a name of the results: rename it")
    for name, col in zip(table.column_names, table.columns):
        kind = _type_kind(col.type)
        if kind is None:
            raise TypeError(f"configuration column {name!r} has type {col.type}: columns must hold numbers, "
                            "booleans, strings or lists of numbers")
        if col.null_count:
            rows = np.flatnonzero(np.asarray(col.is_null().to_numpy(zero_copy_only=False)))[:5].tolist()
            raise ValueError(f"configuration column {name!r} has {col.null_count} missing values (rows {rows}"
                             f"{', ...' if col.null_count > 5 else ''}): give every configuration a value")
    if ID in table.column_names:
        ids = table.column(ID)
        if _type_kind(ids.type) != "int":
            raise TypeError(f"the id column must hold integers, got {ids.type}")
        ids = np.asarray(ids.to_numpy(), np.int64)
        if ids.min() < 0 or len(np.unique(ids)) != len(ids):
            raise ValueError("the id column must hold unique non-negative integers (one id per configuration)")
        table = table.set_column(table.column_names.index(ID), ID, pa.array(ids, pa.int64()))
    else:
        table = table.add_column(0, ID, pa.array(np.arange(n, dtype=np.int64)))
    for name, kind in (requires or {}).items():
        kind = _kind_of(kind)
        if name not in table.column_names:
            missing = [c for c in requires if c not in table.column_names]
            raise ValueError(f"the configuration table lacks the column(s) {missing} that the evaluator needs "
                             f"(it has {[c for c in table.column_names if c != ID]})")
        have = _type_kind(table.column(name).type)
        if have == kind:
            continue
        if kind == "float" and have == "int":
            i = table.column_names.index(name)
            table = table.set_column(i, name, table.column(name).cast(pa.float64()))
            continue
        raise TypeError(f"configuration column {name!r} holds {have} values ({table.column(name).type}), "
                        f"the evaluator needs {kind}")
    return table.combine_chunks()


def fingerprint(table, *extra) -> str:
    """A hash of the configuration table (column names, types and values, row order) and of
    ``extra`` (the chunk size, the evaluator's key): equal for the same sweep only."""
    h = hashlib.sha256()
    for name, col in zip(table.column_names, table.columns):
        h.update(f"{name}:{col.type}:".encode())
        if _type_kind(col.type) in ("int", "float", "bool"):
            h.update(np.ascontiguousarray(col.to_numpy()).tobytes())
        else:
            h.update(json.dumps(col.to_pylist()).encode())
    h.update(json.dumps([str(e) for e in extra]).encode())
    return h.hexdigest()


def evaluator_key(evaluate) -> str:
    """What names an evaluator in the manifest: its ``sweep_key`` attribute (an evaluator's
    settings, e.g. the phantom and the increments) or its qualified name."""
    key = getattr(evaluate, "sweep_key", None)
    if key is not None:
        return str(key)
    f = getattr(evaluate, "func", evaluate)    # functools.partial
    return f"{getattr(f, '__module__', '?')}.{getattr(f, '__qualname__', type(f).__qualname__)}"


def evaluator_code(evaluate) -> str:
    """What the evaluator computes, for the fingerprint: the ``sweep_version`` it declares
    (bump it when what it computes changes), else a hash of its source (a function's, or
    its class's and base classes'; a ``functools.partial`` adds its arguments). Code that
    it calls elsewhere is not covered: declare ``sweep_version`` for that."""
    version = getattr(evaluate, "sweep_version", None)
    if version is not None:
        return f"version {version}"
    f = getattr(evaluate, "func", evaluate)
    h = hashlib.sha256()
    if f is not evaluate:
        h.update(repr((getattr(evaluate, "args", ()), sorted(getattr(evaluate, "keywords", {}).items()))).encode())
    parts = [f] if inspect.isfunction(f) or inspect.ismethod(f) else \
        [c for c in type(f).__mro__ if c is not object]
    for part in parts:
        try:
            text = inspect.getsource(part)
        except (OSError, TypeError):       # defined at a prompt, or built in: its compiled code or its name
            code = getattr(part, "__code__", None)
            text = repr((code.co_code, code.co_consts)) if code is not None else \
                f"{getattr(part, '__module__', '?')}.{getattr(part, '__qualname__', '?')}"
        h.update(text.encode())
    return "code " + h.hexdigest()[:16]


# ------------------------------------------------------------------ evaluating a chunk
def _columns_of(chunk) -> dict:
    """A chunk (pyarrow.Table) as the dict of NumPy arrays that ``evaluate`` receives."""
    out = {}
    for name, col in zip(chunk.column_names, chunk.columns):
        if _type_kind(col.type) == "list":
            out[name] = np.array([np.asarray(v, float) for v in col.to_pylist()], dtype=object) \
                if len({len(v) for v in col.to_pylist()}) > 1 else np.asarray(col.to_pylist())
        else:
            out[name] = col.to_numpy(zero_copy_only=False)
    return out


def _arrow_column(name: str, values, rows: int):
    pa = _pa()
    if isinstance(values, (pa.Array, pa.ChunkedArray)):
        if len(values) != rows:
            raise ValueError(f"evaluate returned {len(values)} values of {name!r} for a chunk of {rows}")
        return values
    if isinstance(values, (list, tuple)) and values and isinstance(values[0], str):
        values = np.asarray(values, dtype=object)
    arr = np.asarray(values) if not isinstance(values, np.ndarray) else values
    if arr.ndim == 0 or arr.shape[0] != rows:
        raise ValueError(f"evaluate returned {name!r} of shape {arr.shape} for a chunk of {rows} configurations "
                         "(one value per configuration, leading axis)")
    if hasattr(arr, "dtype") and arr.dtype.kind in "iufb" and arr.ndim > 1:
        flat = pa.array(np.ascontiguousarray(arr).reshape(-1))
        for size in reversed(arr.shape[1:]):
            flat = pa.FixedSizeListArray.from_arrays(flat, size)
        return flat
    if arr.dtype.kind in "OUS":
        return pa.array([None if v is None else str(v) for v in arr], pa.string())
    return pa.array(arr)


def _result_table(chunk, result) -> Any:
    """The chunk's configuration columns + the evaluator's results + status and reason."""
    pa = _pa()
    if not isinstance(result, Mapping):
        raise TypeError(f"evaluate must return a dict of result columns, got {type(result).__name__}")
    rows = chunk.num_rows
    table = chunk
    for name, values in result.items():
        if name in chunk.column_names:
            raise ValueError(f"evaluate returned a column {name!r}, the name of a configuration column: rename it")
        if name in (STATUS, REASON):
            continue
        table = table.append_column(str(name), _arrow_column(str(name), values, rows))
    status = result.get(STATUS, [OK] * rows)
    reason = result.get(REASON, [""] * rows)
    table = table.append_column(STATUS, _arrow_column(STATUS, np.asarray([str(s) for s in status], object), rows))
    return table.append_column(REASON, _arrow_column(REASON, np.asarray([str(s) for s in reason], object), rows))


def failed_rows(chunk, reason: str):
    """The chunk's configurations as rows with status ``ERROR`` and ``reason``."""
    pa = _pa()
    n = chunk.num_rows
    return chunk.append_column(STATUS, pa.array([ERROR] * n, pa.string())) \
                .append_column(REASON, pa.array([reason] * n, pa.string()))


def _evaluate_isolating(evaluate, chunk):
    """evaluate the chunk; where it raises, split it in halves until the configurations that
    raise are alone (each an ``ERROR`` row); the rest keep their results."""
    pa = _pa()
    try:
        return _result_table(chunk, evaluate(_columns_of(chunk)))
    except Exception as e:            # noqa: BLE001 (a failed configuration is a row, not a crash)
        if chunk.num_rows == 1:
            return failed_rows(chunk, f"{type(e).__name__}: {e}")
    half = chunk.num_rows // 2
    parts = [_evaluate_isolating(evaluate, chunk.slice(0, half)),
             _evaluate_isolating(evaluate, chunk.slice(half))]
    return pa.concat_tables(parts, promote_options="permissive")


_EVALUATORS: dict = {}    # per process: evaluators by key (a worker builds one once, not per chunk)


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
    return _evaluate_isolating(evaluate, chunk)


def worker_settings(env: Mapping | None = None, jax_options: Mapping | None = None) -> dict:
    """The settings a sweep passes to its workers: float64 and the driver's values of
    ``FORWARDED_CONFIG`` (where JAX is imported), ``jax_options`` over them, and ``env``
    (e.g. ``{"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}``
    to keep each worker on one core)."""
    import sys
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


# ------------------------------------------------------------------ the folder
def chunk_path(out: Path, k: int) -> Path:
    return Path(out) / f"chunk-{k:0{CHUNK_DIGITS}d}.parquet"


def _finished_chunks(out: Path) -> dict:
    """chunk number -> its file, for the chunk files in ``out``."""
    found = {}
    for p in Path(out).glob("chunk-*.parquet"):
        stem = p.stem.split("-", 1)[1]
        if stem.isdigit():
            found[int(stem)] = p
    return found


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_atomic(path: Path, write: Callable[[Path], None]) -> None:
    """``write(tmp)`` to a temporary name beside ``path``, flushed to disk, then renamed to
    ``path``: ``path`` exists only whole. A failed write removes the temporary file."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def _write_chunk(out: Path, k: int, table, fingerprint: str) -> None:
    import pyarrow.parquet as pq
    # the sweep's fingerprint travels in the file: a chunk of another sweep is recognised
    meta = {**(table.schema.metadata or {}), META_KEY: json.dumps({"fingerprint": fingerprint, "chunk": k}).encode()}
    table = table.replace_schema_metadata(meta)
    write_atomic(chunk_path(out, k), lambda tmp: pq.write_table(table, tmp))


def _chunk_schemas(out: Path, files: dict, manifest: dict) -> list:
    """The schemas of the chunk files ``files`` ({chunk number: path}), each checked: readable
    and carrying the fingerprint of the sweep whose ``manifest`` the folder holds; raises a
    :class:`SweepFolderError` naming the file otherwise."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    fp, legacy = manifest.get("fingerprint"), manifest.get("version", 1) < 2
    schemas = []
    for k, path in sorted(files.items()):
        try:
            schema = pq.read_schema(path)
        except (pa.ArrowException, OSError) as e:
            raise SweepFolderError(f"the chunk file {path} is unreadable ({type(e).__name__}: {e}), cut short or "
                                   f"not Parquet: delete it and run the same sweep again to redo chunk {k}") from None
        raw = (schema.metadata or {}).get(META_KEY)
        if raw is None and legacy:        # written before chunks carried the fingerprint
            schemas.append(schema)
            continue
        try:
            meta = json.loads(raw)
        except (TypeError, ValueError):
            meta = {}
        if not isinstance(meta, dict) or meta.get("fingerprint") != fp:
            raise SweepFolderError(f"the chunk file {path} was not written by the sweep in {out}/ (its fingerprint "
                                   f"{str(meta.get('fingerprint') if isinstance(meta, dict) else None)[:12]}, the "
                                   f"sweep's {str(fp)[:12]}): a chunk of another sweep; delete it and run the "
                                   f"sweep again to redo chunk {k}")
        if meta.get("chunk") != k:
            raise SweepFolderError(f"the chunk file {path} holds chunk {meta.get('chunk')} of this sweep, not chunk "
                                   f"{k}: delete it and run the sweep again to redo chunk {k}")
        schemas.append(schema.remove_metadata())
    return schemas


def _claim(out: Path, manifest: dict) -> dict:
    """Write the manifest into ``out``, or check that the one there is this sweep's; returns
    the manifest in force (an earlier version's, whose fingerprint does not cover the
    evaluator's code, where the folder holds one of this sweep)."""
    legacy = manifest.pop("legacy_fingerprint", None)
    path = manifest_path(out)
    if path.exists():
        try:
            earlier = json.loads(path.read_text())
            if not isinstance(earlier, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError) as e:
            raise SweepFolderError(f"{path} is unreadable ({e}): choose another folder or remove it") from None
        mine = legacy if earlier.get("version", 1) < 2 else manifest["fingerprint"]
        if earlier.get("fingerprint") != mine:
            names = {"configurations": "configurations", "chunk_size": "chunk_size", "evaluator": "evaluator",
                     "columns": "columns", "evaluator_code": "the evaluator's code (or its sweep_version)"}
            diff = [words for k, words in names.items() if earlier.get(k) != manifest.get(k)]
            what = f"they differ in {', '.join(diff)}" if diff else "the configuration values differ"
            raise SweepFolderError(f"{out}/ holds the results of another sweep ({what}; its manifest: "
                                   f"{earlier.get('configurations')} configurations, evaluator "
                                   f"{earlier.get('evaluator')!r}): choose another folder, or delete it to start over")
        if path.name == LEGACY_SWEEP_FILE:     # an earlier version's folder: readable by any Parquet reader now
            os.replace(path, out / SWEEP_FILE)
        return earlier
    strays = [p.name for p in out.iterdir() if not p.name.startswith(".")]
    if strays:
        raise SweepFolderError(f"{out}/ already holds files and no sweep manifest ({', '.join(sorted(strays)[:5])}): "
                               "choose an empty or new folder")
    write_atomic(out / SWEEP_FILE, lambda tmp: tmp.write_text(json.dumps(manifest, indent=1)))
    return manifest


def _lock(out: Path):
    from filelock import FileLock, Timeout
    lock = FileLock(str(out / ".sweep.lock"))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        raise SweepInUseError(f"another sweep is writing into {out}/ (its lock {out / '.sweep.lock'} is "
                               "held): wait for it, or choose another folder") from None
    return lock


# ------------------------------------------------------------------ executors
def _dask(executor):
    """(client, owned) for a ``distributed.Client`` or a scheduler address."""
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


def _run_local(todo, chunks, evaluate, settings, done):
    for k in todo:
        done(k, run_chunk(evaluate, chunks(k), None))


def _run_dask(executor, todo, chunks, evaluate, settings, done):
    """Chunks as Dask tasks, at most two per worker thread in flight (plus a few): the
    scheduler holds a window, not the whole sweep, and an interrupted driver loses at most
    the window's work."""
    import distributed
    client, owned = _dask(executor)
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


# ------------------------------------------------------------------ the chunk size
class ChunkChoice(NamedTuple):
    """What :func:`choose_chunk_size` measured: the chunk ``sizes`` tried (doubling), the
    ``seconds`` of one evaluation of each once compiled, and the size ``chosen``."""

    sizes: tuple
    seconds: tuple
    chosen: int
    why: str

    @property
    def throughput(self) -> tuple:
        """Configurations per second at each size."""
        return tuple(n / t for n, t in zip(self.sizes, self.seconds))


def _measure_chunk_sizes(evaluate, table, start, tolerance, max_chunk_s, settings, report) -> ChunkChoice:
    """Evaluate the first rows of ``table`` at doubling chunk sizes (each twice: the first
    call compiles, the second is timed) while a larger size is worth measuring; see
    :func:`choose_chunk_size`."""
    apply_settings(settings)
    n = table.num_rows
    largest = min(n, MAX_CHUNK)
    sizes, seconds = [], []
    size, why = min(start, largest), ""
    if size == n:
        return ChunkChoice((), (), n, "the whole table is one chunk of the first size: nothing to measure")
    while True:
        chunk = table.slice(0, size)
        t0 = time.perf_counter()
        first = _evaluate_isolating(evaluate, chunk)
        tic = time.perf_counter()
        _evaluate_isolating(evaluate, chunk)
        sizes.append(size)
        seconds.append(time.perf_counter() - tic)
        cost = time.perf_counter() - t0          # this size's measuring: compile and two calls
        rate = [s / t for s, t in zip(sizes, seconds)]
        report(f"chunk size {size}: {seconds[-1]:.3g} s per chunk, {rate[-1]:.3g} configurations/s")
        if ERROR in first.column(STATUS).to_pylist():
            why = "the evaluator raised on some of these configurations: their timing is not the chunk's"
        elif size >= largest:
            why = "the whole table" if size >= n else f"MAX_CHUNK ({MAX_CHUNK})"
        elif 2 * seconds[-1] > max_chunk_s:
            why = f"a chunk of twice the size would take over {max_chunk_s:g} s (what an interruption may lose)"
        elif len(rate) > 1 and n / rate[-1] * (1 - rate[-2] / rate[-1]) < cost + 2 * seconds[-1]:
            # the next size, if it gained as much as this one did, would shorten the sweep by
            # less than measuring it costs (its compile, and two calls of twice this chunk):
            # where the throughput has stopped growing, it saves nothing
            why = "the next size would save less time than measuring it takes"
        if why:
            break
        size = min(2 * size, largest)
    # the smallest size within ``tolerance`` of the best throughput (one timing each: a few
    # percent is noise), as smaller chunks lose less to an interruption
    best = max(rate)
    chosen = min(s for s, r in zip(sizes, rate) if r >= (1 - tolerance) * best)
    return ChunkChoice(tuple(sizes), tuple(seconds), int(chosen), why)


def choose_chunk_size(configurations, evaluate, *, executor=None, start: int = 4, tolerance: float = 0.05,
                      max_chunk_s: float = 60.0, progress: bool = True,
                      requires: Mapping | None = None, settings: Mapping | None = None,
                      max_configurations: int = MAX_CONFIGURATIONS) -> ChunkChoice:
    """The chunk size of a sweep by measured throughput: the first ``start`` configurations
    of the table, then twice as many, and so on, each evaluated twice (the second call,
    compiled, is timed), until the next size, gaining as much throughput as the last did,
    would shorten the sweep by less than measuring it costs (so measuring stops where the
    throughput stops growing, and a small sweep does not spend its time measuring), or the
    next chunk would take over ``max_chunk_s`` seconds (the work an interruption may lose), or
    the whole table (or ``MAX_CHUNK``) is one chunk. Chosen: the smallest size whose
    throughput is within ``tolerance`` (a fraction) of the best measured. A batched solver's
    throughput grows with its batch until the device is busy (a GPU: thousands; a CPU: a
    few), which is why the size is measured, not fixed (``experiments/bench_chunk_size.py``).

    With an ``executor`` (a ``distributed.Client`` or a scheduler address) the measuring runs
    on one of its workers, where the chunks will. The results computed while measuring are
    not kept (the chunk files follow the chosen size)."""
    requires = getattr(evaluate, "requires", None) if requires is None else requires
    table = configuration_table(configurations, requires, max_configurations)
    if table.num_rows == 0:
        raise ValueError("no configurations to measure the chunk size on")
    _count_in("start", start, 1, MAX_CHUNK)
    if isinstance(tolerance, (bool, np.bool_)) or not isinstance(tolerance, (int, float)) or not 0 <= tolerance < 1:
        raise ValueError(f"tolerance must be a fraction in [0, 1), got {tolerance!r}")
    if isinstance(max_chunk_s, (bool, np.bool_)) or not isinstance(max_chunk_s, (int, float)) or not max_chunk_s > 0:
        raise ValueError(f"max_chunk_s must be a positive number of seconds, got {max_chunk_s!r}")
    settings = worker_settings() if settings is None else settings
    if executor is None:
        import sys
        from tqdm import tqdm
        # what is measured goes where the bars go (stderr, on a terminal), not into stdout
        report = (lambda line: tqdm.write(line, file=sys.stderr)) if progress and _terminal() else _quiet
        return _measure_chunk_sizes(evaluate, table, start, tolerance, max_chunk_s, settings, report)
    client, owned = _dask(executor)
    try:
        fut = client.submit(_measure_chunk_sizes, evaluate, table, start, tolerance, max_chunk_s, settings, _quiet,
                            pure=False)
        return fut.result()
    finally:
        if owned:
            client.close()


def _terminal() -> bool:
    import sys
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


def _quiet(line) -> None:
    """A worker's report (it has no terminal to show it on)."""


def _count_in(name, v, low, high) -> None:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not low <= v <= high:
        raise ValueError(f"{name} must be a whole number in {low}..{high}, got {v!r}")


def _chunk_size_of(out, configurations, evaluate, chunk_size=AUTO, **measure) -> tuple[int, ChunkChoice | None]:
    """The chunk size a sweep into ``out`` uses: ``chunk_size`` where given as a number; for
    ``"auto"`` the folder's (a rerun resumes with the size it started with), else one
    measured by :func:`choose_chunk_size` (``measure``: its options), with what it measured."""
    if not (isinstance(chunk_size, str) and chunk_size == AUTO):
        if isinstance(chunk_size, (bool, np.bool_)) or not isinstance(chunk_size, (int, np.integer)) \
                or not 1 <= chunk_size <= MAX_CHUNK:
            raise ValueError(f"chunk_size must be a whole number of configurations in 1..{MAX_CHUNK} or "
                             f"{AUTO!r}, got {chunk_size!r}")
        return int(chunk_size), None
    earlier = _folder_chunk_size(out)
    if earlier:
        return earlier, None
    choice = choose_chunk_size(configurations, evaluate, **measure)
    return choice.chosen, choice


def manifest_path(out) -> Path:
    """The manifest of the sweep in ``out``: ``_sweep.json``, or an earlier version's
    ``sweep.json`` where only that exists."""
    out = Path(out)
    if not (out / SWEEP_FILE).exists() and (out / LEGACY_SWEEP_FILE).exists():
        return out / LEGACY_SWEEP_FILE
    return out / SWEEP_FILE


def _folder_chunk_size(out) -> int | None:
    """The chunk size of the sweep whose manifest ``out`` holds, or None."""
    try:
        return int(json.loads(manifest_path(out).read_text())["chunk_size"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


# ------------------------------------------------------------------ the sweep
def sweep(configurations, evaluate: Callable[[dict], Mapping], out, *, chunk_size: int | None = None,
          executor=None, progress: bool = True, requires: Mapping | None = None,
          settings: Mapping | None = None, max_configurations: int = MAX_CONFIGURATIONS) -> SweepSummary:
    """Evaluate every configuration of ``configurations`` with ``evaluate``, chunk by chunk,
    into the Parquet results table in folder ``out`` (see the module docstring: format,
    resume, failures, executors). A rerun of the same call skips the chunks already written.

    ``chunk_size``: configurations per ``evaluate`` call (1..``MAX_CHUNK``; default the
    evaluator's ``chunk_size`` attribute, else the folder's, else ``DEFAULT_CHUNK``), or
    ``"auto"``: the folder's, else measured on the first configurations
    (:func:`choose_chunk_size`, recorded in the manifest).
    ``executor``: None (in process), a ``distributed.Client`` or a scheduler address.
    ``requires``: {column: kind} the table must hold (default ``evaluate.requires``).
    ``settings``: what the workers set before computing (default :func:`worker_settings`).
    Returns a :class:`SweepSummary`; read the results with :func:`read_sweep`."""
    requires = getattr(evaluate, "requires", None) if requires is None else requires
    table = configuration_table(configurations, requires, max_configurations)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise SweepFolderError(f"cannot write the sweep to {out}/: it is a file")
    out.mkdir(parents=True, exist_ok=True)
    if chunk_size is None:
        chunk_size = getattr(evaluate, "chunk_size", None)
    if chunk_size is None:
        chunk_size = _folder_chunk_size(out) or DEFAULT_CHUNK
    chunk_size, choice = _chunk_size_of(out, table, evaluate, chunk_size, executor=executor, progress=progress,
                                          requires=requires, settings=settings, max_configurations=max_configurations)
    if hasattr(evaluate, "for_chunk_size"):    # it pads every batch to the chunk size: one program for all
        evaluate = evaluate.for_chunk_size(chunk_size)
    n = table.num_rows
    n_chunks = -(-n // chunk_size)
    key, code = evaluator_key(evaluate), evaluator_code(evaluate)
    manifest = {"format": FORMAT, "version": VERSION, "fingerprint": fingerprint(table, chunk_size, key, code),
                "configurations": n, "chunk_size": chunk_size, "chunks": n_chunks, "evaluator": key,
                "evaluator_code": code, "legacy_fingerprint": fingerprint(table, chunk_size, key),
                "columns": {c: str(t) for c, t in zip(table.column_names, table.schema.types)},
                "files": f"chunk-{'N' * CHUNK_DIGITS}.parquet: configurations [N * chunk_size, (N + 1) * chunk_size)",
                "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    if choice is not None:
        manifest["chunk_size_measured"] = {"sizes": list(choice.sizes), "seconds": list(choice.seconds),
                                           "why_stopped": choice.why}
    lock = _lock(out)
    try:
        manifest = _claim(out, manifest)
        for stale in out.glob(".chunk-*.tmp"):    # a write cut short by a killed driver
            stale.unlink(missing_ok=True)
        finished = _finished_chunks(out)
        _chunk_schemas(out, {k: p for k, p in finished.items() if k < n_chunks}, manifest)
        todo = [k for k in range(n_chunks) if k not in finished]

        def chunks(k):
            return table.slice(k * chunk_size, chunk_size)

        # on a terminal only, drawn in place and left once at the end
        bar = progress_bar(n, initial=sum(chunks(k).num_rows for k in finished if k < n_chunks),
                           unit="config", desc="sweep", progress=progress, leave=True)
        failed = [0]

        def done(k, result):
            _write_chunk(out, k, result, manifest["fingerprint"])
            failed[0] += int(np.sum(np.asarray(result.column(STATUS).to_pylist()) == ERROR))
            bar.update(result.num_rows)
            if failed[0]:
                bar.set_postfix(errors=failed[0])
        try:
            settings = worker_settings() if settings is None else settings
            if executor is None:
                _run_local(todo, chunks, evaluate, settings, done)
            else:
                _run_dask(executor, todo, chunks, evaluate, settings, done)
        finally:
            bar.close()
    finally:
        lock.release()
    statuses = status_counts(out)
    return SweepSummary(out, n, n_chunks, n_chunks - len(todo), len(todo), statuses)


# ------------------------------------------------------------------ reading back
def _files(out: Path) -> dict:
    out = Path(out)
    if not manifest_path(out).exists():
        # a run's output folder often holds its sweep one level down (the CLI's DIR/table/)
        below = sorted({p.parent.name for name in (SWEEP_FILE, LEGACY_SWEEP_FILE)
                        for p in out.glob(f"*/{name}")}) if out.is_dir() else []
        hint = f": the sweep is in {out / below[0]}/" if len(below) == 1 else \
            (f": sweeps are in its subfolders {below}" if below else ": give the folder a sweep wrote")
        raise FileNotFoundError(f"{out}/ holds no sweep (no {SWEEP_FILE}){hint}")
    return _finished_chunks(out)


def _manifest(out: Path) -> dict:
    try:
        manifest = json.loads(manifest_path(out).read_text())
        if not isinstance(manifest, dict):
            raise ValueError("not a JSON object")
        return manifest
    except (OSError, ValueError) as e:
        raise SweepFolderError(f"{manifest_path(out)} is unreadable ({e}): the folder's manifest is damaged") from None


def results_dataset(out):
    """The results in ``out`` as a ``pyarrow.dataset.Dataset`` (lazy: filter and select
    columns before reading), over the chunk files written so far, each checked (readable,
    and written by this folder's sweep: :class:`SweepFolderError` names the file otherwise);
    the schema unifies the chunks (a chunk of ``ERROR`` rows only lacks the result columns:
    they read as null)."""
    import pyarrow.dataset as ds
    files = _files(out)
    schemas = _chunk_schemas(Path(out), files, _manifest(Path(out)))
    schema = _pa().unify_schemas(schemas, promote_options="permissive") if schemas else None
    return ds.dataset([str(p) for _, p in sorted(files.items())], schema=schema, format="parquet")


def read_sweep(out, columns: Sequence[str] | None = None, check: bool = True):
    """The whole results table in ``out`` (a ``pyarrow.Table``, sorted by ``id``), one row per
    configuration of the chunks finished so far; ``columns``: only these. With ``check``,
    raises if an id appears twice (it never should: each chunk is one file). Convert with
    ``.to_pandas()`` / ``polars.from_arrow``; or read the folder with any Parquet reader."""
    dataset = results_dataset(out)
    cols = None if columns is None else list(dict.fromkeys([ID, *columns]))
    table = dataset.to_table(columns=cols)
    if table.num_rows:
        table = table.sort_by(ID)
    if check and table.num_rows:
        ids = table.column(ID).to_numpy()
        if np.any(np.diff(ids) == 0):
            raise RuntimeError(f"{out}/: configuration ids appear more than once: the folder mixes sweeps")
    return table if columns is None or ID in columns else table.drop_columns([ID])


def status_counts(out) -> dict:
    """Rows per status over the chunks written to ``out``."""
    table = results_dataset(out).to_table(columns=[STATUS])
    names, counts = np.unique(np.asarray(table.column(STATUS).to_pylist(), dtype=object).astype(str),
                              return_counts=True) if table.num_rows else ([], [])
    return {str(k): int(c) for k, c in zip(names, counts)}
