"""First contact with the command line: help without JAX, descriptions, --version, exit codes,
one-line errors, the one summary line, the report's verdicts and the figures' fixes. Nothing
here solves anything big: bad input stops before any solve, the rest uses fake summaries."""
import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from jaxrkpm.thesis import cli
from jaxrkpm.thesis.studies import interface

ROOT = Path(__file__).resolve().parents[2]


def python(code: str, timeout: float = 60) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout,
                          env=env, cwd=ROOT)


def test_help_of_every_command_without_jax():
    code = ("import sys\nfrom jaxrkpm.thesis import cli\n"
            "codes = [cli.main(['--help'])] + [cli.main([c, '--help']) for c in cli.COMMANDS]\n"
            "print('CODES', codes, 'JAX', 'jax' in sys.modules)")
    p = python(code)
    assert p.returncode == 0, p.stderr
    assert f"CODES {[0] * (len(cli.COMMANDS) + 1)} JAX False" in p.stdout
    for name, (_, what) in cli.COMMANDS.items():
        assert f"  {name}" in p.stdout and what in p.stdout          # top level: name + description
        assert f"usage: jaxrkpm {name} " in p.stdout                  # the right program name
    assert "exit codes:" in p.stdout and "output folder (--out) cannot be" in p.stdout
    assert "DESIGN.md" not in p.stdout and "as in the issue" not in p.stdout


def test_importing_the_package_is_light_and_float64():
    p = python("import sys, jaxrkpm as jr\nprint('jax' in sys.modules)\n"
               "import jax.numpy as jnp\nprint(jnp.ones(2).dtype, jr.Model.__name__, jr.track.__name__)")
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["False", "float64", "Model", "track"]
    p = python("import jax\nimport jaxrkpm\nimport jax.numpy as jnp\nprint(jnp.ones(2).dtype)")
    assert p.stdout.strip() == "float64", p.stderr   # jax imported first: switched on import


def test_version(capsys):
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"jaxrkpm {version}"


def test_unknown_command_says_so(capsys):
    assert cli.main(["trak"]) == interface.EXIT_USAGE
    err = capsys.readouterr().err
    assert "unknown command 'trak'" in err and "did you mean 'track'" in err and "reproduce" in err


@pytest.mark.parametrize("argv, option, wanted", [
    (["track", "--n", "1"], "--n", "an integer >= 3"),
    (["compress", "--step", "0"], "--step", "a number in (0, 0.5]"),
    (["compress", "--max", "nan"], "--max", "a number in (0, 1)"),
    (["needle", "--increments", "-3"], "--increments", "an integer in [1, 1000]"),
    (["needle", "--paddle", "6"], "--paddle", "an integer in [1, 5]"),
    (["rig-sim", "--gain", "inf"], "--gain", "a number in (0, 1]"),
    (["track", "--tol", "abc"], "--tol", "a number > 0"),
])
def test_out_of_range_numbers_are_one_line_usage_errors(argv, option, wanted, capsys):
    assert cli.main(argv) == interface.EXIT_USAGE
    err = capsys.readouterr().err
    assert f"argument {option}: must be {wanted}, got" in err and "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith(f"jaxrkpm {argv[0]}: error: argument {option}")


def test_step_larger_than_the_range_is_a_usage_error(capsys):
    assert cli.main(["compress", "--step", "0.2", "--max", "0.1"]) == interface.EXIT_USAGE
    assert "--step 0.2 is larger than --max 0.1" in capsys.readouterr().err


