"""What the studies share on the command line, importable without JAX (``jaxrkpm --help``
and ``jaxrkpm COMMAND --help`` answer at once): each command's argument parser, number
checks that name the option and its valid range, the output folder check, the progress bar
and the one summary line a command ends with.

A study's ``main(argv)`` parses with :func:`parse` (every number bounded where a size or
count is made from it; sizes checked against the memory available), claims its folder with
:func:`results` before any work, runs into a temporary folder beside it (progress bars from
:func:`progress`), writes ``summary.json`` and figures, and ends with :meth:`Results.finish`:
the temporary folder takes the place of the results folder (a run that fails leaves the
earlier results as they were) and one line is printed, ``wrote DIR/: files; the result in
words``, ending with ``[goal missed]`` where the exit code is 1. Its ``result(summary) ->
(goal reached, words)`` gives those words and the exit code (:data:`EXIT_CODES`).

A results folder is never written over by another run: it holds ``run.json`` (the command
and the options that made it), and a run with other options (``needle --mode static`` then
``--mode optimize`` into one ``--out``), or a folder holding other files, is refused (exit 3)
unless ``--overwrite`` is given. A run with the same options replaces its own results.
"""
from __future__ import annotations

import argparse
import ast
import importlib.util
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

# bounds of the counts the options make (each option's help shows its range):
ITERATIONS_MAX = 1_000_000      # control / Newton iterations: each one is a solve (hours at 1e6)
INCREMENTS_MAX = 1_000          # needle increments: each is a solve of every paddle (thesis: 15)
INCREMENTS_3D_MAX = 100         # 3D needle increments (each a 3D solve of every patch)
ADAM_MAX = 10_000               # Adam iterations of the paddle optimisers
REPEATS_MAX = 100               # timed warm runs
LEVELS_MAX = 6                  # cantilever refinements: h = 1/4 .. 1/128 (257 x 129 particles)
COMPRESSION_STEPS_MAX = 1_000   # compression steps (--max / --step), a solve each
DEVICES_MAX = 4096
SWEEP_CHUNK_MAX = sweep_limits.MAX_CHUNK          # configurations per chunk of a sweep
SWEEP_MAX = sweep_limits.MAX_CONFIGURATIONS      # configurations of a sweep
SEED_MAX = 2 ** 32 - 1          # NumPy's seeds are unsigned 32-bit words
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
def description(module: str) -> str:
    """A study module's docstring, read from its source without importing it (the study
    imports JAX; its help must not)."""
    spec = importlib.util.find_spec(module)
    return ast.get_docstring(ast.parse(Path(spec.origin).read_text()))


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
    """An argument parser whose errors are one line: ``jaxrkpm CMD: error: what (jaxrkpm CMD
    --help)``, exit code 2 (argparse's own prints its usage block first)."""

    def add_argument(self, *args, **kwargs):
        if "help" not in kwargs and kwargs.get("action") not in ("store_true", "store_false"):
            kwargs["help"] = "(default %(default)s)"     # every option shows its default
        return super().add_argument(*args, **kwargs)

    def error(self, message):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {' '.join(str(message).split())} ({self.prog} --help)\n")


def _parser(command: str, module: str, default_out: str) -> argparse.ArgumentParser:
    """The options every command has. ``default_out``: the default folder; one with a <part>
    is made from the other options (the study fills it in: --out's default is None)."""
    p = Parser(prog=f"jaxrkpm {command}", description=description(module),
                                formatter_class=HelpFormatter,
                                epilog="Exit codes: 0 goal reached; 1 goal missed (the last line says why); "
                                       "2 bad command line; 3 output folder problem (jaxrkpm --help).")
    p.add_argument("--out", default=None if "<" in default_out else default_out, metavar="DIR", type=out_dir,
                   help=f"output folder (default {default_out})")
    p.add_argument("--overwrite", action="store_true",
                   help="replace what DIR holds (another run's results, other files); without it a "
                        "folder is only reused by a run with the same options")
    p.add_argument("--json", action="store_true", help="also print summary.json to stdout")
    return p


