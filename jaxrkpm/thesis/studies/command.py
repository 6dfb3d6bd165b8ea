"""A command of ``jaxrkpm`` is one study module of this package, which declares it once at its
end::

    COMMAND = Command("track", "chapter-5 Jacobian path tracking ...", parser, main, result,
                      order=20, reproduce=entries, interrupted="...")

its name on the command line, its line in ``jaxrkpm --help``, its argument parser (every
option check in it, so that a bad command line ends before any work), its ``main(argv)``, how
to read its goal from its summary, its experiments for ``jaxrkpm reproduce`` and what a run
stopped by Ctrl-C keeps. :func:`commands` finds the declarations of every module of the
package: the command line, ``reproduce`` and the experiments list read them, so a command is
added by adding its module and by nothing else.

``jaxrkpm --help`` imports every study module to read its declaration, so a study module
imports nothing heavy at its top: what it runs on (JAX, the models, matplotlib) it names
through :func:`lazy`, imported on first use.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import types
from dataclasses import dataclass
from typing import Any, Callable, Sequence

# what an interrupted run keeps where its command does not say (a staged run: nothing)
NOTHING_KEPT = "nothing was written (a run puts its folder in place when it ends)"


@dataclass(frozen=True)
class Command:
    """One command of ``jaxrkpm``, declared by its study module (``COMMAND = Command(...)``).

    ``name``: the word on the command line; ``summary``: its line in ``jaxrkpm --help``;
    ``parser()``: its argument parser (``interface.Parser``, every option check in it);
    ``main(argv)``: the run (returns its summary); ``result(summary)``: (goal reached, the
    result in words), which sets the exit code; ``order``: its place in ``jaxrkpm --help``
    and in reproduce's report (lower first); ``reproduce()``: its experiments (a sequence of
    ``experiments.Entry``, made on demand: they quote the thesis' data); ``interrupted``:
    what a run stopped by Ctrl-C keeps (DIR stands for its --out)."""

    name: str
    summary: str
    parser: Callable[[], argparse.ArgumentParser]
    main: Callable[..., Any]
    result: Callable[[Any], tuple]
    order: int = 100
    reproduce: Callable[[], Sequence] | None = None
    interrupted: str = NOTHING_KEPT

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name or self.name.startswith("-") \
                or any(c.isspace() for c in self.name):
            raise ValueError(f"a command's name is one word not starting with '-', got {self.name!r}")
        if not isinstance(self.summary, str) or not self.summary.strip() or "\n" in self.summary:
            raise ValueError(f"command {self.name!r}: its summary is one line of text, got {self.summary!r}")
        for what in ("parser", "main", "result"):
            if not callable(getattr(self, what)):
                raise ValueError(f"command {self.name!r}: {what} must be callable, got {getattr(self, what)!r}")
        if self.reproduce is not None and not callable(self.reproduce):
            raise ValueError(f"command {self.name!r}: reproduce must be a function returning its experiments "
                             f"(or None), got {self.reproduce!r}")


def _package():
    return sys.modules.get(__package__) or importlib.import_module(__package__)


def commands() -> dict:
    """name -> :class:`Command` of every module of this package that declares one (its
    ``COMMAND``), in their ``order``; two modules declaring one name is an error."""
    package = _package()
    found = {}
    for info in pkgutil.iter_modules(package.__path__, package.__name__ + "."):
        declared = getattr(importlib.import_module(info.name), "COMMAND", None)
        if not isinstance(declared, Command):
            continue
        if declared.name in found:
            raise ValueError(f"two study modules declare the command {declared.name!r}: {found[declared.name][0]} "
                             f"and {info.name}")
        found[declared.name] = (info.name, declared)
    ranked = sorted(found.items(), key=lambda kv: (kv[1][1].order, kv[0]))
    return {name: declared for name, (_, declared) in ranked}


def command(name: str) -> Command:
    """The command ``name`` (a KeyError naming the commands there are)."""
    found = commands()
    if name not in found:
        raise KeyError(f"no command {name!r}; the commands are {', '.join(found)}")
    return found[name]


class _Lazy(types.ModuleType):
    """A module imported on its first attribute access (see :func:`lazy`)."""

    def __getattr__(self, attr):
        if attr.startswith("__"):        # copy, pickle and doctest probe these: not worth an import
            raise AttributeError(attr)
        return getattr(importlib.import_module(self.__name__), attr)


def lazy(name: str) -> types.ModuleType:
    """The module ``name``, imported on the first use of one of its attributes: a study names
    JAX, the models and matplotlib at its top without loading them when ``jaxrkpm --help``
    reads its declaration. Each use looks the attribute up in the module itself, so a
    name replaced there (a test's monkeypatch) is the one used."""
    return _Lazy(name)
