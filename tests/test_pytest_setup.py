"""The test command: a plain ``pytest`` runs without pytest-xdist (no xdist options in
addopts), and with it gets two workers, one per file, no worker restart (tests/conftest.py)."""
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ONE = "tests/base/test_programs.py"


def pytest(*args) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "pytest", "--co", "-q", ONE, *args], capture_output=True,
                          text=True, timeout=300, env=env, cwd=ROOT)


def test_without_xdist_plain_pytest_runs():
    p = pytest("-p", "no:xdist")
    assert p.returncode == 0, p.stdout + p.stderr
    assert "unrecognized arguments" not in p.stderr and "tests collected" in p.stdout


def test_with_xdist_two_workers_per_file_no_restart():
    import pytest as pt
    pt.importorskip("xdist")
    code = ("import pytest, sys\n"
            "class Show:\n"
            "    def pytest_configure(self, config):\n"
            "        o = config.option\n"
            "        print('XDIST', o.numprocesses, o.dist, o.maxworkerrestart, len(o.tx), file=sys.stderr)\n"
            f"sys.exit(pytest.main(['-q', '--co', {ONE!r}] + sys.argv[1:], plugins=[Show()]))")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def show(*args):
        p = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300,
                           env=env, cwd=ROOT)
        return next(l for l in p.stderr.splitlines() if l.startswith("XDIST")).split()[1:]
    assert show() == ["2", "loadfile", "0", "2"]
    assert show("-n", "0") == ["0", "no", "0", "0"]
    assert show("-n", "3", "--dist", "load") == ["3", "load", "0", "3"]


def test_the_slow_first_files_exist():
    """tests/conftest.py queues these files first; a renamed one would silently drop out."""
    from tests.conftest import SLOW_FIRST
    missing = [path for path in SLOW_FIRST if not (ROOT / path).is_file()]
    assert not missing, f"tests/conftest.py SLOW_FIRST names files that do not exist: {missing}"


def test_the_default_run_leaves_out_the_slow_set():
    """pyproject.toml's addopts deselect the tests marked slow; ``-m slow`` selects them."""
    default, slow = pytest("-p", "no:xdist", "tests/solvers/test_solver.py"), \
        pytest("-p", "no:xdist", "-m", "slow", "tests/solvers/test_solver.py")
    assert "test_jit_and_eager_solves_agree" not in default.stdout and "deselected" in default.stdout
    assert "test_jit_and_eager_solves_agree" in slow.stdout and "test_jit_and_eager_agree" not in slow.stdout
