"""What the studies share on the command line, importable without JAX (``jaxrkpm --help``
and ``jaxrkpm COMMAND --help`` answer at once): the parser every command's starts from
(:func:`parser`, whose checks of options together run after parsing: :class:`Parser`),
number checks that name the option and its valid range, the output folder check, the
progress bar and the one summary line a command ends with.

A study's ``parser()`` adds its options to :func:`parser`'s (every number bounded where a size
or count is made from it; sizes checked against the memory available) and its checks. Its
``main(argv)`` parses with it, claims its folder with :func:`results` before any work, runs
into a temporary folder beside it (progress bars from :func:`progress`), writes
``summary.json`` and figures, and ends with :meth:`Results.finish`: the temporary folder
takes the place of the results folder (a run that fails leaves the earlier results as they
were) and one line is printed, ``wrote DIR/: files; the result in words``, ending with
``[goal missed]`` where the exit code is 1. Its ``result(summary) -> (goal reached, words)``
gives those words and the exit code (:data:`EXIT_CODES`).

A results folder is never written over by another run: it holds ``run.json`` (the command
and the options that made it), and a run with other options (``needle --mode static`` then
``--mode optimize`` into one ``--out``), or a folder holding other files, is refused (exit 3)
unless ``--overwrite`` is given. A run with the same options replaces its own results.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from tqdm import tqdm

from jaxrkpm.sweeps import limits as sweep_limits

EXIT_OK, EXIT_GOAL, EXIT_USAGE, EXIT_OUTPUT = 0, 1, 2, 3
EXIT_INTERRUPTED = 130          # the shell's code for a run ended by Ctrl-C (128 + SIGINT)
EXIT_CODES = {
    EXIT_OK: "the study ran and reached its goal",
    EXIT_GOAL: "the study ran but did not reach its goal (a solve failed, a path was not tracked, ...): "
               "the summary line says why",
    EXIT_USAGE: "bad command line: unknown command or option, or a number out of its range",
    EXIT_OUTPUT: "the output folder (--out) cannot be created or written, or holds another run's "
                 "results (--overwrite replaces them), or results to --reuse are unreadable",
    EXIT_INTERRUPTED: "interrupted (Ctrl-C): the last line says what was kept",
}

# bounds of the counts the options of several commands make (each option's help shows its range;
# a bound of one command is in its study module):
ITERATIONS_MAX = 1_000_000      # control / Newton iterations: each one is a solve (hours at 1e6)
INCREMENTS_MAX = 1_000          # needle increments: each is a solve of every paddle (thesis: 15)
ADAM_MAX = 10_000               # Adam iterations of the paddle optimisers
DEVICES_MAX = 4096
SWEEP_CHUNK_MAX = sweep_limits.MAX_CHUNK          # configurations per chunk of a sweep
SWEEP_MAX = sweep_limits.MAX_CONFIGURATIONS      # configurations of a sweep
# peak memory per particle of a 2D model (experiments/bench_memory_2d.py: building, solving and
# differentiating the planar square at 65 x 65 particles, sparse path, compile included); sizes
# past the memory available are refused before anything is allocated
BYTES_PER_PARTICLE_2D = 125_000


class OutputError(Exception):
    """The output folder cannot be created or written (exit code 3)."""


# ------------------------------------------------------------------ numbers in range
def number(kind=float, low=None, high=None, *, low_open=False, high_open=False):
    """An argparse ``type``: ``kind`` (int or float), finite, within [low, high] (open ends
    with ``low_open``/``high_open``; None: unbounded). Out of range, argparse reports
    ``argument --step: must be a number in (0, 1], got 0`` and exits with code 2."""
    noun = "an integer" if kind is int else "a number"
    lo = None if low is None else ("(" if low_open else "[") + f"{low:g}"
    hi = None if high is None else f"{high:g}" + (")" if high_open else "]")
    if lo and hi:
        span = f"in {lo}, {hi}"
    elif lo:
        span = (">" if low_open else ">=") + f" {low:g}"
    elif hi:
        span = ("<" if high_open else "<=") + f" {high:g}"
    else:
        span = "finite"
    wanted = f"must be {noun} {span}"

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{wanted}, got {text!r}") from None
        below = low is not None and (value <= low if low_open else value < low)
        above = high is not None and (value >= high if high_open else value > high)
        if not math.isfinite(value) or below or above:
            raise argparse.ArgumentTypeError(f"{wanted}, got {text}")
        return value
    parse.__name__ = kind.__name__   # argparse names the type in its own messages
    return parse


POSITIVE = number(float, 0, low_open=True)
COUNT = number(int, 1)


def iterations(high=ITERATIONS_MAX):
    return number(int, 1, high)


def devices_error(requested) -> str | None:
    """A usage message when --devices asks for more devices than JAX sees (the sweep would
    silently use fewer); None when it fits or is not given."""
    if requested is None:
        return None
    import jax
    visible = len(jax.devices())
    if requested > visible:
        return (f"argument --devices: {requested} asked, but JAX sees {visible} device(s) "
                f"({jax.devices()[0].platform}); give at most {visible}")
    return None


def out_dir(text: str) -> str:
    """An argparse ``type`` for --out: a folder name, not empty (an empty one would write into
    the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"must name a folder, got {text!r}")
    return text


