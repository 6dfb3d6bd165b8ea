"""Shared set-up of the test processes: float64, less XLA optimisation work, and one persistent
XLA compilation cache for the whole run. The two xdist workers, the notebook kernels and the
CLI subprocesses compile many of the same solvers; with the cache each is compiled once (the
variables are set before jax is imported, and the subprocesses inherit them)."""
import os
from pathlib import Path

os.environ.setdefault("JAX_COMPILATION_CACHE_DIR",
                      str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
# Most of the suite's time is XLA compiling programs that then run for milliseconds, so the tests
# ask XLA:CPU for less optimisation work (JAX's flag for this case: it changes how the machine
# code is made, not what it computes); a module whose solves run long (large 3D sweeps) marks
# itself ``pytestmark = pytest.mark.xla_optimised`` and keeps XLA's defaults, as the benches
# and the users' runs do.
os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")


def _with_legacy_cpu_emitters():
    """XLA:CPU's MLIR fusion emitters take much of a compile's time; the older emitters make
    code for the same fusions (same arithmetic) sooner (measured on the suite's heaviest
    modules; docs/troubleshooting.md#compile-times-and-the-compile-cache). XLA aborts on a
    flag it does not know, so the flag is added only where a throwaway interpreter with it
    starts JAX's CPU backend (once per run: the xdist workers and subprocesses inherit the
    environment)."""
    flag = "--xla_cpu_use_fusion_emitters=false"
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" in flags or os.environ.get("JAXRKPM_TEST_XLA_FLAGS_CHECKED"):
        return
    import subprocess
    import sys
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.numpy.zeros(1).block_until_ready()"],
                           env={**os.environ, "XLA_FLAGS": f"{flags} {flag}".strip()},
                           capture_output=True, timeout=120)
    if probe.returncode == 0:
        os.environ["XLA_FLAGS"] = f"{flags} {flag}".strip()
    os.environ["JAXRKPM_TEST_XLA_FLAGS_CHECKED"] = "1"


_with_legacy_cpu_emitters()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import pytest  # noqa: E402

from jaxrkpm.base.programs import release_compiled_programs, release_if_crowded  # noqa: E402


# A test worker that kept every program compiled by half the suite crossed Linux's cap on
# memory mappings (jaxrkpm/programs.py): its next compile died (SIGABRT, or SIGSEGV in
# libgcc's unwinder), the crashed workers seen in CI. So the compiled programs go with the
# test module that compiled them, and sooner where one module alone crowds the cap.
@pytest.fixture(scope="module", autouse=True)
def _programs_per_module():
    yield
    release_compiled_programs()


@pytest.fixture(scope="module", autouse=True)
def _xla_optimisation(request):
    """XLA's full optimisation for the modules marked ``xla_optimised`` (set up before their own
    module fixtures, which compile the long-running programs)."""
    before = jax.config.read("jax_disable_most_optimizations")
    if request.node.get_closest_marker("xla_optimised") is not None:
        jax.config.update("jax_disable_most_optimizations", False)
    yield
    jax.config.update("jax_disable_most_optimizations", before)


def pytest_configure(config):
    config.addinivalue_line("markers", "xla_optimised: the module's programs run long: compile them with "
                                       "XLA's full optimisation (tests/conftest.py)")
    config.addinivalue_line("markers", "slow(reason): a long study reproduction whose parts are tested faster "
                                       "elsewhere; left out of the default run (pyproject.toml), run by "
                                       "`pytest -m slow`; the reason says what it adds")


@pytest.fixture(autouse=True)
def _mapping_headroom():
    yield
    release_if_crowded()


# Two workers (JAX compiles are single-threaded; the machine has 2 cores), one per test file
# (module-scoped compiled models are built once), where pytest-xdist is installed and the command
# line chose no distribution itself (-n, --dist, -p no:xdist); a plain pytest without the test
# extra runs serially. No worker restart: pytest-xdist 3.8's loadfile scheduler deadlocks after
# replacing a crashed worker (it re-queues the dead worker's finished files as empty work units:
# pytest-xdist issues #784, #1378), which turned one crashed worker into a CI run that never
# ended; a crash now fails the run at once.
@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    if not config.pluginmanager.has_plugin("xdist") or hasattr(config, "workerinput"):
        return
    option = config.option
    if option.numprocesses is None and option.dist == "no" and not option.tx:
        option.numprocesses, option.dist = 2, "loadfile"
        option.loadscopereorder = False    # keep SLOW_FIRST's order (below)
    if option.maxworkerrestart is None:
        option.maxworkerrestart = 0



# The files that take longest, first: each worker takes the next file when it is nearly done, so
# with the long ones queued last one worker could still be in a 400 s file while the other has
# run out of work (longest-processing-time-first scheduling; the order is that of a clean run's
# durations, with the compile flags of this conftest). The other files keep
# pytest's order after them.
SLOW_FIRST = (
    "tests/solvers/test_solver.py",
    "tests/mechanics/test_anti_locking.py",
    "tests/thesis/test_needle.py",
    "tests/discretise/test_mesh.py",
    "tests/mechanics/test_contact.py",
    "tests/model/test_jacobian.py",
    "tests/solvers/test_stability.py",
    "tests/thesis/test_needle_contact.py",
    "tests/thesis/rigsim/test_sim.py",
    "tests/discretise/test_mesh_hostile.py",
    "tests/mechanics/test_tissue.py",
    "tests/control/test_batching.py",
    "tests/mechanics/test_hertz.py",
    "tests/discretise/test_scni.py",
    "tests/mechanics/test_springs.py",
    "tests/mechanics/test_pressure.py",
    "tests/test_api.py",
    "tests/model/test_hardening.py",
    "tests/control/test_track_contact.py",
    "tests/test_notebooks.py",
)


def pytest_collection_modifyitems(config, items):
    unjustified = [item.nodeid for item in items
                   if any(not m.kwargs.get("reason") for m in item.iter_markers("slow"))]
    if unjustified:
        raise pytest.UsageError(f"tests marked slow without a reason: {unjustified}; "
                                "write pytest.mark.slow(reason='what it adds beyond the default run')")
    rank = {path: i for i, path in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))   # stable
