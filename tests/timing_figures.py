"""The rule that keeps measurements out of the prose: timing figures belong on the performance
page (``docs/performance.md``, rendered from the benches' records), not in comments,
docstrings or the README, where they go stale with every change.

A *timing figure* is a measured cost written as a number:

- **duration**: a number with a unit of time (``0.8 s``, ``13 us``, ``7 min``, ``2 hours``);
- **memory size**: a number with a unit of bytes (``4.2 GB``, ``150 MB``, ``2 KiB``);
- **speed ratio**: a number directly followed by ``x`` or ``×`` (``1.30x``, ``2×``), or
  ``N times``, in a sentence about cost (it says faster, slower, quicker, cheaper,
  speed-up, time, cost, flops, beat, win or lose); a percentage directly followed by
  faster, slower, longer, shorter, less time or more time (``70% longer``);
- **history**: ``a -> b`` or ``a → b`` between numbers (``2.70 -> 1.22 ms``,
  ``412 -> 213 CG iterations``) in a sentence about cost, iterations or factorisations.

Not timing figures: grid and shape sizes (``9x9``, ``3 x 3``, ``(n, d) -> (n,)``), products
in formulas (``2 x max_iter``), physical quantities (mm, N, Pa, a spacing), tolerances
(``1e-10``), ratios of anything but cost (``the deviation cut 20.8x``), and the thesis'
reference values: a duration within 40 characters after the word *thesis* in the same
sentence (``thesis: 625 min``, ``the thesis' times: 625 / 412 min``).

In Python sources only the prose is read: comments (consecutive comment lines as one text)
and docstrings (module, class and function docstrings, and the bare strings that document
attributes), found with ``tokenize`` and ``ast``; code, including f-strings that print
measured values, is not prose.
"""
from __future__ import annotations

import ast
import io
import re
import tokenize

DIGITS = r"\d[\d,]*(?:\.\d+)?"
NUMBER = r"(?<![\w.^])" + DIGITS
TIME_UNIT = r"(?:ms|us|µs|μs|ns|s|secs?|seconds?|mins?|minutes?|hours?|hrs?)"
MEMORY_UNIT = r"(?:[KMGT]i?B|kB)"
COST = re.compile(r"fast|slow|quick|cheap|speed|\btimes?\b|\btimed?\b|\bcosts?\b|flops|\bbeats?\b|"
                  r"\bwins?\b|\blos[et]s?\b", re.I)
WORK = re.compile(r"iteration|factorisation|factorization", re.I)

DURATION = re.compile(NUMBER + r"(?:\s*[-–]\s*" + DIGITS + r")?\s*" + TIME_UNIT + r"(?![\w²³^])")
MEMORY = re.compile(NUMBER + r"\s*" + MEMORY_UNIT + r"\b")
RATIO = re.compile(NUMBER + r"[x×](?![\w\d²³])|" + NUMBER + r"\s+times\b")
PERCENT = re.compile(NUMBER + r"\s*%\s+(?:faster|slower|longer|shorter|less time|more time)\b")
HISTORY = re.compile(NUMBER + r"\s*" + TIME_UNIT + r"?\s*(?:->|→)\s*" + NUMBER)
THESIS = re.compile(r"thesis", re.I)
SENTENCE_END = re.compile(r"(?<=[.;!?])\s+(?=[A-Z(`*])|\n\s*\n")


def sentences(text: str):
    """(start offset, sentence) of each sentence of ``text`` (split at a full stop, semicolon,
    question or exclamation mark before a capital, and at blank lines)."""
    start = 0
    for m in SENTENCE_END.finditer(text):
        yield start, text[start:m.start()]
        start = m.end()
    yield start, text[start:]


def _thesis_value(sentence: str, at: int) -> bool:
    """A duration at ``at`` that the thesis reports: the word 'thesis' stands at most 40
    characters before it in the same sentence."""
    return any(0 <= at - m.end() <= 40 for m in THESIS.finditer(sentence[:at]))


def timing_figures(text: str) -> list[tuple[int, str, str]]:
    """(offset in ``text``, kind, figure) of every timing figure in ``text`` (see the module
    docstring for the rule)."""
    found = []
    for start, s in sentences(text):
        for m in DURATION.finditer(s):
            if not _thesis_value(s, m.start()):
                found.append((start + m.start(), "duration", m.group()))
        found += [(start + m.start(), "memory", m.group()) for m in MEMORY.finditer(s)]
        if COST.search(s):
            found += [(start + m.start(), "ratio", m.group()) for m in RATIO.finditer(s)]
        found += [(start + m.start(), "ratio", m.group()) for m in PERCENT.finditer(s)]
        if COST.search(s) or WORK.search(s):
            found += [(start + m.start(), "history", m.group()) for m in HISTORY.finditer(s)]
    return sorted(found)


def python_prose(source: str) -> list[tuple[int, str]]:
    """(first line, text) of each comment block and docstring of a Python source."""
    blocks, run, last = [], [], None
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type != tokenize.COMMENT:
            continue
        line, whole = tok.start[0], tok.line.lstrip().startswith("#")
        if run and not (whole and line == last + 1):
            blocks.append(run)
            run = []
        run.append((line, tok.string.lstrip("#").strip()))
        last = line if whole else -2   # an inline comment stands alone
    if run:
        blocks.append(run)
    # a comment block is one text: a figure may be split over two comment lines
    prose = [(block[0][0], "\n".join(text for _, text in block)) for block in blocks]
    for node in ast.walk(ast.parse(source)):
        body = getattr(node, "body", None)
        for stmt in body if isinstance(body, list) else []:
            if (isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant)
                    and isinstance(stmt.value.value, str)):
                prose.append((stmt.lineno, stmt.value.value))
    return sorted(prose)


def figures_in_python(source: str) -> list[tuple[int, str, str]]:
    """(line, kind, figure) of the timing figures in a Python source's comments and docstrings."""
    out = []
    for line, text in python_prose(source):
        for offset, kind, figure in timing_figures(text):
            out.append((line + text.count("\n", 0, offset), kind, figure))
    return out


def figures_in_text(text: str) -> list[tuple[int, str, str]]:
    """(line, kind, figure) of the timing figures in a text file (Markdown)."""
    return [(1 + text.count("\n", 0, offset), kind, figure) for offset, kind, figure in timing_figures(text)]
