"""What identifies a sweep: a hash of its configuration table, its chunk size and its
evaluator (a key naming it and what it computes). A folder's manifest and every chunk file
carry it, so that a rerun resumes only the same sweep and a chunk of another is refused."""
from __future__ import annotations

import hashlib
import inspect
import json

import numpy as np

from .schema import type_kind


def fingerprint(table, *extra) -> str:
    """A hash of the configuration table (column names, types and values, row order) and of
    ``extra`` (the chunk size, the evaluator's key): equal for the same sweep only."""
    h = hashlib.sha256()
    for name, col in zip(table.column_names, table.columns):
        h.update(f"{name}:{col.type}:".encode())
        if type_kind(col.type) in ("int", "float", "bool"):
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
        h.update(_source_of(part).encode())
    return "code " + h.hexdigest()[:16]


def _source_of(part) -> str:
    """The source of a function or class; defined at a prompt or built in: its compiled code,
    else its name."""
    try:
        return inspect.getsource(part)
    except (OSError, TypeError):
        code = getattr(part, "__code__", None)
        return repr((code.co_code, code.co_consts)) if code is not None else \
            f"{getattr(part, '__module__', '?')}.{getattr(part, '__qualname__', '?')}"
