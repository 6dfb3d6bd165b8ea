"""The validators every layer's options use: a bad value raises a ValueError that names the
option, what it must be and what it got (a Python ``bool`` is no number here: ``True`` as an
iteration count is a slip, not a 1)."""
from __future__ import annotations

import numpy as np


def positive(name: str, v) -> None:
    """``v`` is a finite number > 0."""
    if isinstance(v, (bool, np.bool_)) or not (isinstance(v, (int, float, np.integer, np.floating))
                                               and np.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive number, got {v!r}")


def count(name: str, v, low: int = 0) -> None:
    """``v`` is an int >= ``low``."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < low:
        raise ValueError(f"{name} must be an int >= {low}, got {v!r}")


def flag(name: str, v) -> None:
    """``v`` is True or False."""
    if not isinstance(v, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {v!r}")
