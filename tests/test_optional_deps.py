"""`pip install lensforge` calibrates a robot without the mesh/CAD stack (the `export` extra).

Each check runs in a fresh interpreter in which cadquery, OCP, vtk (and, where said, trimesh and
manifold3d) cannot be imported (``sys.modules[name] = None``: any import of them raises
ImportError), as on a lab PC that installed lensforge without extras.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CAD = ("cadquery", "OCP", "vtk", "vtkmodules")
MESH = ("trimesh", "manifold3d")
LENS = "extended_polynomial"  # a paper freeform lens: rank 6, fast to trace


def _python(code: str, blocked, cwd, timeout=600):
    prelude = f"import sys\nfor _m in {tuple(blocked)!r}:\n    sys.modules[_m] = None\n"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "LENSFORGE_NO_SUPERVISOR": "1"}
    return subprocess.run([sys.executable, "-c", prelude + code], capture_output=True, text=True, cwd=cwd, env=env,
                          timeout=timeout)


def _cli(*args, blocked, cwd):
    code = f"import runpy\nsys.argv = ['lensforge', *{list(map(str, args))!r}]\nrunpy.run_module('lensforge', run_name='__main__')\n"
    return _python(code, blocked, cwd)


def test_plan_simulate_calibrate_without_the_export_stack(tmp_path):
    code = f"""
import json
from lensforge.cli import main
codes = {{}}
for name, args in [
    ("plan", ["plan", "{LENS}", "-n", "8", "-o", "plan"]),
    ("simulate-session", ["simulate-session", "{LENS}", "-t", "none", "--seed", "2", "-n", "8", "-o", "s"]),
    ("calibrate", ["calibrate", "{LENS}", "--measurements", "s/wfs_zernike.csv", "--robot-poses",
                   "s/robot_poses.csv", "-o", "c"]),
]:
    sys.argv = ["lensforge", *args]
    try:
        main()
        codes[name] = 0
    except SystemExit as e:
        codes[name] = e.code or 0
print(json.dumps(codes))
"""
    r = _python(code, CAD + MESH, tmp_path)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1]) == {"plan": 0, "simulate-session": 0, "calibrate": 0}, r.stderr
    assert (tmp_path / "plan" / "plan.json").exists() and (tmp_path / "c" / "calibration.json").exists()


def test_step_export_without_the_cad_stack_is_one_line(tmp_path):
    r = _cli("export", LENS, "--step", "-o", "out", "--no-progress", blocked=CAD, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr == "error: STEP export needs the CAD stack: pip install 'lensforge[export]'\n"
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())  # nothing half-written


def test_stl_export_without_the_mesh_stack_is_one_line(tmp_path):
    r = _cli("export", LENS, "--stl", "-o", "out", "--no-progress", blocked=CAD + MESH, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr == "error: STL/3MF export needs trimesh and manifold3d: pip install 'lensforge[export]'\n"
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_import_and_help_load_no_export_stack(tmp_path):
    code = """
import lensforge as lf
lf.Bench.default(); lf.paper_lens("zernike"); lf.export_stl; lf.FeatureSpec
from lensforge.cli import main
sys.argv = ["lensforge", "--help"]
try:
    main()
except SystemExit as e:
    assert not e.code, e.code
sys.argv = ["lensforge", "export", "--help"]
try:
    main()
except SystemExit as e:
    assert not e.code, e.code
heavy = sorted({m.split(".")[0] for m in sys.modules} & {"cadquery", "OCP", "vtk", "vtkmodules"})
print("HEAVY", heavy)
"""
    r = _python(code, (), tmp_path)  # nothing blocked: the export stack is installed, and must stay unloaded
    assert r.returncode == 0, r.stderr
    assert "HEAVY []" in r.stdout
    r = _cli("--help", blocked=CAD + MESH, cwd=tmp_path)
    assert r.returncode == 0 and "calibrate" in r.stdout, r.stderr


def test_base_dependencies_do_not_bring_the_export_stack():
    """pyproject: the CAD and mesh stack is the `export` extra, and `make` installs it; the base
    requirements' closure (as installed here) holds none of it."""
    import tomllib
    from importlib import metadata

    from packaging.requirements import Requirement

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    heavy = {"cadquery", "cadquery-ocp", "vtk", "trimesh", "manifold3d"}
    base = [Requirement(r) for r in project["dependencies"]]
    assert not {r.name.lower() for r in base} & heavy
    assert heavy - {"cadquery-ocp", "vtk"} <= {Requirement(r).name.lower() for r in project["optional-dependencies"]["export"]}
    assert '".[export,test,bench]"' in (ROOT / "Makefile").read_text()
    seen, todo = set(), list(base)
    while todo:
        req = todo.pop()
        name = req.name.lower().replace("_", "-")
        if name in seen:
            continue
        seen.add(name)
        try:
            requires = metadata.distribution(req.name).requires or []
        except metadata.PackageNotFoundError:
            continue
        todo += [r for r in map(Requirement, requires) if r.marker is None or r.marker.evaluate({"extra": ""})]
    assert not seen & heavy, sorted(seen & heavy)
