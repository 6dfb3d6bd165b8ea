"""experiments/bench_peer.py at its smoke size: jaxrkpm and FElupe solve the clamped cube, the
record has its parts, and the two codes agree on the coarse reaction. The bench runs as a
subprocess (tests import no experiment); FElupe is the optional ``reference`` extra."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_bench_peer_smoke_cube():
    pytest.importorskip("felupe")
    r = subprocess.run([sys.executable, "-m", "experiments.bench_peer", "--smoke", "--no-record", "--cases", "cube",
                        "--n", "4", "--m", "1", "2", "--repeats", "1", "--single-thread"],
                       cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    rows = out["figures"]["summary"]
    assert set(rows) == {"cube jaxrkpm-gauss n=4", "cube felupe-hex27 m=1", "cube felupe-hex27 m=2"}
    for row in rows.values():
        assert row["error"] is None
        assert row["load_steps"] >= 5 and row["newton_iterations"] >= row["load_steps"]
        assert row["warm_s"] > 0 and row["cold_s"] > row["warm_s"]
        assert row["reaction"] < 0 and 0 <= row["reaction_error"] < 0.1 and 0 <= row["probe_error"] < 0.3
    ref = out["figures"]["references"]["cube"]
    assert ref["reaction"] < 0 and ref["reaction_error_estimate"] >= 0
    jax_row = rows["cube jaxrkpm-gauss n=4"]
    # the same energy and loads: the coarse models agree with each other within a few percent
    assert abs(jax_row["reaction"] / rows["cube felupe-hex27 m=2"]["reaction"] - 1) < 0.05
    assert jax_row["compile_s"] > 0 and jax_row["warm_ratio_at_reaction_error"] > 0
    assert any("time / FElupe's at equal reaction error" in k for k in out["ratios"])
    assert jax_row["felupe_warm_at_reaction_error_from"] in ("interpolated", "coarsest", "finest")
