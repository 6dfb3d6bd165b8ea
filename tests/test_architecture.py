"""The package's layers: each imports only the layers below it, and no import cycle exists.

Layers, bottom to top (a folder of ``jaxrkpm/`` each; the public API modules ``jaxrkpm``
(``__init__.py`` and its stub) and ``jaxrkpm.internal`` form the "api" layer above the
library, and the thesis application uses them):

    base < discretise, sweeps < mechanics < solvers < model < control, io < api < thesis

``control`` and ``io`` stand side by side (neither imports the other). ``sweeps``, the
Parquet/Dask job runner, stands beside ``discretise`` just above ``base``, so it imports
nothing of jaxrkpm but ``base``; and only the api and ``thesis`` may use it (the numerics never
need it: ``USED_ONLY_BY``). ``rig``, the hardware side, imports nothing of jaxrkpm but itself
(``tests/rig/test_layering.py`` checks it more strictly); any layer above ``model`` may use it.

Every import counts: module-level and inside functions, ``from . import x`` and absolute
``jaxrkpm.x``, ``importlib.import_module`` / ``__import__`` / a study's ``lazy`` with a literal
name, the module paths written as strings in a module that imports by a computed name, and the
lazy imports a ``.pyi`` stub declares (lazy_loader). The checks run on the source with ``ast``;
nothing is imported.

A command of ``jaxrkpm`` lives in one file: its study module declares it (``COMMAND =
Command(...)``) and no other module names it (``test_a_command_is_named_only_by_its_study``).

Complexity (issue 51): radon's cyclomatic complexity of every function, method, class and
closure is at most 15 in the core (every layer but ``thesis`` and ``rig``) and at most 20 in
the thesis application, which is allowed longer study scripts."""
import ast
from pathlib import Path

import pytest
from radon.complexity import cc_visit

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "jaxrkpm"

ORDER = ["base", ("discretise", "sweeps"), "mechanics", "solvers", "model", ("control", "io"), "api", "thesis"]
# layers that only these layers above them may import
USED_ONLY_BY = {"sweeps": ("api", "thesis")}
RANK = {}
for rank, layer in enumerate(ORDER):
    for name in (layer if isinstance(layer, tuple) else (layer,)):
        RANK[name] = rank


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def layer_of(module: str) -> str:
    """The layer of a module name jaxrkpm.<...>."""
    parts = module.split(".")
    if len(parts) == 1 or parts[1] == "internal":
        return "api"
    return parts[1]


def resolve(module: str, is_package: bool, node: ast.ImportFrom) -> list:
    """Absolute names that ``from ... import ...`` in ``module`` refers to (both the module
    and module.name for each name: a name may be a submodule)."""
    if node.level:
        base = module.split(".")
        if not is_package:
            base = base[:-1]
        base = base[: len(base) - (node.level - 1)]
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ""
    return [target] + [f"{target}.{a.name}" for a in node.names]


def imports_of(path: Path) -> set:
    """jaxrkpm module names that the source at ``path`` imports (as far as they exist)."""
    module = module_name(path)
    is_package = path.stem == "__init__"
    tree = ast.parse(path.read_text(), str(path))
    found = set()
    table_driven = False   # import_module(<not a literal>): the module paths in its strings are imported
    strings = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            found.update(resolve(module, is_package, node))
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)
            if name in ("import_module", "__import__", "lazy") and node.args:
                if isinstance(node.args[0], ast.Constant):
                    found.add(str(node.args[0].value))
                else:
                    table_driven = True
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith("jaxrkpm."):
            strings.add(node.value)
    if table_driven:
        found |= strings   # e.g. the CLI's command table
    return {m for m in found if m.split(".")[0] == "jaxrkpm" and existing(m)}


def existing(module: str) -> bool:
    rel = Path(*module.split("."))
    return (ROOT / rel.with_suffix(".py")).exists() or (ROOT / rel / "__init__.py").exists()


def sources():
    """(path, its module name) for every module of the package; a stub counts as its package."""
    for path in sorted(PACKAGE.rglob("*.py")):
        yield path
    for path in sorted(PACKAGE.rglob("*.pyi")):
        yield path


