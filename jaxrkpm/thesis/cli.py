"""Command line: ``jaxrkpm COMMAND [options]``; each command is a study module of
:mod:`jaxrkpm.thesis.studies`, which declares it (``COMMAND``: its name, its parser, its run;
:mod:`jaxrkpm.thesis.studies.command`). Reading the declarations and parsing the options (and
answering ``--help``) imports no JAX; the study's work, and JAX with it, loads only once its
options are good."""
from __future__ import annotations

import difflib
import sys

from jaxrkpm import __version__
from jaxrkpm.base.cache import cache_dir, use_compilation_cache
from jaxrkpm.thesis.studies import interface
from jaxrkpm.thesis.studies.command import commands


def help_text(found: dict | None = None) -> str:
    found = commands() if found is None else found
    width = max(map(len, found))
    cmds = "\n".join(f"  {name:<{width}}  {c.summary}" for name, c in found.items())
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


def unknown(command: str, found: dict) -> str:
    near = difflib.get_close_matches(command, found, n=1)
    return (f"jaxrkpm: error: unknown command {command!r}"
            + (f" (did you mean {near[0]!r}?)" if near else "")
            + f"; commands: {', '.join(found)} (jaxrkpm --help)")


def run(declared, rest: list) -> int:
    """Run the command ``declared`` with its options ``rest``: its exit code."""
    args = None
    try:
        args = declared.parser().parse_args(rest)   # --help and bad options end here, before JAX loads
        use_compilation_cache()          # a second run loads its programs instead of compiling
        summary = declared.main(rest)
    except SystemExit as e:              # argparse: --help (0) or a bad option (2)
        return e.code if isinstance(e.code, int) else interface.EXIT_USAGE
    except interface.OutputError as e:
        print(f"jaxrkpm {declared.name}: error: {' '.join(str(e).split())}", file=sys.stderr)
        return interface.EXIT_OUTPUT
    except KeyboardInterrupt:            # Ctrl-C: one line on what was kept, not a traceback
        kept = declared.interrupted.replace("DIR", str(getattr(args, "out", None) or "DIR"))
        print(f"jaxrkpm {declared.name}: interrupted; {kept}", file=sys.stderr)
        return interface.EXIT_INTERRUPTED
    reached, _ = declared.result(summary)
    return interface.EXIT_OK if reached else interface.EXIT_GOAL


def main(argv=None) -> int:
    """Run ``jaxrkpm`` with ``argv``; returns the exit code (see ``jaxrkpm --help``)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "--version":
        print(f"jaxrkpm {__version__}")
        return interface.EXIT_OK
    found = commands()
    if not argv or argv[0] in ("-h", "--help"):
        print(help_text(found), end="", file=sys.stdout if argv else sys.stderr)
        return interface.EXIT_OK if argv else interface.EXIT_USAGE
    if argv[0] not in found:
        print(unknown(argv[0], found), file=sys.stderr)
        return interface.EXIT_USAGE
    return run(found[argv[0]], argv[1:])


if __name__ == "__main__":
    sys.exit(main())