def available_memory() -> int:
    """Bytes of memory this process may still take: MemAvailable of /proc/meminfo, else the
    physical memory."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 2 ** 40


def memory_error(option: str, value, particles: int, per_particle: int = BYTES_PER_PARTICLE_2D,
                 side=None) -> str | None:
    """A usage message when a model of ``particles`` particles would need more memory than is
    available (estimated at ``per_particle`` bytes each, before anything is allocated); None
    when it fits. ``side(n) -> particles``: to name the largest value that fits."""
    need, have = particles * per_particle, available_memory()
    if need <= have:
        return None
    largest = ""
    if side is not None:
        n = int(value)
        while n > 1 and side(n) * per_particle > have:
            n = max(1, int(n * 0.9))
        largest = f"; the largest {option} that fits is about {n}"
    return (f"argument {option}: {value} makes {particles:,} particles, about {need / 2**30:,.1f} GiB "
            f"(~{per_particle / 1e3:.0f} kB a particle), more than the {have / 2**30:,.1f} GiB available"
            + largest)


# ------------------------------------------------------------------ parsers
class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """The description as written, and every option's default in its help (unless the help
    says it already; a flag is off unless given)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if "default" in text or action.default is None or action.default is False \
                or action.default == argparse.SUPPRESS or not action.option_strings:
            return text
        shown = "%(default)s" if not isinstance(action.default, float) else f"{action.default:g}"
        return f"{text} (default {shown})".strip()


