"""First contact (issue 13): fast first run, one statistics function, clear output, progress, good defaults."""

import io
import json
import re
import subprocess
import sys
from pathlib import Path

import numba as nb
import numpy as np
import pytest

import lensforge as lf
from lensforge.optics import trace
from lensforge.optics.jit import compile_notice
from lensforge.optics.shack_hartmann import ForwardModel


def test_cli_import_loads_no_heavy_module():
    code = ("import sys, lensforge.cli; "
            "print(' '.join(m for m in ('numba', 'scipy', 'matplotlib', 'trimesh', 'dask', 'cadquery') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == ""


def test_read_only_inputs_reuse_the_one_compiled_kernel(bench):
    lens = lf.paper_lens("zernike")
    fm = ForwardModel(bench, lens)
    targets = np.array(fm.pupil.centres)
    ro = targets.copy()
    ro.flags.writeable = False
    a = trace.aim_rays(bench, lens, np.zeros((2, 6)), targets, kernel=fm.kernel)
    b = trace.aim_rays(bench, lens, np.zeros((2, 6)), ro, u0=np.broadcast_to(targets, (2, len(targets), 2)),
                       kernel=fm.kernel)
    assert len(trace._aim.signatures) == 1
    np.testing.assert_array_equal(a[1], b[1])


def test_compile_notice_says_when_numba_compiles_and_stays_quiet_otherwise():
    @nb.njit
    def f(x):
        return x + 1

    buf = io.StringIO()
    with compile_notice("test kernel", stream=buf):
        f(1.0)
    first = buf.getvalue()
    assert first.startswith("compiling the test kernel") and first.rstrip().endswith(" s")
    assert first.count("\n") == 1
    buf2 = io.StringIO()
    with compile_notice("test kernel", stream=buf2):
        f(2.0)  # already compiled
    assert buf2.getvalue() == ""


# ----------------------------------------------------------------------------- statistics

def test_one_percentile_method_failures_count_as_worst():
    from lensforge.verification.statistics import error_stats, percentile

    v = [0.744, 1.03, 0.2, 5.0]
    # method "higher": an order statistic, never an interpolation between two trials
    assert percentile(v, 50) == 1.03
    assert percentile(v, 100) == 5.0
    assert percentile([1.0, np.nan, 2.0, 3.0], 100) is None  # a failed trial decides the max
    assert percentile([], 50) is None
    s = error_stats([1.0, 2.0, 3.0, np.inf], 95)
    assert s == {"median": 3.0, "p95": None, "max": None}


def test_study_summary_and_histogram_lines_agree(monkeypatch):
    from lensforge.plots import study as study_plots
    from lensforge.verification.statistics import format_counts, percentile
    from lensforge.verification.study import summarize_errors

    tr = [0.5, 0.744, 1.03, 1.4]
    recs = [{"ok": True, "rot_err_deg": 0.1 * (i + 1), "trans_err_mm": t, "bias": [0.0] * 6} for i, t in enumerate(tr)]
    recs.append({"ok": False, "failure": "pupil lost: x", "n_pupil_lost": 3})
    s = summarize_errors(recs, 0.1, 0.01, 95.0)
    assert s["translation_mm"]["median"] == percentile(tr + [np.inf], 50) == 1.03
    assert "1 of 5 lenses failed (pupil lost 1)" in format_counts(s)
    assert "3 lost the pupil, 0 did not converge, 0 out of the sensor's range" in format_counts(s)
    figs = []
    monkeypatch.setattr(study_plots, "save_figure", lambda fig, path: figs.append(fig) or path)
    study_plots.plot_error_histograms([0.1, 0.2, 0.3, 0.4, np.nan], tr + [np.nan], "x.png", 0.01, 0.1)
    ax = figs[0].axes[1]
    medians = [ln.get_xdata()[0] for ln in ax.get_lines() if ln.get_linestyle() == "-" and ln.get_color() == "k"]
    assert medians == [s["translation_mm"]["median"]]


# ----------------------------------------------------------------------------- output

def test_unobservable_has_one_spelling_and_columns_carry_units():
    from lensforge.display import UNOBSERVABLE, crlb_cells, crlb_columns, fmt_bound

    assert fmt_bound(None) == fmt_bound(float("inf")) == fmt_bound(3.0, unobservable=True) == UNOBSERVABLE
    assert fmt_bound(3.06) == "3.06"
    assert all(c.endswith("(um)") or c.endswith("(urad)") for c in crlb_columns())
    std = {"tx_um": 3.0, "ty_um": 2.0, "tz_um": 1.0, "rx_urad": 10.0, "ry_urad": 20.0, "rz_urad": 1.85e5}
    cells = crlb_cells(std, pose_scales=(1.0, 1.0, 1.0) + (np.radians(1.0),) * 3)
    assert cells[-1] == UNOBSERVABLE and cells[0] == "3"


def test_lens_labels_tell_paper_lenses_from_design_files(tmp_path, bench):
    from lensforge.optics.lens import resolve_lens

    f = tmp_path / "zernike.json"
    f.write_text(json.dumps({"schema_version": 1, "kind": "lensforge.design", "lens": lf.paper_lens("zernike").to_dict()}))
    assert resolve_lens("zernike").label != resolve_lens(str(f)).label == "zernike"


def test_budget_advice_suggests_relative_target_when_noise_alone_misses():
    from lensforge.commands.study import budget_advice
    from lensforge.verification.budget import Budget

    bud = Budget((), 3.2, None, 0.1, 0.01, 95.0, 8, 0)
    text = " ".join(budget_advice(bud))
    assert "--relative-to-noise" in text and "3.2x" in text
    assert "None" not in " ".join(budget_advice(Budget((), 0.5, None, 0.1, 0.01, 95.0, 8, 0)))
    assert budget_advice(Budget((), 0.5, "index", 0.1, 0.01, 95.0, 8, 0))[0].startswith("dominant: index")


def test_infeasibility_is_explained_in_words(bench):
    from lensforge.design.compare import compare_rows, feasibility_notes

    rows = compare_rows(["paper:zernike"], bench)
    notes = feasibility_notes(rows)
    assert rows[0]["violations"] == ["pupil_lit"] and len(notes) == 1
    assert "cannot be measured" in notes[0] and "--range-mm" in notes[0]


# ----------------------------------------------------------------------------- progress and defaults

def test_estimation_study_ticks_once_per_trial(bench):
    from lensforge.verification.estimation_study import study_lens

    ticks = []
    study_lens(bench, lf.paper_lens("polynomial"), "p", trials=3, seed=1, tick=lambda: ticks.append(1))
    assert len(ticks) == 3


def test_disabled_progress_bar_prints_nothing(capsys):
    from lensforge.progress import progress_bar

    with progress_bar(3, "x", enabled=False) as bar:
        bar.advance()
        bar.describe("y")
    assert capsys.readouterr() == ("", "")


def test_progress_bar_into_a_pipe_prints_nothing():
    # stderr not a terminal (a pipe, a log file): no bar, and no empty line left where it was
    import subprocess
    import sys

    prog = ("from lensforge.progress import progress_bar\n"
            "with progress_bar(3, 'x') as bar:\n    bar.advance()\n    bar.describe('y')\n")
    out = subprocess.run([sys.executable, "-c", prog], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout == "" and out.stderr == "", out


def test_design_defaults_are_the_good_recipe():
    import inspect

    from lensforge.design.optimize import optimize_design
    from lensforge.design.parameterisation import DEFAULT_PRESET

    sig = inspect.signature(optimize_design).parameters
    assert sig["method"].default == "cmaes" and sig["criterion"].default == "A"
    assert DEFAULT_PRESET["zernike"] == "full"


@pytest.mark.slow
def test_default_zernike_design_is_the_good_lens(bench):
    """`lensforge design --model zernike --seed 0`: all six DOF observable, CRLB <= 1 mrad and <= 10 um."""
    from lensforge.design.optimize import optimize_design

    d = optimize_design(bench, model="zernike", seed=0, progress=False)
    m = d.compute_metrics(bench)
    assert m.rank == 6
    assert np.all(m.crlb_std <= np.asarray(bench.pose_scales))  # DESIGN.md's observability rule
    assert np.all(m.crlb_std[:3] <= 0.010) and np.all(m.crlb_std[3:] <= 1e-3)


@pytest.mark.parametrize("command", ["design", "budget", "estimate-study", "scenario", "study"])
def test_long_commands_have_no_progress_and_flags_show_no_bool_metavar(command):
    from typer.testing import CliRunner

    from lensforge.cli import app

    r = CliRunner().invoke(app, [command, "--help"], terminal_width=200)
    assert r.exit_code == 0
    assert "--no-progress" in r.output and "<bool>" not in r.output


# ----------------------------------------------------------------------------- README commands

_README = Path(__file__).resolve().parents[1] / "README.md"


def _readme_blocks(lang):
    text = _README.read_text()
    return re.findall(rf"```{lang}\n(.*?)```", text, flags=re.S)


def _readme_commands():
    """Every `lensforge ...` command of the README: code-block lines and inline `lensforge ...` spans
    (the command table's synopses, with [optional] parts and | alternatives, are not commands)."""
    cmds = []
    for block in _readme_blocks("bash"):
        for line in block.splitlines():
            line = line.split("#", 1)[0].strip()
            if line.startswith("lensforge "):
                cmds.append(line)
    for line in _README.read_text().splitlines():
        if line.startswith("|"):
            continue
        cmds += [c for c in re.findall(r"`(lensforge [^`]+)`", line) if "[" not in c and "|" not in c and "..." not in c]
    return cmds


def test_readme_commands_parse():
    """Each README command names a real command and options it takes, with valid values."""
    import shlex

    import typer

    from lensforge.cli import app

    group = typer.main.get_command(app)
    cmds = _readme_commands()
    assert len(cmds) >= 10 and any(c.startswith("lensforge budget") for c in cmds)
    for line in cmds:
        args = shlex.split(line)[1:]
        ctx = group.make_context("lensforge", args[:1])
        cmd = group.get_command(ctx, args[0])
        assert cmd is not None, line
        cmd.make_context(args[0], args[1:], parent=ctx)  # raises on an unknown option or a bad value


def test_readme_library_example_runs(tmp_path, monkeypatch):
    (code,) = _readme_blocks("python")
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {})
    assert (tmp_path / "zernike.optiland.json").stat().st_size > 0


def test_command_list_summaries_are_whole_sentences():
    """`lensforge --help` lists every command with its one-line summary, never cut off with '...'."""
    from typer.testing import CliRunner

    from lensforge.cli import app

    r = CliRunner().invoke(app, ["--help"], terminal_width=80)
    assert r.exit_code == 0 and "..." not in r.output.split("Commands:")[1]