def demo_parser():
    return _parser("demo", "jaxrkpm.thesis.studies.demo", "results/demo")


def track_parser():
    from jaxrkpm.thesis.data import CUBES, PATHS  # the thesis' data: NumPy only
    p = _parser("track", "jaxrkpm.thesis.studies.track", "results/track/<experiment>")
    p.add_argument("--path", choices=[*PATHS, "table5.1"], default=None,
                   help="2D: " + "|".join(PATHS) + " (default box); 3D: table5.1 (default)")
    p.add_argument("--integration", choices=("gauss", "scni", "mscni"), default="gauss")
    p.add_argument("--dim", type=int, choices=(2, 3), default=2)
    p.add_argument("--model", choices=tuple(CUBES), default=None,
                   help="3D only: the cube's discretisation (default reduced)")
    p.add_argument("--scheme", choices=("self", "reduced-to-refined"), default=None,
                   help="3D refined only: Jacobian from the model itself or from the reduced model (default self)")
    p.add_argument("--n", type=number(int, 3), default=None,
                   help="2D only: particles per side (default 9, the thesis'; bounded by the memory available)")
    p.add_argument("--alpha", type=POSITIVE, default=1.0, help="material alpha (Fung 2D, eq 5.1 in 3D)")
    p.add_argument("--beta", type=POSITIVE, default=None, help="2D only: Fung beta (default 1)")
    p.add_argument("--gain", type=POSITIVE, default=0.05)
    p.add_argument("--clamp", type=POSITIVE, default=0.01, help="largest paddle increment per component")
    p.add_argument("--tol", type=POSITIVE, default=1e-4, help="control point tolerance per waypoint")
    p.add_argument("--max-iter", type=iterations(), default=2000, help="iterations per waypoint, 1..1e6")
    p.add_argument("--max-steps", type=iterations(), default=20000, help="iterations in all, 1..1e6")
    p.add_argument("--window", type=iterations(), default=300,
                   help="iterations without progress before giving up, 1..1e6")
    p.add_argument("--repeats", type=number(int, 1, REPEATS_MAX), default=1,
                   help="timed warm runs (wall_s: their median), 1..100")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--no-mesh", action="store_true", help="skip final.vtu and series.pvd (ParaView)")
    return p


# the compression study's materials (jaxrkpm.thesis.studies.compress.MATERIALS)
COMPRESS_MATERIALS = ("fung", "fung-barrier", "neo-hookean", "neohookean")


def compress_parser():
    from jaxrkpm.thesis.data import PADDLE_HALF_WIDTH
    p = _parser("compress", "jaxrkpm.thesis.studies.compress", "results/compress/<mode>_<integration>_<n>[...]")
    p.add_argument("--mode", choices=("straight", "shear"), default="straight")
    p.add_argument("--integration", choices=("gauss", "scni", "mscni"), default="gauss")
    p.add_argument("--n", type=number(int, 3), default=9,
                   help="particles per side (bounded by the memory available)")
    p.add_argument("--max", type=number(float, 0, 1, low_open=True, high_open=True), default=0.9,
                   help="largest compression tried (fraction of the width)")
    p.add_argument("--step", type=number(float, 0, 0.5, low_open=True), default=0.01,
                   help=f"compression step (fraction of the width; at most {COMPRESSION_STEPS_MAX} steps to --max)")
    p.add_argument("--material", choices=COMPRESS_MATERIALS, default="fung",
                   help="fung: the thesis' Fung (eq 5.2, Table 5.2); fung-barrier: the same plus the volumetric "
                        "barrier kappa/2 (ln J)^2, kappa = Fung's shear modulus 509 (compressed points cannot "
                        "fold flat); neo-hookean: nearly incompressible neo-Hookean tissue, nu = 0.45, mu = 509; "
                        "neohookean: the compressible control (lam = 766, mu = 508)")
    p.add_argument("--paddle-half-width", type=number(float, 0, 0.5, low_open=True), default=PADDLE_HALF_WIDTH,
                   help="paddle = right-edge particles with |y - 0.5| <= this (0.5: the whole edge, "
                        "a homogeneous compression without punch corners)")
    p.add_argument("--through", action="store_true",
                   help="follow the primary branch past the loss of positive definiteness (stability "
                        "check off) until the solve fails, instead of the stable branch")
    return p