@pytest.mark.parametrize("command", list(cli.COMMANDS))
def test_unwritable_output_is_exit_3_before_any_work(command, tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    out = blocker / "results"                       # a folder under a file: cannot be made
    extra = ["--path", "setpoint", "--n", "3"] if command == "track" else []
    assert cli.main([command, *extra, "--out", str(out)]) == interface.EXIT_OUTPUT
    err = capsys.readouterr().err
    assert err.strip() == f"jaxrkpm {command}: error: cannot write to {out}/: Not a directory"


def test_one_summary_line_and_the_exit_code_of_a_missed_goal(tmp_path, monkeypatch, capsys):
    """The cantilever study with its convergence faked to first order: it runs, writes, says
    so in one line and exits 1 (ran, goal missed); JSON only with --json."""
    from jaxrkpm.thesis.studies import cantilever
    fake = {"h": [0.25, 0.125], "relative_l2_error": [1e-2, 5e-3], "rates": [1.0]}
    monkeypatch.setattr(cantilever, "convergence", lambda hs: fake)
    assert cli.main(["cantilever", "--out", str(tmp_path)]) == interface.EXIT_GOAL
    out = capsys.readouterr().out.strip().splitlines()
    assert out == [f"wrote {tmp_path}/: convergence.png, run.json, summary.json; Timoshenko cantilever: relative "
                   "L2 errors 1.00e-02, 5.00e-03; rates 1.00 (expected >= 2, linear basis) [goal missed]"]
    assert json.loads((tmp_path / "summary.json").read_text()) == fake
    monkeypatch.setattr(cantilever, "convergence", lambda hs: {**fake, "rates": [2.0]})
    assert cli.main(["cantilever", "--json", "--out", str(tmp_path)]) == interface.EXIT_OK
    printed = capsys.readouterr().out
    assert json.loads(printed[:printed.index("wrote ")])["rates"] == [2.0]


def test_parser_choices_are_the_studies_own():
    from jaxrkpm.thesis.studies import compress, rig_sim

    def choices(command, option):
        return next(a.choices for a in interface.PARSERS[command]()._actions if option in a.option_strings)
    assert tuple(choices("compress", "--mode")) == tuple(compress.MODES)
    assert tuple(choices("compress", "--material")) == tuple(compress.MATERIALS)
    assert tuple(choices("rig-sim", "--path")) == tuple(rig_sim.RIG_PATHS)


# ------------------------------------------------------------------ words of the summary lines
def test_needle_static_says_which_paddles_stopped_and_why():
    from jaxrkpm.thesis.studies import needle
    row = ["converged"] * 3
    s = {"mode": "static", "inclusion": "none", "best": 3, "deviation": [0.02, 0.01, 0.001, 0.004, 0.006],
         "no_paddle_deviation": 0.014, "best_reduction": 14.0, "thesis": {"best": 4},
         "status": [row[:2] + ["inverted"], row, row, row[:2] + ["inverted"], row], "no_paddle_status": row}
    ok, words = needle.result(s)
    assert ok and "best paddle 3" in words and "14x less" in words
    assert "2 of 5 paddles (1, 4) stopped before full insertion (inverted: a step would invert" in words
    s["best"] = 1
    assert not needle.result(s)[0]          # the best paddle itself failed: goal missed


def test_rig_budget_cap_is_explained():
    from jaxrkpm.thesis.studies import rig_sim
    run = {"status": "DONE", "message": "", "iterations": 5, "waypoints": [{"reached_at": 0}, {"reached_at": 5}],
           "physical_error_mm": {"mean": 0.15, "max": 0.15}}
    budget = {"status": "ITERATION_CAP", "physical_error_mm": {"mean": 9.1, "max": 9.1}}
    s = {"path": "setpoint", "settings": {"tol_mm": 0.3, "budget": 1},
         "runs": {"uncorrected": {"tracking": run, "budget": budget}}}
    ok, words = rig_sim.result(s)
    assert ok and "2/2 waypoints within 0.3 mm (camera) in 5 iterations" in words
    assert "budget run, 1 iteration(s) per waypoint (a measure of the Jacobian, not a settling): mean physical " \
           "error 9.10 mm" in words
    run["physical_error_mm"] = {"mean": 3.0, "max": 9.08}       # tracked, but not settled within 1 mm
    ok, words = rig_sim.result(s)
    assert not ok and "physical error max 9.08 mm (thesis: settles within 1 mm)" in words


# ------------------------------------------------------------------ report.md of reproduce
def test_report_has_a_verdict_per_row_and_each_note_once():
    from jaxrkpm.thesis.studies import experiments, reproduce
    entries = {e.id: e for e in reproduce.ENTRIES}
    comp = {"fold_estimate": 0.44, "max_compression": 0.43}
    assert entries["compress_straight_gauss"].judge(comp) == ("agrees", "limit")
    assert entries["compress_straight_gauss"].judge({**comp, "fold_estimate": 0.19}) == ("differs", "limit point")
    assert entries["compress_straight_scni"].judge(comp) == ("differs", "scheme")
    track = {"waypoints_reached": 2, "waypoints_total": 2, "max_waypoint_error": 5e-5}
    assert entries["track_setpoint_gauss"].judge(track) == ("agrees", "tolerance")
    assert entries["track_setpoint_scni"].judge(track) == ("agrees in kind", "scheme")
    assert entries["track_box_gauss"].judge({**track, "waypoints_reached": 1}) == ("differs", "stopped")
    assert entries["track3d_refined"].judge(track) == ("agrees", "error")
    assert entries["needle_dynamic_none"].judge({"best": 3}) == ("agrees in kind", "phantom")
    assert entries["needle_dynamic_none"].judge({"best": 5}) == ("differs", "phantom")

    rows = []
    for i, (id_, verdict, reason) in enumerate([("track_setpoint_scni", "agrees in kind", "scheme"),
                                                 ("track_box_scni", "agrees in kind", "scheme"),
                                                 ("compress_straight_gauss", "differs", "limit point")]):
        e = entries[id_]
        rows.append({"id": id_, "thesis_ref": e.thesis_ref, "thesis_value": e.thesis_value, "note": e.note,
                     "ours": f"ours {i}", "verdict": verdict, "reason": reason, "wall_s": 1.0,
                     "figures": [f"{id_}/cp_path.png"], "status": "ok"})
    md = reproduce.report_md(rows, quick=False, total_s=60)
    assert "| verdict |" in md
    assert "| ours 0 | agrees in kind (scheme) [1] |" in md and "| ours 1 | agrees in kind (scheme) [1] |" in md
    assert "| ours 2 | differs (limit point) [2] |" in md and md.count(experiments.LIMIT) == 1
    assert md.count(experiments.COLL) == 1 and f"1. {experiments.COLL}" in md
    assert "Verdicts: agrees 0, agrees in kind 2, differs 1." in md
    ok, words = reproduce.result({"experiments": rows, "total_wall_s": 60})
    assert ok and words == "3/3 experiments ran in 1.0 min; verdicts: agrees 0, agrees in kind 2, differs 1 (report.md)"


# ------------------------------------------------------------------ figures
class FakePhantomModel:
    """Just what draw_phantom reads: particles, sets and an affine displacement field."""

    def __init__(self, X, grad):
        self.body = SimpleNamespace(X=X)
        self.grad = np.asarray(grad)

    def displacement(self, sol, P):
        return np.asarray(P) @ self.grad.T

    def particle_displacements(self, sol):
        return self.displacement(sol, self.body.X)

    def set_indices(self, name):
        return np.arange(3) if name == "needle" else np.arange(3, 6)


def test_phantom_drawing_keeps_particles_in_view_and_the_legend_off_them():
    from jaxrkpm.thesis import needle as nd
    from jaxrkpm.io import plot
    from jaxrkpm.thesis.studies import needle
    phantom = nd.Phantom()
    X = np.stack(np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 6)), -1).reshape(-1, 2)
    model = FakePhantomModel(X, [[0.3, 0.0], [0.0, 0.25]])     # stretches the body past x, y = 1.1
    fig, ax = plot.plt.subplots(layout="constrained")
    needle.draw_phantom(ax, phantom, model, None, "right")
    needle.legend_below(fig, ax)
    x = X + model.particle_displacements(None)
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    assert x0 <= x[:, 0].min() and x[:, 0].max() <= x1 and y0 <= x[:, 1].min() and x[:, 1].max() <= y1
    assert ax.get_legend() is None and len(fig.legends) == 1      # the legend is below, not over the body
    inclusion = next(l for l in ax.get_lines() if l.get_label().startswith("inclusion"))
    xy = np.asarray(inclusion.get_xydata())
    assert xy[:, 0].max() == pytest.approx(0.7 * 1.3) and xy[:, 1].max() == pytest.approx(0.4 * 1.25)  # deformed
    assert "model units" in ax.get_xlabel() and "model units" in ax.get_ylabel()
    plot.plt.close(fig)


