"""The persistent compilation cache the command line and the notebooks turn on: where it goes,
how it is turned off, and that a folder JAX was given already is kept."""
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PROBE = ("from jaxrkpm.base.cache import use_compilation_cache\nimport jax\n"
         "print(use_compilation_cache(), jax.config.jax_compilation_cache_dir, "
         "jax.config.jax_persistent_cache_min_compile_time_secs)")


def probe(**env) -> list:
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION", "JAX_PERSISTENT", "JAXRKPM_", "XDG_CACHE"))}
    p = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120,
                       env={**clean, "PYTHONPATH": str(ROOT), **env}, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    return p.stdout.split()


def test_on_by_default_in_the_users_cache_folder(tmp_path):
    folder = tmp_path / "jaxrkpm"
    assert probe(XDG_CACHE_HOME=str(tmp_path)) == [str(folder), str(folder), "0.0"]
    assert folder.is_dir()
    assert probe(HOME=str(tmp_path)) == [str(tmp_path / ".cache" / "jaxrkpm")] * 2 + ["0.0"]
    assert probe(JAXRKPM_CACHE_DIR=str(tmp_path / "mine"))[0] == str(tmp_path / "mine")


def test_turned_off_and_a_given_folder_kept(tmp_path):
    assert probe(XDG_CACHE_HOME=str(tmp_path), JAXRKPM_COMPILATION_CACHE="off") == ["None", "None", "1.0"]
    assert not (tmp_path / "jaxrkpm").exists()
    given = str(tmp_path / "given")
    assert probe(XDG_CACHE_HOME=str(tmp_path), JAX_COMPILATION_CACHE_DIR=given) == [given, given, "1.0"]


def test_the_command_line_turns_it_on(tmp_path, monkeypatch):
    from jaxrkpm.thesis import cli
    from jaxrkpm.thesis.studies import cantilever
    calls = []
    monkeypatch.setattr(cli, "use_compilation_cache", lambda: calls.append(1))
    monkeypatch.setattr(cantilever, "convergence",
                        lambda hs: {"h": [0.25, 0.125], "relative_l2_error": [1e-2, 2.5e-3], "rates": [2.0]})
    assert cli.main(["cantilever", "--out", str(tmp_path / "c")]) == 0 and calls == [1]
    assert cli.main(["cantilever", "--levels", "99"]) == 2 and calls == [1]     # not for a bad command line
