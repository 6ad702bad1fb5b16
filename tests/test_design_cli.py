"""CLI: design, plot, compare (happy path and one-line errors)."""

import json

import pytest
from conftest import run_cli as run


def test_design_plot_compare_evaluate(tmp_path):
    out = tmp_path / "exports" / "e.json"
    r = run("design", "--model", "extended_polynomial", "--method", "cmaes", "--seed", "1", "--max-evals", "20",
            "--start", "random", "--bench", "paper", "-o", str(out), "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["n_evals"] <= 20 and summary["metrics"]["rank"] == 6
    assert json.loads(out.read_text())["lens"]["front"]["kind"] == "extended_polynomial"
    r = run("plot", str(out), "-o", str(tmp_path / "png"), "--json")
    assert r.returncode == 0, r.stderr
    files = json.loads(r.stdout)["files"]
    kinds = {f.rsplit("/", 1)[-1][len("e_"):-len(".png")] for f in files}
    assert kinds == {"singular_values", "sag", "zernike_response", "footprint", "lenslet_field", "cross_section",
                     "bench_layout", "convergence"}
    assert summary["bench"]["pupil_radius_mm"] == 0.9 and summary["bench"]["expander"] == "none"  # --bench paper
    r = run("compare", str(out), "paper:spherical", "paper:zernike", "--json")
    assert r.returncode == 0, r.stderr
    rows = json.loads(r.stdout)["rows"]
    assert [row["rank"] for row in rows] == [6, 5, 6]
    assert rows[0]["n_evals"] == summary["n_evals"] and rows[1]["crlb_std"]["rz_urad"] is None
    r = run("evaluate", str(out), "--json")
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize(
    "args, fragment",
    [
        (("design", "--model", "aspheric-blob"), "unknown design model"),
        (("design", "--method", "annealing"), "unknown optimiser"),
        (("design", "--bounds", "thickness=9:2"), "lo < hi"),
        (("design", "--bounds", "thickness"), "name=lo:hi"),
        (("plot", "missing.json"), "not found"),
        (("compare", "paper:nonesuch"), "unknown paper lens"),
    ],
)
def test_design_cli_errors_one_line(tmp_path, args, fragment):
    r = run(*args, cwd=tmp_path)
    assert r.returncode != 0
    lines = [l for l in r.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and fragment in lines[0], r.stderr


def test_unreadable_design_file(tmp_path):
    p = tmp_path / "broken.json"
    p.write_text("[1, 2")
    r = run("compare", str(p))
    assert r.returncode != 0 and r.stderr.strip().startswith("error:") and "not valid JSON" in r.stderr