# ------------------------------------------------------------------ hostile command lines (issue 35)
def one_line_usage(capsys, argv, *fragments):
    """The command exits 2 with one stderr line holding every fragment, and prints nothing."""
    assert cli.main(argv) == interface.EXIT_USAGE
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert "Traceback" not in captured.err and captured.out == "" and len(lines) == 1, lines
    assert lines[-1].startswith(f"jaxrkpm {argv[0]}: error: "), lines
    for f in fragments:
        assert f in lines[-1], (f, lines[-1])
    return lines[-1]


@pytest.mark.parametrize("argv, fragments", [
    (["track", "--max-iter", "1e20"], ["argument --max-iter: must be an integer in [1, 1e+06], got '1e20'"]),
    (["track", "--max-iter", "100000000000000000000"], ["argument --max-iter: must be an integer in [1, 1e+06]"]),
    (["track", "--max-steps", "10000000"], ["argument --max-steps: must be an integer in [1, 1e+06]"]),
    (["track", "--repeats", "1000"], ["argument --repeats: must be an integer in [1, 100]"]),
    (["cantilever", "--levels", "40"], ["argument --levels: must be an integer in [2, 6], got 40"]),
    (["needle", "--increments", "100000000"], ["argument --increments: must be an integer in [1, 1000]"]),
    (["needle", "--iterations", "1000000"], ["argument --iterations: must be an integer in [1, 10000]"]),
    (["needle3d", "--increments", "5000"], ["argument --increments: must be an integer in [1, 100]"]),
    (["rig-sim", "--seed", "-1"], ["argument --seed: must be an integer in [0, 4.29497e+09], got -1"]),
    (["rig-sim", "--noise", "1e9"], ["argument --noise: must be a number in [0, 255]"]),
])
def test_counts_are_bounded(argv, fragments, capsys):
    one_line_usage(capsys, argv, *fragments)