def graph() -> dict:
    """module -> the jaxrkpm modules it imports (a stub's imports are its package's)."""
    edges = {}
    for path in sources():
        name = module_name(path.with_suffix(".py"))
        edges.setdefault(name, set()).update(imports_of(path) - {name})
    return edges


def allowed(src: str, dst: str) -> bool:
    a, b = layer_of(src), layer_of(dst)
    if b == "rig":
        return a == "rig" or (a != "rig" and RANK.get(a, -1) > RANK["model"])
    if a == "rig":
        return False
    if a == b:
        return True
    if b in USED_ONLY_BY and a not in USED_ONLY_BY[b]:
        return False
    return RANK[a] > RANK[b]


def violations(edges: dict) -> list:
    out = []
    for src, dsts in edges.items():
        for dst in sorted(dsts):
            if dst == "jaxrkpm" and src != "jaxrkpm":
                # ``import jaxrkpm`` or ``from jaxrkpm import name``: an import of the api
                if layer_of(src) not in ("api", "thesis"):
                    out.append(f"{src} -> {dst} (a layer below the api imports the public namespace)")
                continue
            if not allowed(src, dst):
                out.append(f"{src} ({layer_of(src)}) -> {dst} ({layer_of(dst)})")
    return out


def cycles(edges: dict) -> list:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in list(edges):
        if v not in index:
            visit(v)
    return out


def package_edges(edges: dict) -> dict:
    """The graph without the edges into a package's ``__init__`` that Python makes anyway (a
    module's parent package runs first): ``jaxrkpm.solvers.newton`` importing
    ``jaxrkpm.solvers`` (its own parent) is not a dependency."""
    return {src: {d for d in dsts if not src.startswith(d + ".")} for src, dsts in edges.items()}


# ---------------------------------------------------------------------------- the checks
def test_every_module_has_a_layer():
    for path in sources():
        name = module_name(path.with_suffix(".py"))
        assert layer_of(name) in RANK or layer_of(name) == "rig", f"{name} is in no layer: add its folder to ORDER"


def test_no_import_runs_back_up():
    bad = violations(package_edges(graph()))
    assert not bad, "imports against the layering:\n" + "\n".join(bad)


def test_the_sweeps_import_nothing_of_jaxrkpm_but_base():
    """The sweeps are a generic job runner: a numerics module imported there would make every
    sweep depend on it (the rank check allows ``base`` only too; this names the module)."""
    paths = sorted((PACKAGE / "sweeps").rglob("*.py"))
    assert len(paths) > 1
    for path in paths:
        outside = sorted(m for m in imports_of(path) if layer_of(m) not in ("base", "sweeps"))
        assert not outside, f"{path.relative_to(ROOT)} imports {outside}: the sweeps may import only jaxrkpm.base"


def test_no_import_cycle():
    found = cycles(package_edges(graph()))
    assert not found, f"import cycles: {found}"


# ---------------------------------------------------------------------- the checker itself
@pytest.mark.parametrize("edges, expect", [
    ({"jaxrkpm.mechanics.assembly": {"jaxrkpm.solvers.results"}}, 1),          # up one layer
    ({"jaxrkpm.solvers.newton": {"jaxrkpm.mechanics.assembly"}}, 0),          # down
    ({"jaxrkpm.control.tracking": {"jaxrkpm.io.output"}}, 1),                 # sideways: siblings
    ({"jaxrkpm.model.model": {"jaxrkpm"}}, 1),                                # the public namespace
    ({"jaxrkpm.thesis.needle": {"jaxrkpm"}}, 0),
    ({"jaxrkpm.rig.link": {"jaxrkpm.base.outcome"}}, 1),                      # the rig takes no core
    ({"jaxrkpm.thesis.rigsim.sim": {"jaxrkpm.rig.link"}}, 0),
    ({"jaxrkpm.solvers.path": {"jaxrkpm.rig.link"}}, 1),
    ({"jaxrkpm.sweeps.runner": {"jaxrkpm.base.progress"}}, 0),                # the sweeps take base only
    ({"jaxrkpm.sweeps.runner": {"jaxrkpm.discretise.body"}}, 1),
    ({"jaxrkpm.sweeps.executors": {"jaxrkpm.control.batching"}}, 1),
    ({"jaxrkpm.control.batching": {"jaxrkpm.sweeps.runner"}}, 1),            # and only the api and thesis use them
    ({"jaxrkpm.model.model": {"jaxrkpm.sweeps.schema"}}, 1),
    ({"jaxrkpm.thesis.sweeps": {"jaxrkpm.sweeps.runner"}}, 0),
    ({"jaxrkpm.internal": {"jaxrkpm.sweeps.storage"}}, 0),
])
def test_the_layer_check_catches_what_it_must(edges, expect):
    assert len(violations(edges)) == expect


