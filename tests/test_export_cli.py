"""``lensforge export``: files, report keys, and one-line errors."""

import json

import pytest
from conftest import run_cli

from lensforge.manufacturing.slicer import find_prusa_slicer


def run(*args):
    return run_cli("export", *args)


def test_export_stl_step_report(tmp_path):
    out = tmp_path / "exports"
    r = run("zernike", "--stl", "--step", "--fiducial", "--tab", "--edge-diameter", "28", "--layer", "100",
            "--chord-tol", "0.005", "-o", str(out), "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["ok"] and rep["schema_version"] == 1
    m = rep["mesh"]
    assert m["watertight"] and m["manifold_status"] == "NoError" and m["genus"] == 0
    assert m["chord_error_mm"] <= 0.005 and m["triangles"] > 0
    assert rep["printer"]["fits"] and len(rep["printer"]["bounding_box_mm"]) == 2
    assert rep["step"]["max_deviation_mm"] <= 1e-5 and abs(rep["step"]["reimport_volume_rel_error"]) <= 1e-6
    expect = "ok" if find_prusa_slicer() else "not available"
    assert rep["slicer"]["verdict"] == expect
    for f in ("zernike.stl", "zernike.step", "zernike.report.json"):
        assert (out / f).stat().st_size > 0
    assert json.loads((out / "zernike.report.json").read_text())["mesh"] == m
    assert "chord error" in r.stderr and "fits the Formlabs Form 2: yes" in r.stderr
    assert not list(out.glob(".*.tmp"))


@pytest.mark.parametrize("args, fragment", [
    (("zernike", "--layer", "30"), "layer"),
    (("zernike", "--fiducial", "--flange", "0"), "edge_diameter"),
    (("zernike", "--flange", "-1"), "--flange"),
    (("zernike", "--chord-tol", "-1"), "--chord-tol"),
    (("zernike", "--fiducial", "--fiducial-kind", "hole"), "--fiducial-kind"),
    (("no-such-design.json",), "no-such-design.json"),
])
def test_bad_arguments_one_line_error(tmp_path, args, fragment):
    r = run(*args, "-o", str(tmp_path / "x"), "--no-slicer")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and fragment in lines[0]
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())


def test_export_3mf_round_trip(tmp_path):
    import trimesh

    import lensforge as lf
    from lensforge.manufacturing.report import export_lens

    rep = export_lens(lf.paper_lens("zernike"), tmp_path, "z", stl=True, step=False, run_slicer=False, threemf=True)
    assert rep.threemf_path.exists() and rep.to_dict()["files"]["3mf"].endswith("z.3mf")
    m = trimesh.load(rep.threemf_path, force="mesh")
    assert m.is_watertight
    assert abs(m.volume - rep.stl.volume_mm3) / rep.stl.volume_mm3 < 1e-9