@pytest.mark.parametrize("command, choices", [
    ("compress", "'fung', 'fung-barrier', 'neo-hookean', 'neohookean'"),
    ("needle", "'fung', 'fung-barrier', 'neo-hookean'"),
    ("needle3d", "'neo-hookean', 'neohookean', 'fung', 'fung-barrier'"),
])
def test_an_unknown_material_lists_the_choices(command, choices, capsys):
    one_line_usage(capsys, [command, "--material", "rubber"],
                   f"argument --material: invalid choice: 'rubber' (choose from {choices})")


def test_sizes_past_the_memory_are_refused_before_allocating(capsys):
    line = one_line_usage(capsys, ["track", "--n", "100000"], "argument --n: 100000 makes 10,000,000,000 particles",
                          "GiB available", "the largest --n that fits is about")
    assert 3 <= int(line.rsplit("about ", 1)[1].split()[0]) < 100000
    one_line_usage(capsys, ["compress", "--n", "100000"], "argument --n: 100000 makes")
    one_line_usage(capsys, ["rig-sim", "--physical-n", "100000"], "argument --physical-n: 100000 makes")
    one_line_usage(capsys, ["compress", "--step", "1e-6"], "makes 900,000 compression steps, more than 1,000")
    one_line_usage(capsys, ["rig-sim", "--path", "setpoint", "--waypoints", "9"],
                   "argument --waypoints: the setpoint path has 2 waypoints, got 9")
    import jax
    many = str(len(jax.devices()) + 1)
    for command in ("needle", "needle3d"):
        one_line_usage(capsys, [command, "--devices", many], f"argument --devices: {many} asked, but JAX sees")


@pytest.mark.parametrize("command", list(cli.COMMANDS))
def test_an_empty_out_is_refused(command, capsys):
    one_line_usage(capsys, [command, "--out", ""], "argument --out: must name a folder, got ''")
    one_line_usage(capsys, [command, "--out", "  "], "argument --out: must name a folder")


def test_an_option_of_the_other_dimension_is_refused_not_ignored(capsys):
    one_line_usage(capsys, ["track", "--dim", "2", "--model", "refined"],
                   "--model applies to --dim 3 only (this run is --dim 2)")
    one_line_usage(capsys, ["track", "--dim", "2", "--mod", "refined", "--scheme", "self"],
                   "--model, --scheme apply to --dim 3 only")
    one_line_usage(capsys, ["track", "--dim", "3", "--n", "5"], "--n applies to --dim 2 only (this run is --dim 3)")


