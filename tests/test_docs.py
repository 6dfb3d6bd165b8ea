"""The documentation: the README (short, its example runs, its commands are the ones that
exist), no timing figures in the prose (``tests/timing_figures.py`` states the rule), the
README, docs and notebooks use only public names, and the docs build with ``mkdocs build
--strict`` with every public name in the API reference."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.timing_figures import figures_in_python, figures_in_text, python_prose, timing_figures

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
PERFORMANCE = DOCS / "performance.md"   # the one place for timing figures
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
MAX_README_LINES = 150


# ------------------------------------------------------------------ the timing-figure rule
FIGURES = [
    ("0.8 s warm + 8.1 s compile", ["0.8 s", "8.1 s"]),
    ("one step took 13.2 us against 1.0 us", ["13.2 us", "1.0 us"]),
    ("the static run takes 7 min on a quiet machine", ["7 min"]),
    ("it took about 10\nminutes", ["10\nminutes"]),
    ("warm runs 2.1-2.6 s against 28-63 s", ["2.1-2.6 s", "28-63 s"]),
    ("peak 4.2 GB, two 150 MB copies", ["4.2 GB", "150 MB"]),
    ("the box path 2.0× faster", ["2.0×"]),
    ("a vmapped assembly cost 7x the unbatched kernel", ["7x"]),
    ("no batching can beat the loop by more than ~1.6x on this CPU", ["1.6x"]),
    ("three times faster than the loop", []),               # a ratio in words is not a figure
    ("3 times faster than the loop", ["3 times"]),
    ("its compile is ~70% longer", ["70% longer"]),
    ("factorisation 2.70 -> 1.22 ms", ["2.70 -> 1.22", "1.22 ms"]),
    ("412 -> 213 CG iterations", ["412 -> 213"]),
    ("the 20³ solve: 90.8 s → 73.8 s", ["90.8 s", "73.8 s"]),
    ("assembly time 1.40 → 1.00 per call", ["1.40 → 1.00"]),
]
NOT_FIGURES = [
    "the 9x9 square and 33x33 grid, 2x2 Gauss points per cell, 3 x 3 blocks",
    "stops after 2 x max_iter iterations; shape (n, d) -> (n,)",
    "a 5 mm paddle move, 0.3 N, E = 10 kPa; spacing 0.125; rtol 1e-10",
    "the best patch cuts the deviation 20.8x at spacing 0.2",     # a ratio of a result, not of cost
    "retried with a shift at least 4x larger",                      # an algorithm's factor
    "the smallest eigenvalue falls 17.7 -> 4.0 near the fold",      # a history of a physical value
    "box path: 17/17 waypoints reached (thesis: 625 min)",          # the thesis' reference value
    "beside the thesis' times: 625 / 412 min (Gauss)",
    "the 10^3 cube and the 20³ cube; eqs 3.16-3.21",
    "30% compression in 10 steps",
]


@pytest.mark.parametrize("text, figures", FIGURES, ids=[t for t, _ in FIGURES])
def test_the_checker_finds_timing_figures(text, figures):
    assert [f for _, _, f in timing_figures(text)] == figures


@pytest.mark.parametrize("text", NOT_FIGURES)
def test_the_checker_leaves_other_numbers_alone(text):
    assert timing_figures(text) == []


def test_the_checker_reads_only_the_prose_of_python():
    source = '''"""Module docstring: 5 s a call."""
import time
X = 1  # 2 GB held
# a comment block whose figure
# runs over two lines: 1.5
# ms a solve
def f():
    """A docstring, 3x faster."""
    t = 4.0  # seconds: code, not prose
    print(f"took {t:.1f} s and 12 ms")   # an f-string that prints a measured value
    return "a 9 s string that is code"
'''
    assert figures_in_python(source) == [(1, "duration", "5 s"), (3, "memory", "2 GB"),
                                         (5, "duration", "1.5\nms"), (8, "ratio", "3x")]
    lines = [line for line, _ in python_prose(source)]
    assert lines == [1, 3, 4, 8, 9, 10]


def test_the_checker_counts_lines_in_text():
    assert figures_in_text("# title\n\nno figure here\nthe demo takes 8 s\n") == [(4, "duration", "8 s")]


def package_sources():
    return sorted(p for p in (ROOT / "jaxrkpm").rglob("*.py*") if p.suffix in (".py", ".pyi"))


@pytest.mark.parametrize("path", package_sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_timing_figures_in_the_package_prose(path):
    found = figures_in_python(path.read_text())
    assert not found, (f"timing figures in comments/docstrings of {path.relative_to(ROOT)} "
                       f"(give the reason and the bench that measures it; the figures go to "
                       f"docs/performance.md): {found}")


def doc_pages():
    return [README] + sorted(p for p in DOCS.rglob("*.md") if p != PERFORMANCE)


@pytest.mark.parametrize("path", doc_pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_timing_figures_in_the_readme_and_the_guide(path):
    found = figures_in_text(path.read_text())
    assert not found, f"timing figures in {path.relative_to(ROOT)} (they belong on docs/performance.md): {found}"


# ------------------------------------------------------------------ the README
def test_readme_is_short_and_starts_with_the_two_commands():
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_README_LINES
    words = " ".join(text.split())
    assert "*Model Based Deformable Object Manipulation Path Planning and Position Control*" in words
    assert "J. Smolen and A. Patriciu, 2009" in words
    first_block = text.split("```bash", 1)[1].split("```", 1)[0]
    assert "pip install -e . && jaxrkpm demo" in first_block
    assert 'pip install -e ".[test]" && pytest' in first_block
    # CI runs the README's test command (.ci/run)
    assert 'pip install -e ".[test]" && pytest' in (ROOT / ".ci" / "run").read_text()


def test_readme_commands_table_lists_every_command():
    from jaxrkpm.thesis.cli import commands
    text = README.read_text()
    for name in commands():
        assert f"`jaxrkpm {name}" in text, f"the README's commands table misses `jaxrkpm {name}`"


def readme_example() -> str:
    return README.read_text().split("```python", 1)[1].split("```", 1)[0]


def test_readme_example_is_short_and_runs(tmp_path, monkeypatch):
    code = readme_example()
    assert len(code.strip().splitlines()) <= 16
    monkeypatch.chdir(tmp_path)          # it writes square.vtu
    ns = {}
    exec(compile(code, "README.md example", "exec"), ns)
    sol, model = ns["sol"], ns["model"]
    assert sol.converged and model.dim == 2
    # the paddle pushes the square's right edge left: the centre follows, at less than the
    # paddle's travel, and the paddle's force on the body points left too
    u, J, f = (np.asarray(ns[k]) for k in ("u", "J", "f"))
    assert u.shape == (1, 2) and -0.1 < u[0, 0] < 0 and abs(u[0, 1]) < 1e-12
    assert ns["sigma"].shape == (1, 2, 2)
    assert J.shape == (2, 2) and 0 < J[0, 0] < 1 and 0 < J[1, 1] < 1 and abs(J[0, 1]) < 1e-12
    assert f.shape == (2,) and f[0] < 0 and abs(f[1]) < 1e-9 * abs(f[0])
    assert (tmp_path / "square.vtu").stat().st_size > 0


# ------------------------------------------------------------------ public names only
def public_names():
    """name -> what may follow it: the public surface as declared (lazy, no JAX loaded)."""
    import jaxrkpm
    import jaxrkpm.rig
    import jaxrkpm.thesis
    internal = _all_of(ROOT / "jaxrkpm" / "internal.py")
    return {"top": set(jaxrkpm.__all__) | {"__version__", "thesis"}, "internal": internal,
            "rig": set(jaxrkpm.rig.__all__), "thesis": set(jaxrkpm.thesis.__all__)}


def _all_of(path: Path) -> set:
    import ast
    tree = ast.parse(path.read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", None) == "__all__":
            return {e.value for e in node.value.elts}
    raise AssertionError(f"{path} has no __all__")


THESIS_MODULES = {"cli", "contact_paddle", "data", "needle", "phantom3d", "rigsim", "studies", "tools"}


@pytest.fixture(scope="module")
def package():
    """The package as griffe reads it (statically: nothing is imported)."""
    import griffe   # the docs tools are in the test extra: a missing one is a failure, not a skip
    return griffe.GriffeLoader(search_paths=[str(ROOT)], allow_inspection=False).load("jaxrkpm")


def why_not_public(name: str, public: dict, package) -> str | None:
    """None if the dotted ``name`` (jaxrkpm.X...) is public and exists, else why not."""
    parts = name.split(".")[1:]
    if not parts:
        return None
    head = parts[0]
    if head not in public["top"]:
        return f"jaxrkpm.{head} is not a public name (jaxrkpm/__init__.pyi)"
    if head in ("internal", "rig", "thesis") and len(parts) > 1 and parts[1] not in public[head]:
        return f"{head}.{parts[1]} is not declared in jaxrkpm.{head}"
    if any(p.startswith("_") and p != "__version__" for p in parts):
        return "a private name"
    if head == "thesis" and len(parts) > 2 and parts[1] not in THESIS_MODULES and parts[1][0].islower():
        return f"thesis.{parts[1]} is not a declared submodule"
    try:
        package[".".join(parts)]
    except Exception:   # griffe raises KeyError / AliasResolutionError for a missing member
        return None if _bound_in_module(parts, package) else "no such name"
    return None


def _bound_in_module(parts: list, package) -> bool:
    """Whether ``parts`` is a module of the package followed by a name its source binds at
    the top level (griffe leaves out names bound by tuple assignment: ``A, B = 1, 2``)."""
    import ast
    for k in range(len(parts) - 1, -1, -1):
        try:
            module = package[".".join(parts[:k])] if k else package
        except Exception:
            continue
        if not getattr(module, "is_module", False) or k != len(parts) - 1:
            return False
        tree = ast.parse(Path(module.filepath).read_text())
        bound = set()
        for node in tree.body:
            targets = node.targets if isinstance(node, ast.Assign) else []
            for target in targets:
                for leaf in ast.walk(target):
                    if isinstance(leaf, ast.Name):
                        bound.add(leaf.id)
        return parts[-1] in bound
    return False


IMPORT_AS = re.compile(r"^\s*import\s+(jaxrkpm(?:\.\w+)*)\s+as\s+(\w+)", re.M)
FROM_IMPORT = re.compile(r"^\s*from\s+(jaxrkpm(?:\.\w+)*)\s+import\s+(\([^)]*\)|[^\n#]+)", re.M)
DOTTED = re.compile(r"(?<![\w./])jaxrkpm(?:\.\w+)+")


def names_used(text: str) -> set:
    """Every jaxrkpm name a text uses: dotted names, ``from jaxrkpm... import x`` and the
    attributes of aliases (``import jaxrkpm as jr``: ``jr.Body``; ``jr`` is always jaxrkpm)."""
    aliases = {"jr": "jaxrkpm"}
    used = set(DOTTED.findall(text))
    for module, alias in IMPORT_AS.findall(text):
        aliases[alias] = module
    for module, names in FROM_IMPORT.findall(text):
        for item in names.strip("()").replace("\n", " ").split(","):
            words = item.split()
            if not words:
                continue
            used.add(f"{module}.{words[0]}")
            aliases[words[-1] if len(words) == 3 and words[1] == "as" else words[0]] = f"{module}.{words[0]}"
    for alias, target in aliases.items():
        for attr in re.findall(rf"(?<![\w.]){re.escape(alias)}((?:\.\w+)+)", text):
            used.add(target + attr)
    return used


def notebook_text(path: Path) -> str:
    cells = json.loads(path.read_text())["cells"]
    return "\n".join("".join(c["source"]) for c in cells if c["cell_type"] in ("code", "markdown"))


def test_the_public_name_check_itself(package):
    public = public_names()
    used = names_used("import jaxrkpm as jr\nfrom jaxrkpm.thesis import needle as nd, PATHS\n"
                      "jr.Body.grid((3, 3), 0.5); nd.Phantom(); jaxrkpm.internal.Problem\n"
                      "from jaxrkpm.solvers.newton import newton\n")
    assert {"jaxrkpm.Body.grid", "jaxrkpm.thesis.needle", "jaxrkpm.thesis.needle.Phantom",
            "jaxrkpm.thesis.PATHS", "jaxrkpm.internal.Problem", "jaxrkpm.solvers.newton.newton"} <= used
    assert why_not_public("jaxrkpm.Body.grid", public, package) is None
    assert why_not_public("jaxrkpm.thesis.studies.rig_sim.build", public, package) is None
    assert why_not_public("jaxrkpm.internal.Problem", public, package) is None
    assert why_not_public("jaxrkpm.rig.StereoTracker", public, package) is None
    assert "not a public name" in why_not_public("jaxrkpm.solvers.newton.newton", public, package)
    assert "not declared" in why_not_public("jaxrkpm.internal.Ops2", public, package)
    assert why_not_public("jaxrkpm.Model._springs", public, package) == "a private name"
    assert why_not_public("jaxrkpm.Model.no_such_method", public, package) == "no such name"


def user_documents():
    return [README] + sorted(DOCS.rglob("*.md")) + NOTEBOOKS


@pytest.mark.parametrize("path", user_documents(), ids=lambda p: str(p.relative_to(ROOT)))
def test_documents_use_only_public_names(path, package):
    public = public_names()
    text = notebook_text(path) if path.suffix == ".ipynb" else path.read_text()
    bad = {name: why for name in sorted(names_used(text)) if (why := why_not_public(name, public, package))}
    assert not bad, f"{path.relative_to(ROOT)} uses names that are not public: {bad}"


# ------------------------------------------------------------------ the docs build
@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, f"mkdocs build --strict failed:\n{run.stdout}\n{run.stderr}"
    return out


def test_docs_build_strict_and_reference_every_public_name(site):
    html = "\n".join(p.read_text() for p in (site / "api").rglob("*.html"))
    ids = set(re.findall(r'id="(jaxrkpm[\w.]*)"', html))
    public = public_names()
    missing = [f"jaxrkpm.{n}" for n in public["top"] - {"__version__", "thesis"} if f"jaxrkpm.{n}" not in ids]
    missing += [f"jaxrkpm.internal.{n}" for n in public["internal"]
                if f"jaxrkpm.internal.{n}" not in ids and f"jaxrkpm.{n}" not in ids]
    missing += [f"jaxrkpm.thesis.{n}" for n in public["thesis"] if f"jaxrkpm.thesis.{n}" not in ids]
    missing += [f"jaxrkpm.rig.{n}" for n in public["rig"] if f"jaxrkpm.rig.{n}" not in ids]
    assert not missing, f"public names missing from the API reference: {sorted(missing)}"
    # the reST roles of the docstrings are rendered as code, not shown raw
    assert ":class:`" not in html and ":mod:`" not in html and ":func:`" not in html


def test_every_docs_page_is_in_the_navigation(site):
    pages = {str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md")}
    nav = (ROOT / "mkdocs.yml").read_text()
    assert {p for p in pages if p not in nav} == set()