def test_the_cycle_check_catches_a_cycle_through_a_function_level_import(tmp_path):
    a = "def f():\n    from .b import g\n"
    b = "import importlib\nM = importlib.import_module('jaxrkpm.x.a')\n"
    root = tmp_path / "jaxrkpm" / "x"
    root.mkdir(parents=True)
    (tmp_path / "jaxrkpm" / "__init__.py").write_text("")
    (root / "__init__.py").write_text("")
    (root / "a.py").write_text(a)
    (root / "b.py").write_text(b)
    global ROOT
    saved = ROOT
    try:
        ROOT = tmp_path
        edges = {module_name(p): imports_of(p) for p in (root / "a.py", root / "b.py")}
    finally:
        ROOT = saved
    assert cycles(edges) == [["jaxrkpm.x.a", "jaxrkpm.x.b"]]


# ------------------------------------------------------------------- the solver contract
CONTRACT = ("init", "step", "terminate", "postprocess")


def solver_classes(paths) -> dict:
    """class name -> (base names, method names, where) for the classes in ``paths`` (by name:
    the solver classes of the package have unique names)."""
    out = {}
    for path in paths:
        tree = ast.parse(path.read_text(), str(path))
        for node in tree.body:
            if isinstance(node, ast.ClassDef):
                bases = {b.id if isinstance(b, ast.Name) else getattr(b, "attr", "") for b in node.bases}
                methods = {f.name for f in node.body if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))}
                out[node.name] = (bases, methods, f"{path.relative_to(ROOT)}:{node.lineno}")
    return out


def contract_violations(classes: dict, contract: str = "IterativeSolver") -> list:
    """Every class with a ``step`` or ``terminate`` (an iteration) must subclass ``contract``
    (directly or through its bases) and have, itself or by inheritance, all of CONTRACT."""
    def lineage(name, seen=()):
        if name not in classes or name in seen:
            return [name]
        bases, _, _ = classes[name]
        return [name] + [c for b in bases for c in lineage(b, seen + (name,))]

    out = []
    for name, (_, methods, where) in classes.items():
        if name == contract or not methods & {"step", "terminate"}:
            continue
        chain = lineage(name)
        if contract not in chain:
            out.append(f"{where} {name} iterates but is no {contract}")
            continue
        have = set().union(*(classes[c][1] for c in chain if c in classes and c != contract))
        missing = [m for m in CONTRACT if m not in have]
        if missing:
            out.append(f"{where} {name} lacks {missing}")
    return out


def solver_sources():
    """The modules whose classes iterate: solvers/ and the tracking loop."""
    return sorted((PACKAGE / "solvers").rglob("*.py")) + [PACKAGE / "control" / "tracking.py"]


def test_every_solver_implements_the_contract():
    """Every solver and driver (a class with ``step`` or ``terminate``) in solvers/ and the
    tracking loop subclasses ``jaxrkpm.solvers.iterate.IterativeSolver`` and implements
    init, step, terminate and postprocess; and there are such solvers to check."""
    classes = solver_classes(solver_sources())
    assert "IterativeSolver" in classes
    assert {"Newton", "Chord", "LoadPath", "StableDescent", "ArcLength", "ArcLengthPath", "Tracker"} <= set(classes)
    bad = contract_violations(classes)
    assert not bad, "solvers outside the contract:\n" + "\n".join(bad)


