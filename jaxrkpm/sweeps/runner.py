"""The sweep: the configuration table checked, the chunk size resolved, the folder claimed,
the chunks not yet on disk evaluated where the executor says and written as they finish
(see the package docstring: the call; :mod:`.storage`: format and resume;
:mod:`.executors`: failures and executors)."""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from ..base.progress import progress_bar
from .chunk_size import resolve_chunk_size
from .executors import run_chunks, worker_settings
from .limits import MAX_CONFIGURATIONS
from .schema import ERROR, STATUS, configuration_table
from .storage import (SweepFolderError, chunk_schemas, claim, finished_chunks, lock_folder, new_manifest,
                      remove_cut_writes, status_counts, write_chunk)


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


def sweep(configurations, evaluate: Callable[[dict], Mapping], out, *, chunk_size: int | None = None,
          executor=None, progress: bool = True, requires: Mapping | None = None,
          settings: Mapping | None = None, max_configurations: int = MAX_CONFIGURATIONS) -> SweepSummary:
    """Evaluate every configuration of ``configurations`` with ``evaluate``, chunk by chunk,
    into the Parquet results table in folder ``out`` (see :mod:`jaxrkpm.sweeps`: format,
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
    out = _output_folder(out)
    chunk_size, choice = resolve_chunk_size(out, table, evaluate, chunk_size, executor=executor, progress=progress,
                                            requires=requires, settings=settings,
                                            max_configurations=max_configurations)
    if hasattr(evaluate, "for_chunk_size"):    # it pads every batch to the chunk size: one program for all
        evaluate = evaluate.for_chunk_size(chunk_size)
    manifest = new_manifest(table, chunk_size, evaluate, None if choice is None else choice.record())
    n, n_chunks = table.num_rows, manifest["chunks"]
    lock = lock_folder(out)
    try:
        manifest = claim(out, manifest)
        remove_cut_writes(out)
        finished = {k: p for k, p in finished_chunks(out).items() if k < n_chunks}
        chunk_schemas(out, finished, manifest)     # each checked: whole, and this sweep's
        todo = [k for k in range(n_chunks) if k not in finished]
        _evaluate_chunks(out, table, chunk_size, finished, todo, evaluate, manifest["fingerprint"],
                         executor=executor, settings=settings, progress=progress)
    finally:
        lock.release()
    return SweepSummary(out, n, n_chunks, n_chunks - len(todo), len(todo), status_counts(out))


def _output_folder(out) -> Path:
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise SweepFolderError(f"cannot write the sweep to {out}/: it is a file")
    out.mkdir(parents=True, exist_ok=True)
    return out


class _ChunkWriter:
    """What happens as a chunk finishes: its file written, the bar moved on (with the count
    of ``ERROR`` rows so far)."""

    def __init__(self, out: Path, fingerprint: str, bar):
        self.out, self.fingerprint, self.bar, self.errors = out, fingerprint, bar, 0

    def __call__(self, k: int, result) -> None:
        write_chunk(self.out, k, result, self.fingerprint)
        self.errors += int(np.sum(np.asarray(result.column(STATUS).to_pylist()) == ERROR))
        self.bar.update(result.num_rows)
        if self.errors:
            self.bar.set_postfix(errors=self.errors)


def _evaluate_chunks(out, table, chunk_size, finished, todo, evaluate, fingerprint, *, executor, settings,
                     progress) -> None:
    """Evaluate the chunks ``todo`` of ``table`` and write each as it finishes, behind a bar
    that starts at the rows of the chunks ``finished`` already."""
    def chunks(k):
        return table.slice(k * chunk_size, chunk_size)

    # on a terminal only, drawn in place and left once at the end
    bar = progress_bar(table.num_rows, initial=sum(chunks(k).num_rows for k in finished),
                       unit="config", desc="sweep", progress=progress, leave=True)
    try:
        settings = worker_settings() if settings is None else settings
        run_chunks(executor, todo, chunks, evaluate, settings, _ChunkWriter(out, fingerprint, bar))
    finally:
        bar.close()
