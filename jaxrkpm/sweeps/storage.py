"""A sweep's folder: its manifest, one Parquet file per finished chunk, its lock, and reading
the results back.

**Format: Parquet** (through pyarrow), one file per finished chunk. Parquet is columnar
(a column of a million rows reads without the others), typed (floats stay float64, lists
stay lists), compressed, and a folder of Parquet files *is* a table: results are appended by
adding files, never by rewriting one, and pandas, polars, DuckDB or Spark read the folder
without jaxrkpm (``pandas.read_parquet(out)``, ``pyarrow.dataset.dataset(out)``: the
manifest's name begins with ``_``, which Parquet readers skip). Zarr/xarray suit dense
N-dimensional grids; a sweep's results are rows with mixed types and ragged failures, which
is a table.

**Resume.** The folder holds ``_sweep.json`` (the manifest: a fingerprint of the configuration
table, the chunk size, the evaluator's key and its code or declared ``sweep_version``) and
``chunk-NNNNNNN.parquet``, named by chunk number, each carrying the fingerprint in its
Parquet metadata (a chunk of another sweep, or one cut short, is refused by name). A chunk
file is written to a temporary name and renamed into place (atomic on one file system), so a
chunk file exists only whole; a rerun skips the chunks whose files exist and evaluates the
others, so each configuration is written exactly once whatever stopped the sweep (Ctrl-C, a
killed process, a full disk). A folder whose manifest describes another sweep (other
configurations, chunk size or evaluator) is refused, never mixed.
"""
from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Callable

import numpy as np

from .fingerprint import evaluator_code, evaluator_key, fingerprint
from .schema import ID, STATUS

# the manifest's name begins with "_": Parquet readers (pyarrow, pandas, polars) skip such
# names, so the folder is a dataset any of them opens; folders of earlier versions hold
# LEGACY_SWEEP_FILE, read as before and renamed when the sweep resumes
SWEEP_FILE = "_sweep.json"
LEGACY_SWEEP_FILE = "sweep.json"
FORMAT = "jaxrkpm-sweep"
VERSION = 2                         # 2: the fingerprint covers the evaluator's code; chunks carry it
META_KEY = b"jaxrkpm.sweep"         # a chunk file's Parquet metadata: {"fingerprint", "chunk"}
CHUNK_DIGITS = 7
LOCK_FILE = ".sweep.lock"


class SweepFolderError(ValueError):
    """The output folder holds another sweep's results, or is in use by a running sweep."""


class SweepInUseError(SweepFolderError):
    """Another sweep is writing into the output folder (its lock is held)."""


# ------------------------------------------------------------------ the manifest
def manifest_path(out) -> Path:
    """The manifest of the sweep in ``out``: ``_sweep.json``, or an earlier version's
    ``sweep.json`` where only that exists."""
    out = Path(out)
    if not (out / SWEEP_FILE).exists() and (out / LEGACY_SWEEP_FILE).exists():
        return out / LEGACY_SWEEP_FILE
    return out / SWEEP_FILE