def test_the_contract_check_catches_what_it_must(tmp_path):
    src = tmp_path / "fake.py"
    src.write_text("class IterativeSolver:\n    def init(self): ...\n    def step(self): ...\n"
                   "    def terminate(self): ...\n    def postprocess(self): ...\n"
                   "class Rogue:\n    def step(self): ...\n    def terminate(self): ...\n"
                   "class Partial(IterativeSolver):\n    def step(self): ...\n"
                   "class Whole(IterativeSolver):\n    def init(self): ...\n    def step(self): ...\n"
                   "    def terminate(self): ...\n    def postprocess(self): ...\n"
                   "class Heir(Whole):\n    def step(self): ...\n"
                   "class Linear:\n    def init(self): ...\n    def solve(self): ...\n")
    global ROOT
    saved = ROOT
    try:
        ROOT = tmp_path
        classes = solver_classes([src])
    finally:
        ROOT = saved
    # the contract's own (abstract) methods do not count for a class that claims it
    bad = contract_violations(classes)
    assert len(bad) == 2 and "Rogue iterates but is no IterativeSolver" in bad[0] and "Partial lacks" in bad[1]


# names of module-level constants in solvers/ that are codes and tables, not tuning knobs: a
# tuning constant is a field (or class attribute) of the object it tunes, documented there
SOLVER_CODES = {"MKL_DOMAIN_PARDISO", "PARDISO_ERRORS", "FACTORISATIONS", "UNKNOWN", "FAILED", "NONE"}


def _number(node) -> bool:
    """A numeric literal expression (1e-10, 1 << 16, -1)."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, (int, float)) and not isinstance(node.value, bool)
    if isinstance(node, ast.UnaryOp):
        return _number(node.operand)
    return isinstance(node, ast.BinOp) and _number(node.left) and _number(node.right)


def test_no_module_level_tuning_constant_in_solvers():
    """No public UPPER_CASE module constant (but the declared codes and tables) and no
    private numeric one in solvers/: private compiled functions and library handles stay."""
    found = []
    for path in sorted((PACKAGE / "solvers").rglob("*.py")):
        for node in ast.parse(path.read_text(), str(path)).body:
            targets = node.targets if isinstance(node, ast.Assign) else \
                [node.target] if isinstance(node, ast.AnnAssign) else []
            for t in targets:
                name = getattr(t, "id", "")
                public = name.isupper() and not name.startswith("_")
                numeric = name.lstrip("_").isupper() and node.value is not None and _number(node.value)
                if (public or numeric) and name not in SOLVER_CODES:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} {name}")
    assert not found, "module-level constants in solvers/ (make each a field of what it tunes):\n" + "\n".join(found)


# ------------------------------------------------------------------------ complexity
CORE_LIMIT, THESIS_LIMIT = 15, 20
# What is not held to the limits yet (paths under jaxrkpm/, folders or files): the parts of
# issue 51 that other branches are refactoring. Take an entry out when its branch merges;
# empty, the whole package is held (a new module is held from its first commit).
NOT_YET_HELD = ("control/friction.py", "thesis/tools.py")


def limit_of(rel: Path) -> int | None:
    """The complexity limit of the module at ``rel`` (under jaxrkpm/); None: not held (the
    rig, which imports no core and has its own tests, or an entry of NOT_YET_HELD)."""
    if rel.parts[0] == "rig" or any(rel.as_posix() == p or rel.as_posix().startswith(p + "/")
                                    for p in NOT_YET_HELD):
        return None
    return THESIS_LIMIT if rel.parts[0] == "thesis" else CORE_LIMIT


def blocks(source: str):
    """Every function, method and class radon measures in ``source``, and their closures."""
    todo = list(cc_visit(source))
    while todo:
        block = todo.pop()
        yield block
        todo.extend(getattr(block, "closures", ()))


def too_complex(source: str, limit: int) -> list:
    return sorted(f"{b.fullname} (line {b.lineno}): {b.complexity}" for b in blocks(source) if b.complexity > limit)


def test_no_function_is_too_complex():
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        limit = limit_of(path.relative_to(PACKAGE))
        if limit is not None:
            bad += [f"{path.relative_to(ROOT)}: {b} > {limit}" for b in too_complex(path.read_text(), limit)]
    assert not bad, ("radon cyclomatic complexity above the limit; split these into named pieces:\n"
                     + "\n".join(bad))


def test_what_is_not_held_yet_exists():
    """An entry of NOT_YET_HELD names a module or folder of the package (a stale one would
    hold nothing back and hide that the list can shrink)."""
    for p in NOT_YET_HELD:
        assert (PACKAGE / p).exists(), f"NOT_YET_HELD names {p!r}, which is not in jaxrkpm/: take it out"


def test_the_complexity_check_catches_what_it_must():
    def branches(n, indent):   # complexity n + 1
        return "".join(f"{indent}if x == {k}:\n{indent}    return {k}\n" for k in range(n))

    source = ("def f(x):\n" + branches(15, "    ") + "    return -1\n"
              "def g(x):\n    def h(x):\n" + branches(15, "        ") + "        return -1\n    return h(x)\n")
    assert [b.split(" ")[0] for b in too_complex(source, CORE_LIMIT)] == ["f", "h"]   # h: a closure
    assert too_complex(source, THESIS_LIMIT) == []
    assert limit_of(Path("discretise/scni.py")) == CORE_LIMIT
    assert limit_of(Path("thesis/studies/needle.py")) == THESIS_LIMIT
    assert limit_of(Path("rig/link.py")) is None


# ------------------------------------------------------------------ the tests themselves
TESTS = ROOT / "tests"


def _test_sources():
    return sorted(p for p in TESTS.rglob("*.py") if p.name != "timing_figures.py")


@pytest.mark.parametrize("path", _test_sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_tests_import_no_experiments_and_read_no_clock(path):
    """Tests import the package and tests/problems.py, never the benches' scripts; work is
    checked by counts (iterations, factorisations, compiles), never by a timed speed (that is
    a bench's job: experiments/bench_*.py). ``time.monotonic`` stays for what is behaviour,
    not speed: a link's timeout firing on time, a call failing at once instead of hanging."""
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            assert (node.module or "").split(".")[0] != "experiments", f"{path.name}:{node.lineno} imports experiments"
        elif isinstance(node, ast.Import):
            assert all(a.name.split(".")[0] != "experiments" for a in node.names), \
                f"{path.name}:{node.lineno} imports experiments"
        elif isinstance(node, ast.Attribute) and node.attr in ("perf_counter", "process_time") \
                or isinstance(node, ast.Attribute) and node.attr == "time" and getattr(node.value, "id", "") == "time":
            raise AssertionError(f"{path.name}:{node.lineno} reads a clock ({ast.unparse(node)})")


# ------------------------------------------------------------------ one file per command
STUDIES = PACKAGE / "thesis" / "studies"


def _call_name(node: ast.Call) -> str | None:
    f = node.func
    return f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)