def _needle_options(command: str, inclusions, modes=("static", "dynamic", "optimize")) -> argparse.ArgumentParser:
    """The options the 2D and 3D needle studies share (their own ones are added after)."""
    p = _parser(command, f"jaxrkpm.thesis.studies.{command}", f"results/{command}/<mode>_<inclusion>")
    p.add_argument("--mode", choices=modes, default="static")
    p.add_argument("--inclusion", choices=tuple(inclusions), default="none")
    return p


def needle_parser():
    from jaxrkpm.thesis.data import INCLUSIONS, TABLE_6_2
    p = _needle_options("needle", INCLUSIONS, ("static", "dynamic", "optimize", "preload"))
    p.add_argument("--material", choices=("fung", "fung-barrier", "neo-hookean"), default="fung",
                   help="fung: the thesis' Fung (eq 6.1); fung-barrier: the same plus the volumetric barrier "
                        "kappa/2 (ln J)^2, kappa = Fung's shear modulus; neo-hookean: nearly incompressible "
                        "neo-Hookean tissue, nu = 0.45, with Fung's small-strain shear modulus")
    p.add_argument("--increments", type=number(int, 1, INCREMENTS_MAX), default=15,
                   help=f"insertion increments up to 15%%, 1..{INCREMENTS_MAX}")
    p.add_argument("--paddle", type=number(int, 1, len(TABLE_6_2)), default=None,
                   help="dynamic mode: paddle to move (default: the most controllable)")
    p.add_argument("--start", type=number(float, 1, len(TABLE_6_2)), default=None,
                   help="optimize mode: starting position q (default: the best discrete paddle)")
    p.add_argument("--iterations", type=number(int, 1, ADAM_MAX), default=30,
                   help=f"optimize mode: Adam iterations, 1..{ADAM_MAX}")
    p.add_argument("--devices", type=number(int, 1, DEVICES_MAX), default=None,
                   help="shard the sweep over this many devices (default: all visible)")
    contact_options(p, "the position, default 3", "static: one particle spacing; dynamic: half a spacing; "
                                                  "optimize: 1.5 spacings")
    p.add_argument("--tools", type=int, choices=(1, 2, 3), default=None,
                   help="contact paddle model: this many push-only tools on the free skin "
                        "(jaxrkpm.thesis.tools.DEFAULT_TOOLS) instead of one paddle at a Table 6.2 position; "
                        "static: pressed half a spacing in (or --indentation) at the target's height; "
                        "preload: their depths optimised; optimize: positions and depths optimised; dynamic: "
                        "moved during insertion by a QP per correction (default: none, one paddle)")
    return p


def tools_error(args: argparse.Namespace) -> str | None:
    """A usage message where --tools or --mode preload is given without what they need."""
    if args.tools is not None and args.paddle_model != "contact":
        return "--tools applies to the contact paddle model only: add --paddle-model contact"
    if args.mode == "preload" and args.tools is None:
        return "--mode preload applies to several tools only: add --paddle-model contact --tools N"
    return None


def contact_options(p, paddle: str, indentation: str):
    """The contact paddle's options of the needle studies (``paddle``, ``indentation``: what
    --paddle picks and the default indentation of each mode, in words)."""
    p.add_argument("--paddle-model", choices=("glued", "contact"), default="glued",
                   help="glued: the paddle holds its particles (pulls and pushes; the thesis' results); "
                        "contact: a rigid box pressed against the boundary that only pushes, and drags by "
                        "friction (static: pressed --indentation in; dynamic and optimize: its pose is the "
                        f"control, from --indentation; --paddle picks {paddle})")
    p.add_argument("--friction", type=number(float, 0), default=CONTACT_FRICTION,
                   help=f"contact paddle: Coulomb friction coefficient mu (>= 0; default {CONTACT_FRICTION:g})")
    p.add_argument("--indentation", type=number(float, 0), default=None,
                   help="contact paddle: how far it is pressed in, at most two particle spacings (static: "
                        f"its pose; dynamic and optimize: the start; default {indentation})")


