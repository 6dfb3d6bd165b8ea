"""What the studies share on the command line, importable without JAX (``jaxrkpm --help``
and ``jaxrkpm COMMAND --help`` answer at once): each command's argument parser, number
checks that name the option and its valid range, the output folder check, the progress bar
and the one summary line a command ends with.

A study's ``main(argv)`` parses with :func:`parse`, checks its folder with
:func:`output_folder` before any work, runs (progress bars from :func:`progress`), writes
``summary.json`` and figures, and ends with :func:`finish`: one line ``wrote DIR/: files;
the result in words``. Its ``result(summary) -> (goal reached, words)`` gives those words
and the exit code (:data:`EXIT_CODES`).
"""
from __future__ import annotations

import argparse
import ast
import importlib.util
import json
import math
import sys
import tempfile
from pathlib import Path

from tqdm import tqdm

EXIT_OK, EXIT_GOAL, EXIT_USAGE, EXIT_OUTPUT = 0, 1, 2, 3
EXIT_CODES = {
    EXIT_OK: "the study ran and reached its goal",
    EXIT_GOAL: "the study ran but did not reach its goal (a solve failed, a path was not tracked, ...): "
               "the summary line says why",
    EXIT_USAGE: "bad command line: unknown command or option, or a number out of its range",
    EXIT_OUTPUT: "the output folder (--out) cannot be created or written",
}


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


# ------------------------------------------------------------------ parsers
def description(module: str) -> str:
    """A study module's docstring, read from its source without importing it (the study
    imports JAX; its help must not)."""
    spec = importlib.util.find_spec(module)
    return ast.get_docstring(ast.parse(Path(spec.origin).read_text()))


def _parser(command: str, module: str, default_out: str | None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"jaxrkpm {command}", description=description(module),
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="Exit codes: " + "; ".join(f"{c} {w.split(':')[0]}"
                                                                  for c, w in EXIT_CODES.items()) + ".")
    p.add_argument("--out", default=default_out, metavar="DIR",
                   help="output folder" + (f" (default {default_out})" if default_out else ""))
    p.add_argument("--json", action="store_true", help="also print summary.json to stdout")
    return p


def demo_parser():
    return _parser("demo", "jaxrkpm.thesis.studies.demo", "results/demo")


def track_parser():
    from jaxrkpm.thesis.data import CUBES, PATHS  # the thesis' data: NumPy only
    p = _parser("track", "jaxrkpm.thesis.studies.track", None)
    p.add_argument("--path", choices=[*PATHS, "table5.1"], default=None,
                   help="2D: " + "|".join(PATHS) + " (default box); 3D: table5.1 (default)")
    p.add_argument("--integration", choices=("gauss", "scni", "mscni"), default="gauss")
    p.add_argument("--dim", type=int, choices=(2, 3), default=2)
    p.add_argument("--model", choices=tuple(CUBES), default="reduced", help="3D cube discretisation")
    p.add_argument("--scheme", choices=("self", "reduced-to-refined"), default="self",
                   help="3D refined: Jacobian from the model itself or from the reduced model")
    p.add_argument("--n", type=number(int, 3), default=9, help="2D particles per side (9: the thesis)")
    p.add_argument("--alpha", type=POSITIVE, default=1.0, help="material alpha (Fung 2D, eq 5.1 in 3D)")
    p.add_argument("--beta", type=POSITIVE, default=1.0, help="Fung beta (2D)")
    p.add_argument("--gain", type=POSITIVE, default=0.05)
    p.add_argument("--clamp", type=POSITIVE, default=0.01, help="largest paddle increment per component")
    p.add_argument("--tol", type=POSITIVE, default=1e-4, help="control point tolerance per waypoint")
    p.add_argument("--max-iter", type=COUNT, default=2000, help="iterations per waypoint")
    p.add_argument("--max-steps", type=COUNT, default=20000, help="iterations in all")
    p.add_argument("--window", type=COUNT, default=300, help="iterations without progress before giving up")
    p.add_argument("--repeats", type=COUNT, default=1, help="timed warm runs (wall_s: their median)")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--no-mesh", action="store_true", help="skip final.vtu and series.pvd (ParaView)")
    p.epilog = "Default --out: results/track/<experiment>. " + p.epilog
    return p


def compress_parser():
    from jaxrkpm.thesis.data import PADDLE_HALF_WIDTH
    p = _parser("compress", "jaxrkpm.thesis.studies.compress", "results/compress")
    p.add_argument("--mode", choices=("straight", "shear"), default="straight")
    p.add_argument("--integration", choices=("gauss", "scni", "mscni"), default="gauss")
    p.add_argument("--n", type=number(int, 3), default=9, help="particles per side")
    p.add_argument("--max", type=number(float, 0, 1, low_open=True, high_open=True), default=0.9,
                   help="largest compression tried (fraction of the width)")
    p.add_argument("--step", type=number(float, 0, 0.5, low_open=True), default=0.01,
                   help="compression step (fraction of the width)")
    p.add_argument("--material", choices=("fung", "neohookean"), default="fung")
    p.add_argument("--paddle-half-width", type=number(float, 0, 0.5, low_open=True), default=PADDLE_HALF_WIDTH,
                   help="paddle = right-edge particles with |y - 0.5| <= this (0.5: the whole edge, "
                        "a homogeneous compression without punch corners)")
    p.add_argument("--through", action="store_true",
                   help="follow the primary branch past the loss of positive definiteness (stability "
                        "check off) until the solve fails, instead of the stable branch")
    return p


