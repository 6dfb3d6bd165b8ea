"""One vocabulary for outcomes: every enumeration of results (a solve, a tracking run, a
needle study, the simulated rig) is an ``Outcome``.

An Outcome is an ``int`` (so it can be a status code inside jit and in batched arrays),
prints as its name (``print(sol.status_name)`` shows ``CONVERGED``, not ``0``) and carries a
one-line message. Arrays of codes convert back with ``Kind.of(code)``.
"""
from __future__ import annotations

import enum

import numpy as np


class Outcome(enum.IntEnum):
    """Base of the outcome enumerations: members are declared as ``NAME = code, "message"``."""

    def __new__(cls, code: int, message: str = ""):
        obj = int.__new__(cls, code)
        obj._value_ = code
        obj._message = message
        return obj

    @property
    def message(self) -> str:
        return self._message

    @property
    def ok(self) -> bool:
        """A success (code 0)."""
        return int(self) == 0

    def __str__(self) -> str:
        return self.name

    def __format__(self, spec: str) -> str:
        return format(self.name, spec)

    @classmethod
    def of(cls, code) -> "Outcome":
        """The member of a code (a Python int, a NumPy or a concrete JAX scalar)."""
        arr = np.asarray(code)
        if arr.ndim:
            raise ValueError(f"{cls.__name__}.of takes one code, got an array of shape {arr.shape}")
        return cls(int(arr))