def test_a_patch_out_of_range_is_refused_before_any_folder(tmp_path, capsys):
    out = tmp_path / "never"
    one_line_usage(capsys, ["needle3d", "--paddle", "99", "--out", str(out)],
                   "argument --paddle: must be an integer in [1, 20] (the candidate patches), got 99")
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize("command, deepest", [("needle", "0.2"), ("needle3d", "0.4")])
def test_contact_paddle_options(command, deepest, tmp_path, capsys):
    """--paddle-model contact takes --friction and --indentation (glued stays the default);
    a negative friction, an indentation past two spacings, or either with the glued paddle
    is a one-line usage error before any folder is made."""
    a = interface.parse(command, ["--paddle-model", "contact", "--friction", "0.8", "--indentation", "0.02"])
    assert (a.paddle_model, a.friction, a.indentation) == ("contact", 0.8, 0.02)
    a = interface.parse(command, [])
    assert (a.paddle_model, a.friction, a.indentation) == ("glued", 0.3, None)
    out = tmp_path / "never"
    one_line_usage(capsys, [command, "--paddle-model", "contact", "--friction", "-1", "--out", str(out)],
                   "argument --friction: must be a number >= 0, got -1")
    one_line_usage(capsys, [command, "--paddle-model", "push"], "argument --paddle-model: invalid choice: 'push'")
    one_line_usage(capsys, [command, "--friction", "0.8", "--out", str(out)],
                   "--friction applies to the contact paddle only: add --paddle-model contact, or leave it out")
    one_line_usage(capsys, [command, "--fric", "0.8", "--indentation", "0.01", "--out", str(out)],
                   "--friction, --indentation apply to the contact paddle only")
    one_line_usage(capsys, [command, "--paddle-model", "contact", "--indentation", "0.5", "--out", str(out)],
                   f"argument --indentation: must be a number in [0, {deepest}] (two particle spacings",
                   "got 0.5")
    assert not out.exists()


def test_contact_summary_words():
    """The contact paddle's summary line: the paddle, the final deviation and the status; a
    contact force out of the cone misses the goal."""
    from jaxrkpm.thesis.studies import needle3d
    s = {"mode": "dynamic", "paddle_model": "contact", "friction": 0.8, "inclusion": "none", "paddle": 5,
         "final": 1.2e-4, "status": "not_held", "message": "the push-only paddle cannot reach the needle line",
         "contact_ok": True}
    ok, words = needle3d.result(s)
    assert not ok and words.startswith("needle3d dynamic (none, contact paddle, mu 0.8): paddle 5: final deviation "
                                       "1.20e-04; not_held")
    ok, words = needle3d.result({**s, "mode": "optimize", "status": "max_iterations", "message": "6 iterations"})
    assert ok
    ok, words = needle3d.result({**s, "mode": "static", "status": "converged", "message": "", "contact_ok": False})
    assert not ok and "a contact force left the cone" in words


def test_studies_that_fail_say_so():
    """A contact paddle sweep whose best paddle leaves the deviation as it was misses its goal;
    a sweep whose rows failed counts them by status and misses its goal (exit code 1)."""
    from jaxrkpm.thesis.studies import needle, sweep
    s = {"mode": "static", "paddle_model": "contact", "friction": 0.5, "inclusion": "right", "table": [],
         "deviation": [0.0688, 0.0690, np.nan], "no_paddle_deviation": 0.0688, "glued_only": [1, 2],
         "contact_ok": True}
    ok, words = needle.result(s)
    assert not ok and "deviation 0.0688 -> 0.0688" in words and "no contact paddle reduced the deviation" in words
    ok, words = needle.result({**s, "deviation": [0.03, 0.069, np.nan]})
    assert ok and "no contact paddle" not in words
    summary = {"configurations": 30, "chunks": 2, "skipped_chunks": 0, "evaluated_chunks": 2,
               "statuses": {"CONVERGED": 13, "INVERTED": 16, "MAX_ITERATIONS": 1}}
    ok, words = sweep.result(summary)
    assert not ok and words.endswith("; 17 of 30 rows failed (16 INVERTED, 1 MAX_ITERATIONS; their reasons are "
                                     "in table/'s reason column)")
    assert sweep.result({**summary, "statuses": {"CONVERGED": 30}})[0]


