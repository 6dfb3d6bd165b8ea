"""A griffe extension for the API reference: the package's docstrings are written in reST
habits (``literals``, :class:`X` roles, ``::`` before a literal block, aligned field
tables), and the reference renders them as Markdown. It rewrites each docstring before
mkdocstrings renders it; the source stays as it is.

- ``:class:`~pkg.Name``` (any role: class, func, meth, mod, data, attr, ...) becomes the
  code span ``Name`` (``~`` keeps the last part, as Sphinx does); double-backtick literals
  are Markdown code spans already.
- A paragraph ending in ``::`` ends in ``:`` (the indented block after it is a Markdown code
  block already).
- An aligned field table (two or more lines ``name   description``, as in ``Model`` and
  ``Body``) becomes a text block, so that its columns stay aligned.
"""
from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:py:)?[a-z]+:`(~?)([^`]+)`")
ROW = re.compile(r"^[A-Za-z_][\w.,()\[\]^' -]*?\S\s{2,}\S")


def _role(match: re.Match) -> str:
    tilde, target = match.groups()
    target = target.strip()
    if "<" in target and target.endswith(">"):   # :class:`text <target>`
        target = target[: target.index("<")].strip()
    if tilde:
        target = target.rsplit(".", 1)[-1]
    return f"`{target}`"


def _tables(text: str) -> str:
    """Aligned field tables (paragraphs with at least two ``name  text`` rows) as text blocks."""
    out = []
    for para in re.split(r"(\n\s*\n)", text):
        lines = para.split("\n")
        rows = sum(bool(ROW.match(line)) for line in lines)
        if rows >= 2 and ROW.match(lines[0]) and "```" not in para:
            para = "```text\n" + re.sub(r"``([^`]+)``", r"\1", para) + "\n```"
        out.append(para)
    return "".join(out)


def markdown(text: str) -> str:
    """The docstring ``text`` rewritten for Markdown (see the module docstring)."""
    text = ROLE.sub(_role, text)
    text = re.sub(r"(\S)::[ \t]*$", r"\1:", text, flags=re.M)
    text = re.sub(r"^::[ \t]*$", "", text, flags=re.M)
    return _tables(text)


class ReSTRoles(griffe.Extension):
    """Rewrites every docstring once the package is loaded (see the module docstring)."""

    def on_object(self, *, obj, loader, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = markdown(obj.docstring.value)
