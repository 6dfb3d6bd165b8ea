"""The guide runs as written (as scikit-fem's ``test_examples`` runs its examples): every
```python block of docs/guide/*.md, a page's blocks in order in one namespace, from a folder
holding the repository's small example files (docs/examples/). Every page is checked for
names it uses but never defines; the pages whose blocks run long (the needle studies, the
rig, the 3D and tracking sweeps) run in the slow set, each with its reason. A block after
``<!-- not run: why -->`` is one the suite cannot run (a Dask scheduler elsewhere). The
"Next" links and the home page follow the navigation's order."""
from __future__ import annotations

import builtins
import re
import shutil
import symtable
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "guide"
BLOCK = re.compile(r"(<!-- not run: [^>]*-->\s*)?```python\n(.*?)```", re.S)

# page -> why its blocks run in the slow set (what they add beyond the default run)
SLOW = {
    "needle.md": "the 2D static sweep at the thesis' 15 increments, the dynamic and contact paddles and the "
                 "3D phantom: the needle study tests run each of them small",
    "rig.md": "the simulated rig's closed loop on the 17x17 object: tests/thesis/rigsim run it small",
    "tracking.md": "the box path on the 9x9 square and a contact tracking: tests/control run both",
    "sweeps.md": "the 3D needle and the tracking sweeps: tests/thesis/test_sweeps.py runs them small "
                 "(the first block, the plain sweep, runs in the default set)",
    "solving.md": "the output functions on a 2D and a 3D model, each compiled anew: tests/io and "
                  "tests/model run them; every name the page uses is checked in the default set",
    "derivatives.md": "three derivatives through the solve, each compiled anew: tests/model and "
                      "tests/solvers compare them with finite differences",
    "tools.md": "placement optimisation and closed loop of push-only tools over a full insertion: "
                "tests/thesis/test_needle_tools.py runs them at one increment; every name the page uses "
                "is checked in the default set",
}
FAST_BLOCKS = {"sweeps.md": 1}     # the blocks of a slow page that run in the default set too


def nav_pages() -> list:
    """The guide pages in the navigation's order (mkdocs.yml)."""
    return re.findall(r"guide/([\w-]+\.md)", (ROOT / "mkdocs.yml").read_text())


def blocks(page: str) -> list:
    """The runnable python blocks of a guide page, in order."""
    return [textwrap.dedent(code) for skip, code in BLOCK.findall((GUIDE / page).read_text()) if not skip]


def undefined(code: str) -> set:
    """Names ``code`` reads that it never binds (nor are builtins): in any scope that reads
    them as globals."""
    top = symtable.symtable(code, "guide", "exec")
    bound = {s.get_name() for s in top.get_symbols() if s.is_assigned() or s.is_imported()}
    bound |= {c.get_name() for c in top.get_children()}      # functions and classes defined

    def free(table) -> set:
        out = {s.get_name() for s in table.get_symbols()
               if s.is_referenced() and (s.is_global() or table is top) and not s.is_assigned()
               and not s.is_imported() and not s.is_parameter()}
        for child in table.get_children():
            out |= free(child)
        return out
    return {n for n in free(top) if n not in bound and not hasattr(builtins, n)}


def test_the_checker_finds_undefined_names():
    assert undefined("import numpy as np\nx = np.zeros(3)\nf = lambda X: X[:, 0] < 1e-9\n") == set()
    assert undefined("sol = model.solve()\ny = [p for p in points]\n") == {"model", "points"}
    assert undefined("def g(a):\n    return a + b\n") == {"b"}


@pytest.mark.parametrize("page", nav_pages())
def test_every_guide_page_defines_what_it_uses(page):
    code = "\n".join(blocks(page))
    compile(code, page, "exec")
    assert not undefined(code), f"{page} uses names it never defines: {sorted(undefined(code))}"


def test_next_links_and_the_home_page_follow_the_navigation():
    pages = nav_pages()
    assert {p.name for p in GUIDE.glob("*.md")} == set(pages)
    for page, after in zip(pages, pages[1:]):
        links = re.findall(r"^Next: \[[^\]]+\]\(([\w-]+\.md)\)", (GUIDE / page).read_text(), re.M)
        assert links == [after], f"{page} ends with Next: {links}, the navigation's next page is {after}"
    listed = re.findall(r"^\d+\. \[[^\]]+\]\(guide/([\w-]+\.md)\)", (ROOT / "docs" / "index.md").read_text(), re.M)
    assert listed == pages


def test_getting_started_lists_every_command_and_exit_code():
    from jaxrkpm.thesis.cli import commands
    from jaxrkpm.thesis.studies.interface import EXIT_CODES
    text = (GUIDE / "getting-started.md").read_text()
    for command in commands():
        assert f"`jaxrkpm {command}" in text, command
    for code in EXIT_CODES:
        assert re.search(rf"^\| {code} \|", text, re.M), code
    assert "holds another run's results" in text


def _run(page: str, tmp_path, monkeypatch, which=None) -> dict:
    import matplotlib
    matplotlib.use("Agg")
    shutil.copytree(ROOT / "docs" / "examples", tmp_path / "docs" / "examples")
    monkeypatch.chdir(tmp_path)                 # what the pages write (results/, out.vtu) stays there
    ns: dict = {"__name__": f"guide_{page[:-3]}"}
    for i, code in enumerate(blocks(page)):
        if which is None or i < which:
            exec(compile(code, f"{page} block {i + 1}", "exec"), ns)
    import matplotlib.pyplot as plt
    plt.close("all")
    return ns


FAST = [p for p in nav_pages() if p not in SLOW] + list(FAST_BLOCKS)
RUNS = [pytest.param(p, id=p) for p in FAST] + \
    [pytest.param(p, id=f"{p} (all)", marks=pytest.mark.slow(reason=SLOW[p])) for p in SLOW]


@pytest.mark.parametrize("page", RUNS)
def test_the_guide_runs_as_written(page, request, tmp_path, monkeypatch):
    whole = request.node.callspec.id.endswith("(all)")
    which = None if whole or page not in FAST_BLOCKS else FAST_BLOCKS[page]
    ns = _run(page, tmp_path, monkeypatch, which)
    # what each page promises, in numbers
    if page == "bodies.md":
        assert ns["organ"].dim == 3 and ns["organ"].volumes.sum() > 0 and len(ns["shell"].cells) > 0
        assert len(ns["base"]) > 0 and len(ns["track"]) > 0
    elif page == "solving.md":
        centre = ns["model"].displacement(ns["sol"], [[0.5, 0.5]])
        assert str(ns["sol"].outcome) == "CONVERGED" and float(centre[0, 0]) < 0 and ns["u"].shape == (81, 2)
        assert (tmp_path / "out.vtu").stat().st_size > 0 and (tmp_path / "solution.png").stat().st_size > 0
    elif page == "derivatives.md":
        assert ns["J"].shape == (2, 2) and abs(float(ns["J"][0, 0] - ns["J_fd"][0, 0])) < 1e-5
    elif page == "continuation.md":
        path = ns["path"]                                      # it snaps: the load falls after a limit point
        k = int(path.limit_points[0])
        assert path.load[k + 1] < path.load[k] and str(ns["sol"].outcome) == "CONVERGED"
    elif page == "contact.md":
        assert float(ns["res"].min_gap) > 0 and float(ns["res"].force[1]) < 0
    elif page == "sweeps.md":
        assert ns["summary"].complete and ns["table"].num_rows == 103
