"""The bounds and defaults of a sweep, in a module that imports nothing, so that the command
line's parsers state the same ranges without importing NumPy or pyarrow."""

MAX_CONFIGURATIONS = 10_000_000     # bounds the table checked before anything is allocated
MAX_CHUNK = 65_536                  # configurations in one chunk (one evaluate call)
DEFAULT_CHUNK = 64                  # where neither the call, the evaluator nor the folder says
AUTO = "auto"                       # chunk_size: measured (``chunk_size.choose_chunk_size``)
