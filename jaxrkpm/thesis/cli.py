"""Command line: ``jaxrkpm COMMAND [options]``; each command runs a study of
:mod:`jaxrkpm.thesis.studies`. The options are parsed (and ``--help`` answered) by
:mod:`jaxrkpm.thesis.studies.interface`, which imports no JAX; the study itself, and JAX with it,
is imported only once its options are good."""
from __future__ import annotations

import difflib
import importlib
import sys

from jaxrkpm import __version__
from jaxrkpm.base.cache import cache_dir, use_compilation_cache
from jaxrkpm.thesis.studies import interface

# command -> (module with main(argv) and result(summary), what it does in a line)
COMMANDS = {
    "demo": ("jaxrkpm.thesis.studies.demo", "the thesis' box path tracked on the 9x9 Fung square (Table 5.3)"),
    "track": ("jaxrkpm.thesis.studies.track", "chapter-5 Jacobian path tracking: 2D paths, the 3D cube of Table 5.1"),
    "compress": ("jaxrkpm.thesis.studies.compress", "compression to failure, Gauss vs nodal integration (Figs 5.10-5.18)"),
    "needle": ("jaxrkpm.thesis.studies.needle", "chapter 6: needle insertion, static/dynamic/optimised paddle"),
    "needle3d": ("jaxrkpm.thesis.studies.needle3d", "chapter 6 lifted to 3D: a half-ellipsoid phantom from a mesh, "
                                            "paddle patches on its skin"),
    "rig-sim": ("jaxrkpm.thesis.studies.rig_sim", "the simulated rig of section 5.3.2: vision, robot link, "
                                           "an object the model does not know"),
    "cantilever": ("jaxrkpm.thesis.studies.cantilever", "Timoshenko cantilever: error and convergence rate (verification)"),
    "sweep": ("jaxrkpm.thesis.studies.sweep", "2D needle sweeps to disk: paddle x inclusion x stiffness, "
                                          "resumable Parquet, in process or on a Dask cluster"),
    "reproduce": ("jaxrkpm.thesis.studies.reproduce", "every experiment above; report.md with a verdict per row"),
}


def help_text() -> str:
    width = max(map(len, COMMANDS))
    cmds = "\n".join(f"  {name:<{width}}  {what}" for name, (_, what) in COMMANDS.items())
    codes = "\n".join(f"  {code}  {what}" for code, what in interface.EXIT_CODES.items())
    return (f"usage: jaxrkpm [-h] [--version] COMMAND [options]\n\n"
            f"jaxrkpm {__version__}: a differentiable meshfree (RKPM) solver in JAX and the thesis studies "
            f"built on it.\nEach command writes summary.json and figures to its --out folder and ends "
            f"with one line: wrote DIR/: files; the result (and [goal missed] where the exit code is 1).\n"
            f"A folder holding another run's results is not written over without --overwrite.\n\n"
            f"commands:\n{cmds}\n\n"
            f"jaxrkpm COMMAND --help lists a command's options.\n"
            f"Compiled programs are cached in {cache_dir()} (JAXRKPM_COMPILATION_CACHE=off: no cache).\n\n"
            f"exit codes:\n{codes}\n")


def unknown(command: str) -> str:
    near = difflib.get_close_matches(command, COMMANDS, n=1)
    return (f"jaxrkpm: error: unknown command {command!r}"
            + (f" (did you mean {near[0]!r}?)" if near else "")
            + f"; commands: {', '.join(COMMANDS)} (jaxrkpm --help)")


def main(argv=None) -> int:
    """Run ``jaxrkpm`` with ``argv``; returns the exit code (see ``jaxrkpm --help``)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(help_text(), end="", file=sys.stdout if argv else sys.stderr)
        return interface.EXIT_OK if argv else interface.EXIT_USAGE
    if argv[0] == "--version":
        print(f"jaxrkpm {__version__}")
        return interface.EXIT_OK
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        print(unknown(command), file=sys.stderr)
        return interface.EXIT_USAGE
    args = None
    try:
        args = interface.parse(command, rest)   # --help and bad options end here, before JAX loads
        use_compilation_cache()          # a second run loads its programs instead of compiling
        study = importlib.import_module(COMMANDS[command][0])
        summary = study.main(rest)
    except SystemExit as e:              # argparse: --help (0) or a bad option (2)
        return e.code if isinstance(e.code, int) else interface.EXIT_USAGE
    except interface.OutputError as e:
        print(f"jaxrkpm {command}: error: {' '.join(str(e).split())}", file=sys.stderr)
        return interface.EXIT_OUTPUT
    except KeyboardInterrupt:            # Ctrl-C: one line on what was kept, not a traceback
        module = sys.modules.get(COMMANDS[command][0])
        kept = getattr(module, "ON_INTERRUPT", "nothing was written (a run puts its folder in place when it ends)")
        kept = kept.replace("DIR", str(getattr(args, "out", None) or "DIR"))
        print(f"jaxrkpm {command}: interrupted; {kept}", file=sys.stderr)
        return interface.EXIT_INTERRUPTED
    reached, _ = study.result(summary)
    return interface.EXIT_OK if reached else interface.EXIT_GOAL


if __name__ == "__main__":
    sys.exit(main())
