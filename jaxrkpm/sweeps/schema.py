"""The tables of a sweep: the configuration table going in (checked before any work, with an
``id`` column), the chunk an evaluator receives (a dict of NumPy arrays) and the results
table coming out (the configuration columns, the evaluator's result columns, ``status`` and
``reason``), as Arrow types."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .limits import MAX_CONFIGURATIONS

ID, STATUS, REASON = "id", "status", "reason"
OK, ERROR = "OK", "ERROR"
KINDS = ("int", "float", "bool", "str")


def _pa():
    import pyarrow as pa
    return pa


def _kind_of(kind) -> str:
    names = {int: "int", float: "float", bool: "bool", str: "str"}
    k = names.get(kind, kind)
    if k not in KINDS:
        raise ValueError(f"unknown column kind {kind!r}: choose one of {list(KINDS)} (or int, float, bool, str)")
    return k


def type_kind(t) -> str | None:
    """The kind of values an Arrow type holds: one of ``KINDS``, ``"list"`` (a list of
    numbers or booleans), or None (a type a configuration column may not have)."""
    import pyarrow.types as pt
    if pt.is_boolean(t):
        return "bool"
    if pt.is_integer(t):
        return "int"
    if pt.is_floating(t):
        return "float"
    if pt.is_string(t) or pt.is_large_string(t):
        return "str"
    if (pt.is_list(t) or pt.is_fixed_size_list(t) or pt.is_large_list(t)) and type_kind(t.value_type) in ("int", "float", "bool"):
        return "list"
    return None


# ------------------------------------------------------------------ the configuration table
def configuration_table(configurations, requires: Mapping | None = None,
                        max_configurations: int = MAX_CONFIGURATIONS):
    """The configurations as a ``pyarrow.Table`` with an ``id`` column, checked: at most
    ``max_configurations`` rows (counted before anything is built), columns of numbers,
    booleans, strings or lists of numbers, no missing values, ``id`` (when given) unique
    non-negative integers, no column named ``status`` or ``reason`` (result columns), and
    the columns ``requires`` names ({name: "int" | "float" | "bool" | "str"}) present with
    those kinds (an int column where a float is required is converted)."""
    n = _row_count(configurations)
    if n > max_configurations:
        raise ValueError(f"{n:,} configurations, more than max_configurations = {max_configurations:,}: "
                         "split the sweep or raise the bound")
    if n == 0:
        raise ValueError("the configuration table is empty: give at least one configuration")
    table = _as_arrow(configurations)
    _check_columns(table)
    table = _with_ids(table, n)
    return _with_required(table, requires).combine_chunks()


def _row_count(configurations) -> int:
    """The rows of a configuration table, counted before anything is built from it."""
    pa = _pa()
    if isinstance(configurations, pa.Table):
        return configurations.num_rows
    if isinstance(configurations, Mapping):
        lengths = {k: len(v) for k, v in configurations.items()}
        if len(set(lengths.values())) > 1:
            raise ValueError(f"the configuration columns differ in length: {lengths}")
        return next(iter(lengths.values()), 0)
    if isinstance(configurations, Sequence) and not isinstance(configurations, (str, bytes)):
        return len(configurations)
    raise TypeError("configurations must be a list of dicts (one per configuration), a dict of columns "
                    f"or a pyarrow.Table, got {type(configurations).__name__}")


def _as_arrow(configurations):
    """A table, a dict of columns or a list of rows (one set of columns) as a pyarrow.Table."""
    pa = _pa()
    if isinstance(configurations, pa.Table):
        return configurations
    if isinstance(configurations, Mapping):
        return pa.table({str(k): (np.asarray(v) if isinstance(v, np.ndarray) and v.ndim == 1 else v)
                         for k, v in configurations.items()})
    first = configurations[0]
    if not isinstance(first, Mapping):
        raise TypeError(f"configuration 0 is a {type(first).__name__}, not a dict of column values")
    keys = list(first)
    for i, row in enumerate(configurations):
        if not isinstance(row, Mapping) or set(row) != set(keys):
            got = sorted(row) if isinstance(row, Mapping) else type(row).__name__
            raise ValueError(f"configuration {i} has columns {got}, configuration 0 has {sorted(keys)}: "
                             "every configuration must give the same columns")
    return pa.Table.from_pylist(list(configurations))


def _check_columns(table) -> None:
    """No column named as a result; every column of a kind a chunk can hold, with no gaps."""
    for name in (STATUS, REASON):
        if name in table.column_names:
            raise ValueError(f"a configuration column is named {name!r}, a name of the results: rename it")
    for name, col in zip(table.column_names, table.columns):
        if type_kind(col.type) is None:
            raise TypeError(f"configuration column {name!r} has type {col.type}: columns must hold numbers, "
                            "booleans, strings or lists of numbers")
        if col.null_count:
            rows = np.flatnonzero(np.asarray(col.is_null().to_numpy(zero_copy_only=False)))[:5].tolist()
            raise ValueError(f"configuration column {name!r} has {col.null_count} missing values (rows {rows}"
                             f"{', ...' if col.null_count > 5 else ''}): give every configuration a value")


def _with_ids(table, n: int):
    """The table with its ``id`` column as int64: the one given (checked), else 0..n-1 first."""
    pa = _pa()
    if ID not in table.column_names:
        return table.add_column(0, ID, pa.array(np.arange(n, dtype=np.int64)))
    ids = table.column(ID)
    if type_kind(ids.type) != "int":
        raise TypeError(f"the id column must hold integers, got {ids.type}")
    ids = np.asarray(ids.to_numpy(), np.int64)
    if ids.min() < 0 or len(np.unique(ids)) != len(ids):
        raise ValueError("the id column must hold unique non-negative integers (one id per configuration)")
    return table.set_column(table.column_names.index(ID), ID, pa.array(ids, pa.int64()))


def _with_required(table, requires: Mapping | None):
    """The table with the columns ``requires`` names checked for their kinds (an int column
    where a float is required converted)."""
    pa = _pa()
    for name, kind in (requires or {}).items():
        kind = _kind_of(kind)
        if name not in table.column_names:
            missing = [c for c in requires if c not in table.column_names]
            raise ValueError(f"the configuration table lacks the column(s) {missing} that the evaluator needs "
                             f"(it has {[c for c in table.column_names if c != ID]})")
        have = type_kind(table.column(name).type)
        if have == kind:
            continue
        if kind == "float" and have == "int":
            i = table.column_names.index(name)
            table = table.set_column(i, name, table.column(name).cast(pa.float64()))
            continue
        raise TypeError(f"configuration column {name!r} holds {have} values ({table.column(name).type}), "
                        f"the evaluator needs {kind}")
    return table


# ------------------------------------------------------------------ a chunk in, its rows out
def columns_of(chunk) -> dict:
    """A chunk (pyarrow.Table) as the dict of NumPy arrays that ``evaluate`` receives."""
    out = {}
    for name, col in zip(chunk.column_names, chunk.columns):
        if type_kind(col.type) == "list":
            out[name] = np.array([np.asarray(v, float) for v in col.to_pylist()], dtype=object) \
                if len({len(v) for v in col.to_pylist()}) > 1 else np.asarray(col.to_pylist())
        else:
            out[name] = col.to_numpy(zero_copy_only=False)
    return out


def _arrow_column(name: str, values, rows: int):
    """One result column as an Arrow array of ``rows`` values: Arrow arrays as given, numbers
    of shape (rows, ...) as nested fixed-size lists, anything else as strings or numbers."""
    pa = _pa()
    if isinstance(values, (pa.Array, pa.ChunkedArray)):
        if len(values) != rows:
            raise ValueError(f"evaluate returned {len(values)} values of {name!r} for a chunk of {rows}")
        return values
    arr = _as_numpy(values)
    if arr.ndim == 0 or arr.shape[0] != rows:
        raise ValueError(f"evaluate returned {name!r} of shape {arr.shape} for a chunk of {rows} configurations "
                         "(one value per configuration, leading axis)")
    if arr.dtype.kind in "iufb" and arr.ndim > 1:
        return _fixed_size_lists(arr)
    if arr.dtype.kind in "OUS":
        return pa.array([None if v is None else str(v) for v in arr], pa.string())
    return pa.array(arr)


def _as_numpy(values) -> np.ndarray:
    """A result column as a NumPy array (a list of strings as an object array, so that its
    values stay whole strings)."""
    if isinstance(values, (list, tuple)) and values and isinstance(values[0], str):
        values = np.asarray(values, dtype=object)
    return np.asarray(values) if not isinstance(values, np.ndarray) else values


def _fixed_size_lists(arr: np.ndarray):
    """Numbers of shape (rows, n1, n2, ...) as an Arrow column of nested fixed-size lists."""
    pa = _pa()
    flat = pa.array(np.ascontiguousarray(arr).reshape(-1))
    for size in reversed(arr.shape[1:]):
        flat = pa.FixedSizeListArray.from_arrays(flat, size)
    return flat


def result_table(chunk, result) -> Any:
    """The chunk's configuration columns + the evaluator's results + status and reason."""
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