class Parser(argparse.ArgumentParser):
    """A command's argument parser: its errors are one line, ``jaxrkpm CMD: error: what
    (jaxrkpm CMD --help)``, exit code 2 (argparse's own prints its usage block first), and it
    runs the command's checks of options together (:meth:`check`) after parsing, so that
    every bad command line ends in the parser, before any work."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.checks = []

    def add_argument(self, *args, **kwargs):
        if "help" not in kwargs and kwargs.get("action") not in ("store_true", "store_false"):
            kwargs["help"] = "(default %(default)s)"     # every option shows its default
        return super().add_argument(*args, **kwargs)

    def check(self, rule):
        """Add ``rule(args, given) -> message or None`` (``given``: the options given on the
        command line, dest names), run after parsing: a message is a usage error. Returns
        ``rule`` (a decorator)."""
        self.checks.append(rule)
        return rule

    def parse_args(self, args=None, namespace=None):
        argv = sys.argv[1:] if args is None else list(args)
        parsed = super().parse_args(argv, namespace)
        if self.checks:
            given = self.given(argv)
            for rule in self.checks:
                if message := rule(parsed, given):
                    self.error(message)
        return parsed

    def given(self, argv) -> set:
        """The options given in ``argv`` (dest names; abbreviations resolved)."""
        saved = [(action, action.default) for action in self._actions]
        try:
            for action, _ in saved:
                action.default = argparse.SUPPRESS
            parsed, _ = super().parse_known_args(list(argv))
        finally:
            for action, default in saved:
                action.default = default
        return set(vars(parsed))

    def error(self, message):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {' '.join(str(message).split())} ({self.prog} --help)\n")


def parser(command: str, description: str, default_out: str) -> Parser:
    """A command's parser with the options every command has (a study's ``parser()`` adds
    its own and its checks): ``description``, its help text (the study module's docstring);
    ``default_out``, the default folder, where one with a <part> is made from the other
    options (the study fills it in: --out's default is None)."""
    p = Parser(prog=f"jaxrkpm {command}", description=description, formatter_class=HelpFormatter,
               epilog="Exit codes: 0 goal reached; 1 goal missed (the last line says why); "
                      "2 bad command line; 3 output folder problem (jaxrkpm --help).")
    p.add_argument("--out", default=None if "<" in default_out else default_out, metavar="DIR", type=out_dir,
                   help=f"output folder (default {default_out})")
    p.add_argument("--overwrite", action="store_true",
                   help="replace what DIR holds (another run's results, other files); without it a "
                        "folder is only reused by a run with the same options")
    p.add_argument("--json", action="store_true", help="also print summary.json to stdout")
    return p


def memory_check(option: str, side, when=lambda args: True):
    """A parser check (:meth:`Parser.check`): the model that ``option`` sizes, ``side(value)
    -> particles``, fits the memory available (:func:`memory_error`); ``when(args)``: whether
    the option sizes a model in this run."""
    dest = option.lstrip("-").replace("-", "_")

    def rule(args, given):
        value = getattr(args, dest)
        if value is None or not when(args):
            return None
        return memory_error(option, value, side(value), side=side)
    return rule


def parse(command: str, argv=None) -> argparse.Namespace:
    """The options of ``command`` (argparse exits with code 2 on a bad one)."""
    from jaxrkpm.thesis.studies.command import command as declared
    return declared(command).parser().parse_args(argv)


def identity(command: str, args: argparse.Namespace, ignore=()) -> dict:
    """What makes a run the same run: the command and its options but the output ones (and
    ``ignore``)."""
    return {"command": command, "options": {k: v for k, v in sorted(vars(args).items())
                                            if k not in ("out", "json", "overwrite", *ignore)}}


# ------------------------------------------------------------------ output and progress
RUN_FILE = "run.json"


def _fail(out: Path, e: OSError):
    raise OutputError(f"cannot write to {out}/: {e.strerror or e}") from None


def output_folder(path) -> Path:
    """Create the folder ``path`` (and its parents) and check that a file can be written
    there, before any work; raises :class:`OutputError` naming the folder and the reason."""
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as e:
        _fail(out, e)
    return out


class Results:
    """A study's results folder, claimed before any work (:func:`results`) and written
    atomically: ``with results as tmp:`` gives a temporary folder beside it to write into;
    :meth:`finish` puts it in place (the earlier results of the same run go only then) and
    prints the one line. A run that raises leaves the folder as it was. ``staged=False``
    (``reproduce``, whose experiments are each written atomically by their own study) writes
    in place."""

    def __init__(self, out: Path, run: dict, staged: bool = True, replaces: bool = False):
        self.out, self.run, self.staged = out, run, staged
        self.replaces = replaces          # --overwrite over another run's results
        self.t0 = time.time()
        self.tmp = None

    def __enter__(self) -> Path:
        if not self.staged:           # claimed at once: an interrupted run is recognised as this run
            out = output_folder(self.out)
            if self.replaces or not (out / RUN_FILE).exists():
                (out / RUN_FILE).write_text(json.dumps({**self.run, "files": []}, indent=2, default=str))
            return out
        try:
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.", dir=self.out.parent))
        except OSError as e:
            _fail(self.out, e)
        return self.tmp

    def __exit__(self, *exc):
        if self.tmp is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
        return False

    def finish(self, summary: dict, reached: bool, words: str, as_json: bool = False) -> str:
        """Put the results in place, then print ``summary`` as JSON (``--json``) and the one
        line ``wrote DIR/: files; words`` (``[goal missed]`` at its end where the exit code
        is 1); return the line."""
        where = self.tmp if self.staged else self.out
        files = sorted(p.name + ("/" if p.is_dir() else "") for p in where.iterdir()) if self.staged \
            else written_since(self.out, self.t0)
        files = sorted(set(files) | {RUN_FILE})
        record = {**self.run, "files": files}
        (where / RUN_FILE).write_text(json.dumps(record, indent=2, default=str))
        if self.staged:
            self._swap()
        if as_json:
            print(json.dumps(summary, indent=2, default=str))
        line = f"wrote {self.out}/: {', '.join(files) or 'nothing'}" + (f"; {words}" if words else "")
        line = " ".join(line.split()) + ("" if reached else " [goal missed]")
        print(line, flush=True)
        return line

    def _swap(self):
        """The temporary folder in place of ``out``: the whole folder where it held only an
        earlier run's results (two renames), else (``--overwrite`` over other files) file by
        file, keeping the files this run did not write."""
        out, tmp = self.out.resolve(), self.tmp
        here = Path.cwd().resolve()
        try:
            if not out.exists():
                tmp.rename(out)
            elif out != here and out not in here.parents and \
                    set(os.listdir(out)) <= set(_earlier(out).get("files", [])):
                old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
                out.rename(old / "results")
                tmp.rename(out)
                shutil.rmtree(old, ignore_errors=True)
            else:
                for entry in tmp.iterdir():
                    target = out / entry.name
                    if target.is_dir() and not target.is_symlink():
                        shutil.rmtree(target)
                    os.replace(entry, target)
        except OSError as e:
            _fail(out, e)
        self.tmp = None if not tmp.exists() else tmp


def _earlier(out: Path) -> dict:
    try:
        record = json.loads((out / RUN_FILE).read_text())
        return record if isinstance(record, dict) else {}
    except (OSError, ValueError):
        return {}


def _earlier_run(out: Path, ignore) -> dict:
    """The record of the run whose results ``out`` holds ({} where none), without the options
    ``ignore`` names (a record of a version that kept them)."""
    earlier = _earlier(out) if out.is_dir() else {}
    if isinstance(earlier.get("options"), dict):
        earlier = {**earlier, "options": {k: v for k, v in earlier["options"].items() if k not in ignore}}
    return earlier


def _refuse_other_results(out: Path, run: dict, earlier: dict) -> None:
    """An OutputError where ``out`` holds files no jaxrkpm run wrote, or another run's results."""
    if not earlier:
        raise OutputError(f"{out}/ already holds files that no jaxrkpm run wrote: choose another --out, "
                          "or pass --overwrite to write over them")
    if {k: earlier.get(k) for k in ("command", "options")} != run:
        mine, theirs = _options_text(run), _options_text(earlier)
        raise OutputError(f"{out}/ holds the results of another run ({theirs}; this run: {mine}): "
                          "choose another --out, or pass --overwrite to replace them")


def _check_writable(out: Path) -> None:
    """An OutputError where no file can be written where ``out`` is (or will be) made."""
    parent = next((p for p in [out, *out.parents] if p.exists()), Path("."))
    if not parent.is_dir():
        raise OutputError(f"cannot write to {out}/: Not a directory")
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        _fail(out, e)


def results(command: str, args: argparse.Namespace, out=None, staged: bool = True, ignore=()) -> Results:
    """Claim the results folder ``out`` (default ``args.out``) for this run before any work:
    an :class:`OutputError` (exit 3) if it is a file, cannot be made, or holds another run's
    results or other files (unless ``args.overwrite``); it may hold this same run's earlier
    results, which the run replaces."""
    out = Path(args.out if out is None else out)
    run = identity(command, args, ignore)
    if out.exists() and not out.is_dir():
        raise OutputError(f"cannot write to {out}/: it is a file")
    earlier = _earlier_run(out, ignore)
    replaces = bool(earlier) and {k: earlier.get(k) for k in ("command", "options")} != run
    overwrite = bool(getattr(args, "overwrite", False))
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        _refuse_other_results(out, run, earlier)
    _check_writable(out)
    return Results(out, run, staged, replaces and overwrite)


def also_written(out: Path, name: str):
    """Add ``name`` to the files of the run recorded in ``out`` (a file written there after
    the run, e.g. reproduce's log of it), so the next run of it replaces the folder whole."""
    record = _earlier(Path(out))
    if record:
        record["files"] = sorted(set(record.get("files", [])) | {name})
        (Path(out) / RUN_FILE).write_text(json.dumps(record, indent=2, default=str))


def _options_text(run: dict) -> str:
    options = run.get("options") or {}
    return " ".join([str(run.get("command"))] + [f"--{k.replace('_', '-')} {v}" for k, v in options.items()
                                                 if v not in (None, False)])


def progress(iterable=None, *, total=None, desc: str, unit: str = "step", leave: bool = False):
    """A tqdm bar on stderr, shown only when stderr is a terminal (logs stay clean)."""
    return tqdm(iterable, total=total, desc=desc, unit=unit, file=sys.stderr, disable=None,
                leave=leave, dynamic_ncols=True)


def written_since(out: Path, t0: float) -> list[str]:
    """Names of the entries of ``out`` written since ``t0`` (time.time()), folders (with a
    trailing slash) where anything inside was: what this run wrote, whichever part of the
    study wrote it."""
    def newest(p: Path) -> float:
        return max([p.stat().st_mtime] + [q.stat().st_mtime for q in p.rglob("*")]) if p.is_dir() \
            else p.stat().st_mtime
    # file times come from a coarser clock than time.time(): allow it a few milliseconds
    return sorted(p.name + ("/" if p.is_dir() else "") for p in Path(out).iterdir() if newest(p) >= t0 - 0.05)