def test_every_option_shows_its_default():
    for command, make in interface.PARSERS.items():
        p = make()
        formatter = p._get_formatter()
        for action in p._actions:
            if not action.option_strings or action.nargs == 0:    # -h and on/off flags
                continue
            text = formatter._get_help_string(action)
            assert "default" in text, f"jaxrkpm {command} {action.option_strings[0]}: {text!r}"
    text = interface.track_parser().format_help()
    assert "(default 2000)" in " ".join(text.split()) and "(default 0.05)" in text


def fake_cantilever(monkeypatch, rates=(2.0,)):
    from jaxrkpm.thesis.studies import cantilever
    fake = {"h": [0.25, 0.125], "relative_l2_error": [1e-2, 2.5e-3], "rates": list(rates)}
    monkeypatch.setattr(cantilever, "convergence", lambda hs: fake)
    return cantilever


def test_a_folder_of_another_run_is_not_written_over(tmp_path, monkeypatch, capsys):
    out = tmp_path / "res"
    fake_cantilever(monkeypatch)
    assert cli.main(["cantilever", "--out", str(out)]) == interface.EXIT_OK
    assert cli.main(["cantilever", "--out", str(out)]) == interface.EXIT_OK       # the same run: replaced
    assert json.loads((out / "run.json").read_text())["options"] == {"levels": 3}
    capsys.readouterr()
    assert cli.main(["cantilever", "--levels", "2", "--out", str(out)]) == interface.EXIT_OUTPUT
    err = capsys.readouterr().err.strip()
    assert err == (f"jaxrkpm cantilever: error: {out}/ holds the results of another run (cantilever --levels 3; "
                   "this run: cantilever --levels 2): choose another --out, or pass --overwrite to replace them")
    assert cli.main(["cantilever", "--levels", "2", "--overwrite", "--out", str(out)]) == interface.EXIT_OK
    assert json.loads((out / "run.json").read_text())["options"] == {"levels": 2}
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "summary.json").write_text("my own notes")
    assert cli.main(["cantilever", "--out", str(mine)]) == interface.EXIT_OUTPUT
    assert "holds files that no jaxrkpm run wrote" in capsys.readouterr().err
    assert (mine / "summary.json").read_text() == "my own notes"
    (mine / "keep.txt").write_text("kept")
    assert cli.main(["cantilever", "--overwrite", "--out", str(mine)]) == interface.EXIT_OK
    assert (mine / "keep.txt").read_text() == "kept" and json.loads((mine / "summary.json").read_text())["rates"]


def test_a_failed_run_leaves_the_earlier_results(tmp_path, monkeypatch, capsys):
    cantilever = fake_cantilever(monkeypatch)
    out = tmp_path / "res"
    assert cli.main(["cantilever", "--out", str(out)]) == interface.EXIT_OK
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def broken(out, s):
        (out / "convergence.png").write_text("half a figure")
        raise RuntimeError("the figure failed")
    monkeypatch.setattr(cantilever, "figure", broken)
    with pytest.raises(RuntimeError, match="the figure failed"):
        cli.main(["cantilever", "--out", str(out)])
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]                  # no temporary folder left


def test_ctrl_c_is_one_line_that_says_what_was_kept(tmp_path, monkeypatch, capsys):
    """Ctrl-C ends with exit 130 and one line: a staged study keeps the earlier results (no
    traceback, no temporary folder); the sweep says its finished chunks are kept and resume."""
    cantilever = fake_cantilever(monkeypatch)
    out = tmp_path / "res"
    assert cli.main(["cantilever", "--out", str(out)]) == interface.EXIT_OK
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()

    def interrupted(out, s):
        raise KeyboardInterrupt
    monkeypatch.setattr(cantilever, "figure", interrupted)
    assert cli.main(["cantilever", "--out", str(out)]) == interface.EXIT_INTERRUPTED == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["jaxrkpm cantilever: interrupted; nothing was written (a run puts its folder in place when "
                   "it ends)"]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]

    from jaxrkpm.thesis import sweeps

    def sweep_interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(sweeps, "needle_sweep", sweep_interrupted)
    assert cli.main(["sweep", "--out", str(tmp_path / "sw")]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"jaxrkpm sweep: interrupted; the chunks finished so far are kept in "
                              f"{tmp_path / 'sw'}/table/")


