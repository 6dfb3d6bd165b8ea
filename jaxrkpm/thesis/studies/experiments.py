"""The thesis experiments this project reproduces, one ``Entry`` each: how to run it (its
study's ``main(argv)``), how to read our number from its summary, the thesis' value and a
verdict rule. Each study declares its own (``Command.reproduce``); :func:`entries` reads them
all, in the commands' order (``jaxrkpm reproduce`` and its ``--only`` choices; no JAX).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable


@dataclass
class Entry:
    """One thesis experiment: how to run it and how to read our number from its summary."""
    id: str
    thesis_ref: str            # figure / table / section of the thesis
    thesis_value: str          # quoted from the thesis text
    run: Callable[[Path, bool], tuple]  # (out dir, quick) -> (study command, its argv)
    ours: Callable[[dict], str]         # summary -> our value, as text
    note: str = ""
    quick: bool = False        # part of --quick
    tags: list = field(default_factory=list)
    # summary -> (verdict: agrees | agrees in kind | differs, the reason in a word); None:
    # nothing in the thesis to compare with
    judge: Callable[[dict], tuple[str, str]] | None = None


# ------------------------------------------------------------------ verdicts against the thesis
AGREES, IN_KIND, DIFFERS = "agrees", "agrees in kind", "differs"

# the note of the rows that compare SCNI with the thesis' collocation (compression, tracking)
COLL = ("the thesis used collocation; we use SCNI (stabilised conforming nodal integration), "
        "the stable nodal scheme, so this compares the nodal alternative, not the same scheme")


def entries() -> list:
    """Every experiment: the entries each command declares (``Command.reproduce``), in the
    commands' order; an id declared twice is an error."""
    from jaxrkpm.thesis.studies.command import commands
    out, seen = [], {}
    for name, declared in commands().items():
        for e in (declared.reproduce() if declared.reproduce is not None else ()):
            if e.id in seen:
                raise ValueError(f"experiment {e.id!r} is declared by {seen[e.id]} and by {name}")
            seen[e.id] = name
            out.append(e)
    return out