def folder_chunk_size(out) -> int | None:
    """The chunk size of the sweep whose manifest ``out`` holds, or None."""
    try:
        return int(json.loads(manifest_path(out).read_text())["chunk_size"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def new_manifest(table, chunk_size: int, evaluate, measured: dict | None = None) -> dict:
    """The manifest of a sweep of the configuration ``table`` in chunks of ``chunk_size`` by
    ``evaluate``; ``measured``: how the chunk size was measured, where it was. It holds the
    fingerprint of an earlier version too (``legacy_fingerprint``, without the evaluator's
    code), which :func:`claim` uses on a folder of that version and does not write."""
    n = table.num_rows
    key, code = evaluator_key(evaluate), evaluator_code(evaluate)
    manifest = {"format": FORMAT, "version": VERSION, "fingerprint": fingerprint(table, chunk_size, key, code),
                "configurations": n, "chunk_size": chunk_size, "chunks": -(-n // chunk_size), "evaluator": key,
                "evaluator_code": code, "legacy_fingerprint": fingerprint(table, chunk_size, key),
                "columns": {c: str(t) for c, t in zip(table.column_names, table.schema.types)},
                "files": f"chunk-{'N' * CHUNK_DIGITS}.parquet: configurations [N * chunk_size, (N + 1) * chunk_size)",
                "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    if measured is not None:
        manifest["chunk_size_measured"] = measured
    return manifest


def _read_manifest(path: Path, advice: str) -> dict:
    try:
        manifest = json.loads(path.read_text())
        if not isinstance(manifest, dict):
            raise ValueError("not a JSON object")
        return manifest
    except (OSError, ValueError) as e:
        raise SweepFolderError(f"{path} is unreadable ({e}): {advice}") from None


def read_manifest(out) -> dict:
    """The manifest of the sweep in ``out`` (a :class:`SweepFolderError` where it is damaged)."""
    return _read_manifest(manifest_path(out), "the folder's manifest is damaged")


def claim(out: Path, manifest: dict) -> dict:
    """Write the manifest into ``out``, or check that the one there is this sweep's; returns
    the manifest in force (an earlier version's, whose fingerprint does not cover the
    evaluator's code, where the folder holds one of this sweep)."""
    legacy = manifest.pop("legacy_fingerprint", None)
    path = manifest_path(out)
    if not path.exists():
        strays = [p.name for p in out.iterdir() if not p.name.startswith(".")]
        if strays:
            raise SweepFolderError(f"{out}/ already holds files and no sweep manifest "
                                   f"({', '.join(sorted(strays)[:5])}): choose an empty or new folder")
        write_atomic(out / SWEEP_FILE, lambda tmp: tmp.write_text(json.dumps(manifest, indent=1)))
        return manifest
    earlier = _read_manifest(path, "choose another folder or remove it")
    mine = legacy if earlier.get("version", 1) < 2 else manifest["fingerprint"]
    if earlier.get("fingerprint") != mine:
        raise _another_sweep(out, earlier, manifest)
    if path.name == LEGACY_SWEEP_FILE:     # an earlier version's folder: readable by any Parquet reader now
        os.replace(path, out / SWEEP_FILE)
    return earlier


def _another_sweep(out: Path, earlier: dict, manifest: dict) -> SweepFolderError:
    """The error for a folder whose manifest ``earlier`` is not this sweep's, naming how they differ."""
    names = {"configurations": "configurations", "chunk_size": "chunk_size", "evaluator": "evaluator",
             "columns": "columns", "evaluator_code": "the evaluator's code (or its sweep_version)"}
    diff = [words for k, words in names.items() if earlier.get(k) != manifest.get(k)]
    what = f"they differ in {', '.join(diff)}" if diff else "the configuration values differ"
    return SweepFolderError(f"{out}/ holds the results of another sweep ({what}; its manifest: "
                            f"{earlier.get('configurations')} configurations, evaluator "
                            f"{earlier.get('evaluator')!r}): choose another folder, or delete it to start over")


def lock_folder(out: Path):
    """The folder's lock, held (a :class:`SweepInUseError` where another sweep holds it)."""
    from filelock import FileLock, Timeout
    lock = FileLock(str(out / LOCK_FILE))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        raise SweepInUseError(f"another sweep is writing into {out}/ (its lock {out / LOCK_FILE} is "
                              "held): wait for it, or choose another folder") from None
    return lock


# ------------------------------------------------------------------ chunk files
def chunk_path(out: Path, k: int) -> Path:
    return Path(out) / f"chunk-{k:0{CHUNK_DIGITS}d}.parquet"


def finished_chunks(out: Path) -> dict:
    """chunk number -> its file, for the chunk files in ``out``."""
    found = {}
    for p in Path(out).glob("chunk-*.parquet"):
        stem = p.stem.split("-", 1)[1]
        if stem.isdigit():
            found[int(stem)] = p
    return found


def remove_cut_writes(out: Path) -> None:
    """Remove the temporary chunk files of writes cut short (a killed driver)."""
    for stale in Path(out).glob(".chunk-*.tmp"):
        stale.unlink(missing_ok=True)


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


def write_chunk(out: Path, k: int, table, fingerprint: str) -> None:
    """Chunk ``k``'s results ``table`` into its file, carrying the sweep's ``fingerprint``."""
    import pyarrow.parquet as pq
    # the sweep's fingerprint travels in the file: a chunk of another sweep is recognised
    meta = {**(table.schema.metadata or {}), META_KEY: json.dumps({"fingerprint": fingerprint, "chunk": k}).encode()}
    table = table.replace_schema_metadata(meta)
    write_atomic(chunk_path(out, k), lambda tmp: pq.write_table(table, tmp))


def chunk_schemas(out: Path, files: dict, manifest: dict) -> list:
    """The schemas of the chunk files ``files`` ({chunk number: path}), each checked: readable
    and carrying the fingerprint of the sweep whose ``manifest`` the folder holds; raises a
    :class:`SweepFolderError` naming the file otherwise."""
    fp, legacy = manifest.get("fingerprint"), manifest.get("version", 1) < 2
    return [_checked_schema(out, k, path, fp, legacy) for k, path in sorted(files.items())]


def _checked_schema(out: Path, k: int, path: Path, fp, legacy: bool):
    """The schema of chunk ``k``'s file ``path`` (without its metadata), checked to be
    readable and written by the sweep of fingerprint ``fp`` as chunk ``k``; ``legacy``: a
    folder of the version whose chunks did not carry the fingerprint."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    try:
        schema = pq.read_schema(path)
    except (pa.ArrowException, OSError) as e:
        raise SweepFolderError(f"the chunk file {path} is unreadable ({type(e).__name__}: {e}), cut short or "
                               f"not Parquet: delete it and run the same sweep again to redo chunk {k}") from None
    raw = (schema.metadata or {}).get(META_KEY)
    if raw is None and legacy:        # written before chunks carried the fingerprint
        return schema
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
    return schema.remove_metadata()


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
    return finished_chunks(out)


def results_dataset(out):
    """The results in ``out`` as a ``pyarrow.dataset.Dataset`` (lazy: filter and select
    columns before reading), over the chunk files written so far, each checked (readable,
    and written by this folder's sweep: :class:`SweepFolderError` names the file otherwise);
    the schema unifies the chunks (a chunk of ``ERROR`` rows only lacks the result columns:
    they read as null)."""
    import pyarrow as pa
    import pyarrow.dataset as ds
    files = _files(out)
    schemas = chunk_schemas(Path(out), files, read_manifest(out))
    schema = pa.unify_schemas(schemas, promote_options="permissive") if schemas else None
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