def test_sweep_checks_where_it_runs_before_writing(tmp_path, monkeypatch, capsys):
    """A malformed or unreachable --executor, or --workers without Dask, ends at once with exit
    2 and writes nothing; changing only where the chunks run is the same sweep."""
    out = tmp_path / "sw"
    one_line_usage(capsys, ["sweep", "--executor", "localhost:8786", "--out", str(out)],
                   "--executor", "SCHEME://HOST:PORT", "got 'localhost:8786'")
    one_line_usage(capsys, ["sweep", "--executor", "tcp://127.0.0.1:1", "--out", str(out)],
                   "--executor: no Dask scheduler answers at tcp://127.0.0.1:1")
    import importlib.util
    find = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "distributed" else find(name, *a))
    one_line_usage(capsys, ["sweep", "--workers", "2", "--out", str(out)],
                   "--workers runs the chunks on Dask, which is not installed: pip install 'dask[distributed]'")
    assert not out.exists()
    monkeypatch.setattr(importlib.util, "find_spec", find)
    from jaxrkpm.thesis import sweeps
    from jaxrkpm.thesis.studies import sweep

    def fake_sweep(table, cfg, **k):
        (table / "chunk-0000000.parquet").parent.mkdir(parents=True, exist_ok=True)
        (table / "chunk-0000000.parquet").write_text(str(len(cfg["paddle"])))
        return SimpleNamespace(configurations=len(cfg["paddle"]), chunks=1, skipped=0, evaluated=1,
                               statuses={"CONVERGED": len(cfg["paddle"])})
    monkeypatch.setattr(sweeps, "needle_sweep", fake_sweep)
    monkeypatch.setattr(sweep, "_cluster", lambda args: (None, lambda: None))
    monkeypatch.setattr("jaxrkpm.sweeps.storage.read_sweep", lambda *a, **k: __import__("pyarrow").table(
        {"id": [0], "paddle": [1], "inclusion": ["right"], "stiffness_ratio": [1.0], "final_deviation": [0.1],
         "status": ["CONVERGED"]}))
    monkeypatch.setattr(interface, "unreachable", lambda address: None)
    assert cli.main(["sweep", "--paddles", "1", "2", "--workers", "2", "--out", str(out)]) == 0
    assert cli.main(["sweep", "--paddles", "1", "2", "--out", str(out)]) == 0            # in process: the same run
    assert cli.main(["sweep", "--paddles", "1", "2", "--executor", "tcp://h:1", "--out", str(out)]) == 0
    assert cli.main(["sweep", "--paddles", "1", "--out", str(out)]) == interface.EXIT_OUTPUT
    capsys.readouterr()
    # --overwrite with other options: the other sweep's table goes, the new run is recorded
    (out / "table" / "chunk-0000001.parquet").write_text("old")
    assert cli.main(["sweep", "--paddles", "1", "--overwrite", "--out", str(out)]) == 0
    assert sorted(p.name for p in (out / "table").iterdir()) == ["chunk-0000000.parquet"]
    assert json.loads((out / "run.json").read_text())["options"]["paddles"] == [1]
    assert cli.main(["sweep", "--paddles", "1", "--out", str(out)]) == 0                 # and it resumes


def test_help_names_no_internal_reference_and_bounds_the_gain(capsys):
    """Every command's help speaks to a user (no "the issue's" bound); rig-sim's gain is a
    fraction of the error (a gain of 100 ran long and reached almost nothing)."""
    import re
    for command in interface.PARSERS:
        text = interface.PARSERS[command]().format_help()
        assert not re.search(r"\bissue", text, re.I), (command, text)
    one_line_usage(capsys, ["rig-sim", "--gain", "100"], "--gain", "(0, 1]", "got 100")
    assert interface.parse("rig-sim", ["--gain", "1"]).gain == 1.0


