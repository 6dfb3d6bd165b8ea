"""Layering: the hardware package jaxrkpm.rig (stereo, frames, link) imports nothing from the
jaxrkpm solver core and not JAX. Allowed: the standard library, NumPy, SciPy, OpenCV and
sibling rig modules. The simulated rig and the calibration, which need the core, live in
jaxrkpm.thesis.rigsim.

Checked two ways: on the source (every import statement, at any depth, parsed with ``ast``)
and by importing the package under a bare parent package (so jaxrkpm/__init__.py, which
loads JAX and the core, does not run) in a fresh interpreter."""
import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RIG = ROOT / "jaxrkpm" / "rig"
THIRD_PARTY = {"numpy", "scipy", "cv2"}
RIG_PACKAGE = "jaxrkpm.rig"


def _allowed(name: str) -> bool:
    """An absolute module name a hardware module may import."""
    top = name.split(".")[0]
    if top == "jaxrkpm":
        return name == RIG_PACKAGE or name.startswith(RIG_PACKAGE + ".")
    return top in THIRD_PARTY or top in sys.stdlib_module_names


def import_violations(source: str, filename: str = "<string>") -> list:
    """``"line: what"`` for every import in ``source`` a hardware rig module may not make.
    Relative imports: ``from . import x`` / ``from .x import y`` are siblings (allowed),
    ``..`` and above reach the core (refused). ``importlib.import_module`` and
    ``__import__`` with a literal name are checked like imports; with any other argument
    they are refused (the target cannot be checked)."""
    bad = []
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Import):
            bad += [f"{node.lineno}: import {a.name}" for a in node.names if not _allowed(a.name)]
        elif isinstance(node, ast.ImportFrom):
            what = f"{node.lineno}: from {'.' * node.level}{node.module or ''} import " \
                   + ", ".join(a.name for a in node.names)
            if node.level >= 2:
                bad.append(what)
            elif node.level == 0:
                # ``from jaxrkpm import rig`` is the rig package; ``from jaxrkpm import Model`` is not
                names = [f"{node.module}.{a.name}" for a in node.names] if node.module == "jaxrkpm" \
                    else [node.module]
                if not all(_allowed(n) for n in names):
                    bad.append(what)
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            if name in ("import_module", "__import__"):
                arg = node.args[0] if node.args else None
                if not (isinstance(arg, ast.Constant) and isinstance(arg.value, str) and _allowed(arg.value)):
                    bad.append(f"{node.lineno}: {name}({ast.unparse(arg) if arg else ''})")
    return bad


def rig_modules():
    return sorted(RIG.glob("*.py"))


def test_the_hardware_modules_are_all_checked():
    assert {p.name for p in rig_modules()} >= {"__init__.py", "stereo.py", "frames.py", "link.py"}


@pytest.mark.parametrize("path", rig_modules(), ids=lambda p: p.name)
def test_hardware_module_imports_no_core_and_no_jax(path):
    bad = import_violations(path.read_text(), str(path))
    assert not bad, f"{path.relative_to(ROOT)} imports outside the hardware layer: {bad}"


@pytest.mark.parametrize("source", [
    "from .. import Model",
    "from ..solve import point_values",
    "from ...x import y",
    "import jax",
    "import jax.numpy as jnp",
    "from jax import numpy",
    "import jaxrkpm",
    "import jaxrkpm.model",
    "from jaxrkpm import Model",
    "from jaxrkpm.control.tracking import control_increment",
    "from jaxrkpm.thesis.rigsim.sim import ClosedLoop",
    "from jaxrkpm.rigid import x",          # a prefix of the package name is not the package
    "import optax",
    "def f():\n    if True:\n        import jax\n",   # nested, lazy imports count too
    "class A:\n    def m(self):\n        from ..model import Model\n",
    "import importlib\nimportlib.import_module('jaxrkpm.solve')",
    "import importlib\nname = 'jax'\nimportlib.import_module(name)",
    "__import__('jax')",
])
def test_checker_flags_a_violation(source):
    assert import_violations(source)


@pytest.mark.parametrize("source", [
    "from __future__ import annotations",
    "import json, socket, threading",
    "from typing import Callable",
    "import numpy as np",
    "from scipy.special import erfc",
    "import cv2",
    "from .frames import RigidTransform",
    "from . import stereo",
    "from jaxrkpm.rig.frames import RigidTransform",
    "from jaxrkpm import rig",
    "import importlib\nimportlib.import_module('numpy')",
])
def test_checker_allows_the_hardware_dependencies(source):
    assert import_violations(source) == []


def test_hardware_package_imports_without_the_core():
    """Import jaxrkpm.rig with a bare ``jaxrkpm`` package object in place of jaxrkpm/__init__.py:
    nothing from the core and no JAX may be loaded."""
    code = (
        "import sys, types\n"
        f"pkg = types.ModuleType('jaxrkpm'); pkg.__path__ = [{str(ROOT / 'jaxrkpm')!r}]\n"
        "sys.modules['jaxrkpm'] = pkg\n"
        "import jaxrkpm.rig\n"
        "print(' '.join(sorted(m for m in sys.modules if m == 'jax' or m.startswith(('jax.', 'jaxrkpm.')))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    loaded = out.stdout.split()
    assert loaded and all(m.startswith(RIG_PACKAGE) for m in loaded), loaded
