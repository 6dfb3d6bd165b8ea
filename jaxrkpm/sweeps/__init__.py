"""Sweeps (a layer of its own, beside ``discretise`` just above ``base``): a table of
configurations in, a results table on disk out, written chunk by chunk so that an interrupted
sweep loses nothing it finished and a rerun of the same call does only what is left. A
generic job runner: it imports nothing of jaxrkpm but ``base``, and only the public API and
the thesis use it (the numerics never need it).

**The call.** ``sweep(configurations, evaluate, out)`` (:mod:`.runner`): ``configurations``
is a table (a list of dicts, a dict of columns, or a ``pyarrow.Table``) with one row per
configuration (paddle placement, material parameters, inclusion stiffness, ...). The rows are
cut into chunks of ``chunk_size``; ``evaluate(chunk) -> dict of columns`` computes one chunk
(``chunk``: a dict of NumPy arrays, one per configuration column, plus ``"id"``) and returns
one value per row for each of its result columns (an array of shape (B, ...) becomes a column
of fixed-size lists), optionally with ``"status"`` (one name per row, "OK" where not given)
and ``"reason"`` (words, "" where not given). A batched solver evaluates a whole chunk in one
compiled call (:class:`jaxrkpm.thesis.sweeps.NeedleSweep` is the needle study's evaluator);
one with a ``for_chunk_size(size)`` method is replaced by what it returns once the chunk size
is known (an evaluator that pads each batch to that size, so that every chunk, the last and
short one too, runs one compiled program).

The modules, one job each:

- :mod:`.limits`: the bounds and defaults (importable without NumPy: the CLI states them);
- :mod:`.schema`: the configuration table and the result columns (their Arrow types);
- :mod:`.fingerprint`: what identifies a sweep (its table, chunk size and evaluator);
- :mod:`.storage`: the folder (manifest, chunk files, lock) and reading it back;
- :mod:`.executors`: where a chunk runs (in process or on Dask) and its failures as rows;
- :mod:`.chunk_size`: the one place that resolves a sweep's chunk size, measured or given;
- :mod:`.runner`: :func:`~.runner.sweep`, which joins them.
"""
