"""A sweep's chunk size: resolved in one place (:func:`resolve_chunk_size`), given or
measured (:func:`choose_chunk_size`).

Given as a number, or ``"auto"``: measured on the first configurations. The throughput of a
batched solver grows with its batch until the device is busy, which on a GPU is thousands of
configurations and on a CPU a few; hence measured, not fixed
(``experiments/bench_chunk_size.py``).
"""
from __future__ import annotations

import sys
import time
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from .executors import apply_settings, dask_client, evaluate_isolating, worker_settings
from .limits import AUTO, DEFAULT_CHUNK, MAX_CHUNK, MAX_CONFIGURATIONS
from .schema import ERROR, STATUS, configuration_table
from .storage import folder_chunk_size


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

    def record(self) -> dict:
        """What the sweep's manifest records of the measuring."""
        return {"sizes": list(self.sizes), "seconds": list(self.seconds), "why_stopped": self.why}


# ------------------------------------------------------------------ the one place
def resolve_chunk_size(out, configurations, evaluate, chunk_size=None, **measure) -> tuple[int, ChunkChoice | None]:
    """The chunk size of a sweep of ``configurations`` by ``evaluate`` into the folder
    ``out``, in this order: ``chunk_size`` where given; else the evaluator's ``chunk_size``
    attribute; else the folder's (a rerun resumes with the size it started with); else
    ``DEFAULT_CHUNK``. Where that is ``"auto"``: the folder's, else measured by
    :func:`choose_chunk_size` (``measure``: its options). Returns the size (checked:
    1..``MAX_CHUNK``) and what was measured (None where nothing was)."""
    if chunk_size is None:
        chunk_size = getattr(evaluate, "chunk_size", None)
    if chunk_size is None:
        chunk_size = folder_chunk_size(out) or DEFAULT_CHUNK
    if not (isinstance(chunk_size, str) and chunk_size == AUTO):
        return _checked_chunk_size(chunk_size), None
    earlier = folder_chunk_size(out)
    if earlier:
        return earlier, None
    choice = choose_chunk_size(configurations, evaluate, **measure)
    return choice.chosen, choice


def _checked_chunk_size(chunk_size) -> int:
    if isinstance(chunk_size, (bool, np.bool_)) or not isinstance(chunk_size, (int, np.integer)) \
            or not 1 <= chunk_size <= MAX_CHUNK:
        raise ValueError(f"chunk_size must be a whole number of configurations in 1..{MAX_CHUNK} or "
                         f"{AUTO!r}, got {chunk_size!r}")
    return int(chunk_size)


# ------------------------------------------------------------------ measured
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
    _check_measuring(start, tolerance, max_chunk_s)
    settings = worker_settings() if settings is None else settings
    if executor is None:
        from tqdm import tqdm
        # what is measured goes where the bars go (stderr, on a terminal), not into stdout
        report = (lambda line: tqdm.write(line, file=sys.stderr)) if progress and _terminal() else _quiet
        return _measure_chunk_sizes(evaluate, table, start, tolerance, max_chunk_s, settings, report)
    client, owned = dask_client(executor)
    try:
        fut = client.submit(_measure_chunk_sizes, evaluate, table, start, tolerance, max_chunk_s, settings, _quiet,
                            pure=False)
        return fut.result()
    finally:
        if owned:
            client.close()


def _check_measuring(start, tolerance, max_chunk_s) -> None:
    _count_in("start", start, 1, MAX_CHUNK)
    if isinstance(tolerance, (bool, np.bool_)) or not isinstance(tolerance, (int, float)) or not 0 <= tolerance < 1:
        raise ValueError(f"tolerance must be a fraction in [0, 1), got {tolerance!r}")
    if isinstance(max_chunk_s, (bool, np.bool_)) or not isinstance(max_chunk_s, (int, float)) or not max_chunk_s > 0:
        raise ValueError(f"max_chunk_s must be a positive number of seconds, got {max_chunk_s!r}")


def _count_in(name, v, low, high) -> None:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not low <= v <= high:
        raise ValueError(f"{name} must be a whole number in {low}..{high}, got {v!r}")


def _terminal() -> bool:
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


def _quiet(line) -> None:
    """A worker's report (it has no terminal to show it on)."""


def _measure_chunk_sizes(evaluate, table, start, tolerance, max_chunk_s, settings, report) -> ChunkChoice:
    """Evaluate the first rows of ``table`` at doubling chunk sizes (each twice: the first
    call compiles, the second is timed) while a larger size is worth measuring; see
    :func:`choose_chunk_size`."""
    apply_settings(settings)
    n = table.num_rows
    largest = min(n, MAX_CHUNK)
    sizes, seconds = [], []
    size = min(start, largest)
    if size == n:
        return ChunkChoice((), (), n, "the whole table is one chunk of the first size: nothing to measure")
    while True:
        chunk = table.slice(0, size)
        t0 = time.perf_counter()
        first = evaluate_isolating(evaluate, chunk)
        tic = time.perf_counter()
        evaluate_isolating(evaluate, chunk)
        sizes.append(size)
        seconds.append(time.perf_counter() - tic)
        cost = time.perf_counter() - t0          # this size's measuring: compile and two calls
        rate = [s / t for s, t in zip(sizes, seconds)]
        report(f"chunk size {size}: {seconds[-1]:.3g} s per chunk, {rate[-1]:.3g} configurations/s")
        why = _why_stop(first, size, n, largest, seconds[-1], rate, cost, max_chunk_s)
        if why:
            break
        size = min(2 * size, largest)
    # the smallest size within ``tolerance`` of the best throughput (one timing each: a few
    # percent is noise), as smaller chunks lose less to an interruption
    best = max(rate)
    chosen = min(s for s, r in zip(sizes, rate) if r >= (1 - tolerance) * best)
    return ChunkChoice(tuple(sizes), tuple(seconds), int(chosen), why)


def _why_stop(first, size, n, largest, last_s, rate, cost, max_chunk_s) -> str:
    """Why measuring stops at ``size`` (its results ``first``, one call ``last_s`` seconds,
    its measuring ``cost`` seconds; ``rate``: the throughputs so far), or "" to go on."""
    if ERROR in first.column(STATUS).to_pylist():
        return "the evaluator raised on some of these configurations: their timing is not the chunk's"
    if size >= largest:
        return "the whole table" if size >= n else f"MAX_CHUNK ({MAX_CHUNK})"
    if 2 * last_s > max_chunk_s:
        return f"a chunk of twice the size would take over {max_chunk_s:g} s (what an interruption may lose)"
    if len(rate) > 1 and n / rate[-1] * (1 - rate[-2] / rate[-1]) < cost + 2 * last_s:
        # the next size, if it gained as much as this one did, would shorten the sweep by
        # less than measuring it costs (its compile, and two calls of twice this chunk):
        # where the throughput has stopped growing, it saves nothing
        return "the next size would save less time than measuring it takes"
    return ""