CONTACT_FRICTION = 0.3
CONTACT_ONLY = ("friction", "indentation")   # options that only the contact paddle reads


def contact_error(command: str, args: argparse.Namespace, argv, spacing: float, deepest: float) -> str | None:
    """A usage message when a contact paddle option is given with the glued paddle (which has
    neither friction nor an indentation), or the indentation passes ``deepest``
    (``jaxrkpm.thesis.contact_paddle.max_indentation`` of the phantom, whose particle spacing
    is ``spacing``); None when they are fine."""
    if args.paddle_model == "glued":
        wrong = [o for o in CONTACT_ONLY if o in given(command, argv)]
        if wrong:
            return (f"{', '.join('--' + o for o in wrong)} {'applies' if len(wrong) == 1 else 'apply'} to the "
                    "contact paddle only: add --paddle-model contact, or leave "
                    f"{'it' if len(wrong) == 1 else 'them'} out (the glued paddle holds its particles)")
    if args.indentation is not None and args.indentation > deepest:
        return (f"argument --indentation: must be a number in [0, {deepest:g}] (two particle spacings at "
                f"spacing {spacing:g}: the contact paddle's travel), got {args.indentation:g}")
    return None


def needle3d_parser():
    from jaxrkpm.thesis.data import INCLUSIONS_3D
    p = _needle_options("needle3d", INCLUSIONS_3D)
    p.add_argument("--material", choices=("neo-hookean", "neohookean", "fung", "fung-barrier"),
                   default="neo-hookean",
                   help="neo-hookean (default): nearly incompressible neo-Hookean tissue, mu = 1, nu = 0.45; "
                        "neohookean: compressible neo-Hookean, lam = 4, mu = 1 (nu = 0.4, the default before); "
                        "fung: chapter 6's Fung with the 3D Table 5.2 pattern; fung-barrier: the same plus the "
                        "volumetric barrier kappa/2 (ln J)^2")
    p.add_argument("--spacing", type=number(float, 0.05, 0.4), default=0.2,
                   help="mesh size of the phantom (0.3: 231 particles; 0.2: 390; 0.1: 1,332)")
    p.add_argument("--increments", type=number(int, 1, INCREMENTS_3D_MAX), default=4,
                   help=f"insertion increments, 1..{INCREMENTS_3D_MAX}")
    p.add_argument("--paddle", type=COUNT, default=None,
                   help="dynamic mode: patch to move, 1..the number of patches (default: the most controllable); "
                        "contact paddle: its patch in every mode (default: the best glued patch)")
    p.add_argument("--tol", type=POSITIVE, default=1e-5, help="dynamic mode: |lateral deviation| to hold")
    p.add_argument("--iterations", type=number(int, 1, ADAM_MAX), default=12,
                   help=f"optimize mode: Adam iterations, 1..{ADAM_MAX}")
    p.add_argument("--devices", type=number(int, 1, DEVICES_MAX), default=None,
                   help="shard the sweep over this many devices (default: one)")
    contact_options(p, "the patch, default the best glued one", "a tenth of a particle spacing")
    return p