def declared_commands(path: Path) -> list:
    """(command name, problem or None) of every ``Command(...)`` in the source at ``path``: a
    problem where it is not the module-level ``COMMAND`` of a study module or its name is not
    a literal."""
    tree = ast.parse(path.read_text(), str(path))
    top = {id(node.value): node for node in tree.body if isinstance(node, ast.Assign)}
    out = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and _call_name(node) == "Command"):
            continue
        name = node.args[0] if node.args else next((k.value for k in node.keywords if k.arg == "name"), None)
        name = name.value if isinstance(name, ast.Constant) else None
        assign = top.get(id(node))
        targets = [getattr(t, "id", None) for t in assign.targets] if assign else []
        problem = None
        if path.parent != STUDIES or targets != ["COMMAND"]:
            problem = "a Command is declared only as the module-level COMMAND of a module of thesis/studies"
        elif name is None:
            problem = "a command's name is a literal string"
        out.append((name, problem))
    return out


REGISTERING = ("parser", "parse", "results", "identity", "command")   # calls that take a command's name


def _module_level(tree: ast.Module):
    """The nodes of a module's own statements, not inside its functions and classes."""
    stack = [n for n in tree.body if not isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))]
    while stack:
        node = stack.pop()
        yield node
        stack.extend(ast.iter_child_nodes(node))


