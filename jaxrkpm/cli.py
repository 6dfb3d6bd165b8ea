"""Command line: ``jaxrkpm <command> [options]``; each command runs a study of
:mod:`jaxrkpm.studies` (imported only when its command is given, so ``--help`` stays cheap)."""
from __future__ import annotations

import importlib
import sys

# command -> module with a main(argv) in jaxrkpm/studies/
COMMANDS = {
    "demo": "jaxrkpm.studies.demo",
    "track": "jaxrkpm.studies.track",
    "compress": "jaxrkpm.studies.compress",
    "needle": "jaxrkpm.studies.needle",
    "needle3d": "jaxrkpm.studies.needle3d",
    "rig-sim": "jaxrkpm.studies.rig_sim",
    "reproduce": "jaxrkpm.studies.reproduce",
}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        names = ", ".join(COMMANDS)
        print(f"usage: jaxrkpm {{{names}}} [options]   (jaxrkpm COMMAND --help for options)")
        return 0 if (not argv or argv[0] in ("-h", "--help")) else 2
    importlib.import_module(COMMANDS[argv[0]]).main(argv[1:])
    return 0


if __name__ == "__main__":
    sys.exit(main())