def test_the_demo_line_counts_the_whole_run():
    from jaxrkpm.thesis.studies import track
    s = {"path": "box", "integration": "gauss", "particles": [9, 9], "dim": 2, "waypoints_reached": 4,
         "waypoints_total": 4, "max_waypoint_error": 9e-5, "tol": 1e-4, "iterations": 100, "wall_s": 1.0,
         "compile_s": 2.0, "total_s": 7.5, "status": "DONE"}
    ok, words = track.result(s)
    assert ok and "1.0 s warm + 2.0 s compile, 7.5 s in all with the model, figures and files" in words


def test_needle_modes_write_their_own_folders(tmp_path, monkeypatch, capsys):
    from jaxrkpm.thesis.studies import needle
    static = {"mode": "static", "inclusion": "none", "best": 3, "deviation": [0.02, 0.01, 0.001, 0.004, 0.006],
              "no_paddle_deviation": 0.014, "best_reduction": 14.0, "thesis": {"best": 4},
              "status": [["converged"]] * 5, "no_paddle_status": ["converged"]}
    optimum = {"mode": "optimize", "inclusion": "none", "optimum": {"q": 3.2, "deviation": 2e-3},
               "best_discrete": 3, "improvement_over_discrete": 0.5, "status": "max_iterations",
               "message": "the iteration budget ran out; the best iterate is returned"}
    monkeypatch.setattr(needle, "run_static", lambda *a: static)
    monkeypatch.setattr(needle, "run_optimize", lambda *a: optimum)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["needle"]) == interface.EXIT_OK
    assert cli.main(["needle", "--mode", "optimize"]) == interface.EXIT_GOAL
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("wrote results/needle/optimize_none/: run.json, summary.json; needle optimize (none)")
    assert "2.0x ABOVE the best discrete paddle 3; Adam max_iterations" in line and line.endswith("[goal missed]")
    assert json.loads(Path("results/needle/static_none/summary.json").read_text())["mode"] == "static"
    assert json.loads(Path("results/needle/optimize_none/summary.json").read_text())["mode"] == "optimize"


def test_compress_says_why_it_stopped_in_one_short_line():
    from jaxrkpm.thesis.studies import compress
    s = {"mode": "straight", "integration": "gauss", "particles": [9, 9], "material": {"name": "Fung"},
         "max_compression": 0.43, "max_stable_compression": 0.43, "critical_points": [],
         "reason": "Newton failure in the step to 44% (INVERTED); at the last converged sub-step, 43.20%, the "
                   "smallest tangent eigenvalue is ...; stable states (trust-region energy minima) end at\n43.2%",
         "steps": [{"compression": 0.43, "status": "CONVERGED"}, {"compression": 0.44, "status": "INVERTED"}],
         "stable_path_end": {"compression": 0.4321, "full": False, "collapse": True}, "fold_estimate": 0.44}
    ok, words = compress.result(s)
    assert ok and "\n" not in words and len(words) < 300
    assert words.endswith("stopped in the step to 44% (INVERTED), stable states end at 43.21% (the material "
                          "collapses: det F -> 0); limit point extrapolated at 44.0%")


def test_reuse_over_a_corrupt_report_is_a_named_error(tmp_path, capsys):
    from jaxrkpm.thesis.studies import reproduce
    out = tmp_path / "rep"
    out.mkdir()
    (out / "run.json").write_text(json.dumps({"command": "reproduce", "options": {"quick": True}, "files": []}))
    (out / "report.json").write_text("{ not json")
    assert cli.main(["reproduce", "--quick", "--reuse", "--out", str(out)]) == interface.EXIT_OUTPUT
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"jaxrkpm reproduce: error: cannot --reuse {out}/report.json: not a readable report "
                          "(JSONDecodeError: ") and "\n" not in err
    (out / "report.json").write_text(json.dumps({"experiments": [{"no id": 1}]}))
    with pytest.raises(interface.OutputError, match="KeyError"):
        reproduce.main(["--quick", "--reuse", "--out", str(out)])