def _registrations(tree: ast.Module):
    """The string literals where a module would register a command by its name: anywhere at
    module level (a table: COMMANDS, PARSERS, STUDIES), the first argument of a call that
    takes a command's name (``interface.parser("track", ...)``), the first item of a tuple
    returned (an experiment's ``("track", argv)``)."""
    for node in _module_level(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            yield node
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and _call_name(node) in REGISTERING and node.args:
            yield node.args[0]
        elif isinstance(node, ast.Return) and isinstance(node.value, ast.Tuple) and node.value.elts:
            yield node.value.elts[0]


def command_names_outside(path: Path, names: dict, studies: set) -> list:
    """Where the source at ``path`` names a command that another module declares (``names``:
    command -> its module's path; ``studies``: the dotted paths of the modules declaring one):
    a study module's path anywhere, or the command's name where a module would register it
    (:func:`_registrations`)."""
    tree = ast.parse(path.read_text(), str(path))
    mine = {n for n, p in names.items() if p == path}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and node.value in studies and node.value != module_name(path):
            found.append(f"{path.relative_to(ROOT)}:{node.lineno} names the study module {node.value}")
    for node in _registrations(tree):
        text = node.value if isinstance(node, ast.Constant) else None
        if isinstance(text, str) and text in names and text not in mine:
            found.append(f"{path.relative_to(ROOT)}:{node.lineno} names the command {text!r} "
                         f"(declared in {names[text].relative_to(ROOT)})")
    return sorted(set(found))


def command_problems(root: Path) -> list:
    """Every breach of one file per command in the package at ``root``."""
    names, studies, problems = {}, set(), []
    for path in sorted(root.rglob("*.py")):
        for name, problem in declared_commands(path):
            studies.add(module_name(path))
            if problem:
                problems.append(f"{path.relative_to(ROOT)}: {problem}")
            elif name in names:
                problems.append(f"{path.relative_to(ROOT)}: the command {name!r} is declared twice "
                                f"(also in {names[name].relative_to(ROOT)})")
            else:
                names[name] = path
    for path in sorted(root.rglob("*.py")):
        problems += command_names_outside(path, names, studies)
    return problems


def test_a_command_is_named_only_by_its_study():
    """Each command of ``jaxrkpm`` is declared once, by its study module's ``COMMAND``, and
    registered nowhere else: no table of names or module paths in the CLI, reproduce or the
    experiments list (they read the declarations)."""
    problems = command_problems(PACKAGE)
    assert not problems, "\n".join(problems)
    assert sum(1 for p in STUDIES.glob("*.py") for _ in declared_commands(p)) >= 9


def test_the_command_check_catches_a_table_of_commands(tmp_path):
    global ROOT, STUDIES
    studies = tmp_path / "jaxrkpm" / "thesis" / "studies"
    studies.mkdir(parents=True)
    (studies / "hello.py").write_text("COMMAND = Command('hello', 'says hello', p, m, r)\n")
    (studies / "again.py").write_text("COMMAND = Command(name='hello', summary='again', parser=p, main=m, result=r)\n")
    (studies / "table.py").write_text("STUDIES = {'hello': 'jaxrkpm.thesis.studies.hello'}\n"
                                      "EXTRA = Command('bye', 'in a table', p, m, r)\n")
    (tmp_path / "jaxrkpm" / "thesis" / "cli.py").write_text("COMMANDS = ['hello']\n")
    saved = ROOT, STUDIES
    try:
        ROOT, STUDIES = tmp_path, studies
        problems = command_problems(tmp_path / "jaxrkpm")
    finally:
        ROOT, STUDIES = saved
    text = "\n".join(problems)
    assert "declared twice" in text and "only as the module-level COMMAND" in text
    assert "table.py:1 names the study module jaxrkpm.thesis.studies.hello" in text
    assert "table.py:1 names the command 'hello'" in text and "cli.py:1 names the command 'hello'" in text


# --------------------------------------------------------------------------- the model
MODEL = PACKAGE / "model"


def test_the_model_is_a_thin_facade():
    """``Model`` delegates to the builders of the lower layers (discretise, assemble, the
    linear solver) and to the functions beside it (inputs, solving, jacobian, post)."""
    lines = len((MODEL / "model.py").read_text().splitlines())
    assert lines <= 300, f"model/model.py has {lines} lines (at most 300): move the work into a module beside it"


BUILT_IN_NAMES = {"strain", "springs", "dead_load"}


@pytest.mark.parametrize("path", sorted(MODEL.glob("*.py")), ids=lambda p: p.name)
def test_the_model_finds_built_in_terms_by_type(path):
    """No built-in term is reached by its name (``problem.term("strain")``): by its type
    (``Problem.term_of(StrainEnergy)``), so that a name is only a key of parameters."""
    names = [n.value for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Constant)
             and n.value in BUILT_IN_NAMES]
    assert not names, f"model/{path.name} names built-in terms {names}: find them by type"