def rig_sim_parser():
    p = _parser("rig-sim", "jaxrkpm.thesis.studies.rig_sim", "results/rig_sim/<path>")
    p.add_argument("--path", choices=("setpoint", "box"), default="box")
    p.add_argument("--calibrate", action="store_true", help="fit beta + a 3x3 stiffness map to a probe first")
    p.add_argument("--broyden", action="store_true", help="online Broyden Jacobian correction")
    p.add_argument("--physical-n", type=number(int, 5), default=17,
                   help="particles per side of the physical object (bounded by the memory available)")
    p.add_argument("--noise", type=number(float, 0, 255), default=2.0, help="pixel noise std (grey levels, 0..255)")
    p.add_argument("--seed", type=number(int, 0, SEED_MAX), default=0, help="noise seed, 0..2^32-1")
    p.add_argument("--gain", type=number(float, 0, 1, low_open=True), default=0.7,
                   help="the fraction of the camera error each iteration corrects, in (0, 1] (above 1 every "
                        "step overshoots its waypoint and the loop oscillates)")
    p.add_argument("--tol-mm", type=POSITIVE, default=0.3, help="camera tolerance per waypoint (mm)")
    p.add_argument("--max-iter", type=number(int, 1, 10_000), default=30,
                   help="iterations per waypoint (tracking), 1..10000")
    p.add_argument("--budget", type=number(int, 1, 10_000), default=1,
                   help="iterations per waypoint (budget mode), 1..10000")
    p.add_argument("--transport", choices=("tcp", "inprocess"), default="tcp")
    p.add_argument("--waypoints", type=COUNT, default=None,
                   help="only the first N waypoints (default: all; at most the path's)")
    p.add_argument("--no-figures", action="store_true")
    return p


def reproduce_parser():
    from jaxrkpm.thesis.studies.experiments import ENTRIES  # the experiments: thesis data, no JAX
    p = _parser("reproduce", "jaxrkpm.thesis.studies.reproduce", "results/reproduce")
    p.add_argument("--quick", action="store_true", help="small subset at reduced sizes (smoke test)")
    p.add_argument("--only", nargs="+", default=None, metavar="ID",
                   help=f"run only these (default: all): {', '.join(e.id for e in ENTRIES)}")
    p.add_argument("--reuse", action="store_true",
                   help="read DIR/<id>/summary.json where it exists instead of re-running (resume / rebuild)")
    return p


def cantilever_parser():
    p = _parser("cantilever", "jaxrkpm.thesis.studies.cantilever", "results/cantilever")
    p.add_argument("--levels", type=number(int, 2, LEVELS_MAX), default=3,
                   help=f"refinement levels, h = 1/4, 1/8, ...; 2..{LEVELS_MAX} (1/128: 257 x 129 particles)")
    return p


def sweep_parser():
    from jaxrkpm.thesis.data import INCLUSIONS, TABLE_6_2
    p = _parser("sweep", "jaxrkpm.thesis.studies.sweep", "results/sweep")
    p.add_argument("--paddles", type=number(int, 1, len(TABLE_6_2)), nargs="+", default=None,
                   help=f"paddle positions of Table 6.2, 1..{len(TABLE_6_2)} (default: all)")
    p.add_argument("--ratios", type=POSITIVE, nargs="+", default=[100.0], help="inclusion stiffness ratios")
    p.add_argument("--inclusions", choices=tuple(INCLUSIONS), nargs="+", default=["right"])
    p.add_argument("--alphas", type=POSITIVE, nargs="+", default=[1.0], help="Fung alpha values")
    p.add_argument("--betas", type=POSITIVE, nargs="+", default=[1.0], help="Fung beta values")
    p.add_argument("--increments", type=number(int, 1, INCREMENTS_MAX), default=15,
                   help=f"insertion increments, 1..{INCREMENTS_MAX}")
    p.add_argument("--insertion", type=number(float, 0, 0.5, low_open=True), default=0.15,
                   help="needle depth at full insertion (fraction of the phantom's height)")
    count = number(int, 1, SWEEP_CHUNK_MAX)

    def chunk_size(text: str):
        if text == "auto":
            return text
        try:
            return count(text)
        except argparse.ArgumentTypeError as e:
            raise argparse.ArgumentTypeError(str(e).replace(", got", " or auto, got")) from None
    p.add_argument("--chunk-size", type=chunk_size, default=20,
                   help=f"configurations per batched call (one file each), 1..{SWEEP_CHUNK_MAX}, or auto: "
                        "measured on the first configurations (throughput per chunk size; a rerun keeps the "
                        "size the sweep started with)")
    p.add_argument("--jacobians", action="store_true", help="keep every increment's paddle Jacobian")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--executor", type=scheduler_address, default=None, metavar="ADDRESS",
                       help="a Dask scheduler's address (tcp://host:8786): run the chunks on that cluster "
                            "(default: in this process)")
    where.add_argument("--workers", type=number(int, 1, 256), default=None,
                       help="run the chunks on a local Dask cluster of this many worker processes, 1..256 "
                            "(default: in this process)")
    return p


