"""Progress bars of the long Python-API calls (sweeps, phantom studies, contact sweeps,
optimisers): tqdm on stderr with the rate and an estimate of the time left, drawn only where
stderr is a terminal (a log file or a pipe gets nothing) and only while ``progress`` is on
(every such call takes ``progress=False`` to silence it)."""
from __future__ import annotations

import sys


def progress_bar(total=None, *, desc: str, unit: str = "step", progress: bool = True, leave: bool = False,
                 **options):
    """A tqdm bar of ``total`` steps on stderr: disabled where ``progress`` is False or stderr
    is not a terminal (tqdm's ``disable=None``), so it is written once, in place, or not at
    all. ``options``: more of tqdm's (``initial``, ...)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, disable=None if progress else True,
                leave=leave, dynamic_ncols=True, **options)
