"""Compiled programs hold memory mappings until released (jaxrkpm/programs.py)."""
import jax
import jax.numpy as jnp
import pytest

from jaxrkpm.base import programs


@pytest.mark.skipif(programs.memory_mappings() == 0, reason="needs /proc (Linux)")
def test_release_frees_the_mappings_of_compiled_programs():
    programs.release_compiled_programs()
    before = programs.memory_mappings()
    fs = [jax.jit(lambda x, k=k: jnp.sin(x * k).cumsum() @ x) for k in range(8)]
    for f in fs:
        f(jnp.ones(16)).block_until_ready()
    held = programs.memory_mappings()
    assert held > before + 8, (before, held)            # each program holds some
    assert not programs.release_if_crowded(fraction=1.0)  # far below the cap: kept
    assert programs.memory_mappings() >= held - 2
    assert programs.release_if_crowded(fraction=0.0)      # "crowded": released
    assert programs.memory_mappings() < held - 8, (before, held, programs.memory_mappings())


def test_mapping_limit_is_the_kernel_setting():
    assert programs.mapping_limit() >= 1024