SCHEDULER_SCHEMES = ("tcp", "tls", "ucx", "ws", "wss")     # Dask's network protocols with a host and port


def scheduler_address(text: str) -> str:
    """A Dask scheduler's address, checked for its form (``tcp://host:8786``); whether one
    answers there is checked before any work (:func:`unreachable`)."""
    from urllib.parse import urlsplit
    try:
        parts = urlsplit(text)
        port = parts.port
    except ValueError:
        port, parts = None, None
    if parts is None or parts.scheme not in SCHEDULER_SCHEMES or not parts.hostname or port is None:
        raise argparse.ArgumentTypeError(f"a Dask scheduler's address is SCHEME://HOST:PORT with SCHEME one of "
                                         f"{', '.join(SCHEDULER_SCHEMES)} (e.g. tcp://localhost:8786), got {text!r}")
    return text


def unreachable(address: str, timeout: float = 5.0) -> str | None:
    """Why nothing answers at the scheduler ``address`` (None where something does): checked
    before a sweep claims its folder, so that a wrong address ends at once, having written
    nothing."""
    import socket
    from urllib.parse import urlsplit
    parts = urlsplit(address)
    try:
        with socket.create_connection((parts.hostname, parts.port), timeout=timeout):
            return None
    except OSError as e:
        return f"no Dask scheduler answers at {address} ({e.strerror or e}): start one (dask scheduler) or fix the address"


PARSERS = {"sweep": sweep_parser, "demo": demo_parser, "track": track_parser, "compress": compress_parser,
           "needle": needle_parser, "needle3d": needle3d_parser, "rig-sim": rig_sim_parser, "reproduce": reproduce_parser,
           "cantilever": cantilever_parser}


def parse(command: str, argv=None) -> argparse.Namespace:
    """The options of ``command`` (argparse exits with code 2 on a bad one)."""
    return PARSERS[command]().parse_args(argv)


def given(command: str, argv) -> set:
    """The options given on the command line (dest names; abbreviations resolved)."""
    p = PARSERS[command]()
    for action in p._actions:
        action.default = argparse.SUPPRESS
    return set(vars(p.parse_args(argv)))


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


def results(command: str, args: argparse.Namespace, out=None, staged: bool = True, ignore=()) -> Results:
    """Claim the results folder ``out`` (default ``args.out``) for this run before any work:
    an :class:`OutputError` (exit 3) if it is a file, cannot be made, or holds another run's
    results or other files (unless ``args.overwrite``); it may hold this same run's earlier
    results, which the run replaces."""
    out = Path(args.out if out is None else out)
    run = identity(command, args, ignore)
    if out.exists() and not out.is_dir():
        raise OutputError(f"cannot write to {out}/: it is a file")
    earlier = _earlier(out) if out.is_dir() else {}
    if isinstance(earlier.get("options"), dict):   # a record of a version that kept the ignored options
        earlier = {**earlier, "options": {k: v for k, v in earlier["options"].items() if k not in ignore}}
    replaces = bool(earlier) and {k: earlier.get(k) for k in ("command", "options")} != run
    if out.is_dir() and any(out.iterdir()) and not getattr(args, "overwrite", False):
        if not earlier:
            raise OutputError(f"{out}/ already holds files that no jaxrkpm run wrote: choose another --out, "
                              "or pass --overwrite to write over them")
        if {k: earlier.get(k) for k in ("command", "options")} != run:
            mine, theirs = _options_text(run), _options_text(earlier)
            raise OutputError(f"{out}/ holds the results of another run ({theirs}; this run: {mine}): "
                              "choose another --out, or pass --overwrite to replace them")
    parent = next((p for p in [out, *out.parents] if p.exists()), Path("."))
    if not parent.is_dir():
        raise OutputError(f"cannot write to {out}/: Not a directory")
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        _fail(out, e)
    return Results(out, run, staged, replaces and bool(getattr(args, "overwrite", False)))


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
