"""Hertz's line contact: a rigid cylinder pressed into an elastic block (plane strain, small
strains), the contact half-width and peak pressure against Hertz's at two loads. The setting and
the fit are ``tests.problems.hertz_line_contact``'s (``experiments/hertz_contact.py`` runs it):
a half-model whose half-width is several particles wide and whose block is well over ten
half-widths (a block of just ten half-widths at this spacing misses the 5% at the larger load)."""
from tests.problems import hertz_line_contact


def test_hertz_half_width_and_peak_pressure_within_5_percent():
    record = hertz_line_contact(spacing=0.02, depths=(0.002, 0.0038))
    for load in record["loads"]:
        print(f"depth {load['depth']}: half-width / Hertz {load['half_width_ratio']:.4f}, "
              f"peak pressure / Hertz {load['peak_ratio']:.4f}")
        assert load["status"].startswith("converged"), load["status"]
        assert load["block_over_half_width"] >= 10
        assert abs(load["half_width_ratio"] - 1) < 0.05, load
        assert abs(load["peak_ratio"] - 1) < 0.05, load
        assert load["min_gap"] > 0    # no interpenetration