def _needle_options(command: str, inclusions) -> argparse.ArgumentParser:
    """The options the 2D and 3D needle studies share (their own ones are added after)."""
    p = _parser(command, f"jaxrkpm.thesis.studies.{command}", f"results/{command}")
    p.add_argument("--mode", choices=("static", "dynamic", "optimize"), default="static")
    p.add_argument("--inclusion", choices=tuple(inclusions), default="none")
    return p


def needle_parser():
    from jaxrkpm.thesis.data import INCLUSIONS, TABLE_6_2
    p = _needle_options("needle", INCLUSIONS)
    p.add_argument("--increments", type=COUNT, default=15, help="insertion increments up to 15%%")
    p.add_argument("--paddle", type=number(int, 1, len(TABLE_6_2)), default=None,
                   help="dynamic mode: paddle to move (default: the most controllable)")
    p.add_argument("--start", type=number(float, 1, len(TABLE_6_2)), default=None,
                   help="optimize mode: starting position q (default: the best discrete paddle)")
    p.add_argument("--iterations", type=COUNT, default=30, help="optimize mode: Adam iterations")
    p.add_argument("--devices", type=COUNT, default=None,
                   help="shard the sweep over this many devices (default: all visible)")
    return p


def needle3d_parser():
    from jaxrkpm.thesis.data import INCLUSIONS_3D
    p = _needle_options("needle3d", INCLUSIONS_3D)
    p.add_argument("--spacing", type=number(float, 0.05, 0.4), default=0.2,
                   help="mesh size of the phantom (0.3: 231 particles; 0.2: 390; 0.1: 1,332)")
    p.add_argument("--increments", type=COUNT, default=4, help="insertion increments")
    p.add_argument("--paddle", type=COUNT, default=None,
                   help="dynamic mode: patch to move (default: the most controllable)")
    p.add_argument("--tol", type=POSITIVE, default=1e-5, help="dynamic mode: |lateral deviation| to hold")
    p.add_argument("--iterations", type=COUNT, default=12, help="optimize mode: Adam iterations")
    p.add_argument("--devices", type=COUNT, default=None,
                   help="shard the sweep over this many devices (default: one)")
    return p


def rig_sim_parser():
    p = _parser("rig-sim", "jaxrkpm.thesis.studies.rig_sim", None)
    p.add_argument("--path", choices=("setpoint", "box"), default="box")
    p.add_argument("--calibrate", action="store_true", help="fit beta + a 3x3 stiffness map to a probe first")
    p.add_argument("--broyden", action="store_true", help="online Broyden Jacobian correction")
    p.add_argument("--physical-n", type=number(int, 5), default=17,
                   help="particles per side of the physical object")
    p.add_argument("--noise", type=number(float, 0), default=2.0, help="pixel noise std (grey levels)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--gain", type=POSITIVE, default=0.7)
    p.add_argument("--tol-mm", type=POSITIVE, default=0.3, help="camera tolerance per waypoint (mm)")
    p.add_argument("--max-iter", type=COUNT, default=30, help="iterations per waypoint (tracking)")
    p.add_argument("--budget", type=COUNT, default=1, help="iterations per waypoint (budget mode)")
    p.add_argument("--transport", choices=("tcp", "inprocess"), default="tcp")
    p.add_argument("--waypoints", type=COUNT, default=None, help="only the first N waypoints")
    p.add_argument("--no-figures", action="store_true")
    p.epilog = "Default --out: results/rig_sim/<path>. " + p.epilog
    return p


def reproduce_parser():
    from jaxrkpm.thesis.studies.experiments import ENTRIES  # the experiments: thesis data, no JAX
    p = _parser("reproduce", "jaxrkpm.thesis.studies.reproduce", "results/reproduce")
    p.add_argument("--quick", action="store_true", help="small subset at reduced sizes (smoke test)")
    p.add_argument("--only", nargs="+", default=None, metavar="ID",
                   help=f"run only these ({', '.join(e.id for e in ENTRIES)})")
    p.add_argument("--reuse", action="store_true",
                   help="read DIR/<id>/summary.json where it exists instead of re-running (resume / rebuild)")
    return p


def cantilever_parser():
    p = _parser("cantilever", "jaxrkpm.thesis.studies.cantilever", "results/cantilever")
    p.add_argument("--levels", type=number(int, 2), default=3, help="refinement levels (h = 1/4, 1/8, ...)")
    return p


PARSERS = {"demo": demo_parser, "track": track_parser, "compress": compress_parser,
           "needle": needle_parser, "needle3d": needle3d_parser, "rig-sim": rig_sim_parser, "reproduce": reproduce_parser,
           "cantilever": cantilever_parser}


def parse(command: str, argv=None) -> argparse.Namespace:
    """The options of ``command`` (argparse exits with code 2 on a bad one)."""
    return PARSERS[command]().parse_args(argv)


# ------------------------------------------------------------------ output and progress
def output_folder(path) -> Path:
    """Create the folder ``path`` (and its parents) and check that a file can be written
    there, before any work; raises :class:`OutputError` naming the folder and the reason."""
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as e:
        raise OutputError(f"cannot write to {out}/: {e.strerror or e}") from None
    return out


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


def finish(out: Path, t0: float, summary: dict, words: str, as_json: bool = False) -> str:
    """Print ``summary`` as JSON (``--json``), then the one summary line
    ``wrote DIR/: file, ...; words`` (files: what this run wrote since ``t0``); return it."""
    if as_json:
        print(json.dumps(summary, indent=2, default=str))
    files = written_since(out, t0)
    line = f"wrote {out}/: {', '.join(files) or 'nothing'}" + (f"; {words}" if words else "")
    print(line, flush=True)
    return line
