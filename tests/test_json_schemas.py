"""Every --json output has a documented schema; every command's real output validates against it.

Each command that has ``--json`` runs here once, in this process (the traced kernels are
shared), on the smallest inputs that still produce every key, and its stdout is checked
against ``lensforge/schemas/<command>.schema.json``: it must validate, and every key it
carries must be documented (a key added to an output without a schema entry fails)."""

import inspect
from pathlib import Path

import pytest
from conftest import run_cli_inprocess

jsonschema = pytest.importorskip("jsonschema")

from lensforge.cli import _COMMANDS  # noqa: E402
from lensforge.schemas import COMMANDS, load_schema, render_markdown, resolve_ref  # noqa: E402

LENS = "extended_polynomial"  # paper lens with every DOF observable (the bench commands need one)


def test_every_json_command_has_a_valid_schema():
    with_json = {name for name, fn in _COMMANDS.items() if "json_out" in inspect.signature(fn).parameters}
    assert set(COMMANDS) == with_json, set(COMMANDS) ^ with_json
    tested = set(CASES) | set(BENCH_CHAIN) | SLOW
    assert tested == with_json, tested ^ with_json
    for c in COMMANDS:
        s = load_schema(c)
        jsonschema.Draft202012Validator.check_schema(s)
        assert s["title"] == f"lensforge {c} --json" and s["required"]
        assert "schema_version" in s["required"], c


def test_docs_are_rendered_from_the_schemas():
    doc = Path(__file__).resolve().parents[1] / "docs" / "json.md"
    assert doc.read_text() == render_markdown(), "docs/json.md is stale: regenerate with lensforge.schemas.render_markdown()"


def undocumented(data, schema, root=None, path=""):
    """Keys in ``data`` that its schema does not name (objects with named properties only;
    maps such as ``files`` or ``crlb_std`` are described as a whole)."""
    root = schema if root is None else root
    schema = resolve_ref(schema, root)
    out = []
    if isinstance(data, dict):
        props = schema.get("properties") or {}
        extra = schema.get("additionalProperties")
        for k, v in data.items():
            if k in props:
                out += undocumented(v, props[k], root, f"{path}.{k}")
            elif isinstance(extra, dict):
                out += undocumented(v, extra, root, f"{path}.<{k}>")
            elif props:
                out.append(f"{path}.{k}")
    elif isinstance(data, list) and isinstance(schema.get("items"), dict):
        for v in data[:1]:
            out += undocumented(v, schema["items"], root, f"{path}[]")
    return out


def test_undocumented_keys_are_found():
    s = load_schema("calibrate")
    assert undocumented({"Z": {"matrix": [], "extra": 1}, "new": 2}, s) == [".Z.extra", ".new"]


def check(command, args, monkeypatch, capsys):
    """Run ``lensforge COMMAND ARGS --json`` in this process; its stdout validates and is documented."""
    import json

    code, out, err = run_cli_inprocess(monkeypatch, capsys, command, *args, "--json")
    assert code == 0, err
    data = json.loads(out)
    schema = load_schema(command)
    jsonschema.validate(data, schema)
    assert not undocumented(data, schema), f"{command} --json: keys missing from its schema: {undocumented(data, schema)}"
    return data


# command -> its arguments (t: a fresh output folder); small sizes, every key present
CASES = {
    "evaluate": lambda t: ["spherical", LENS],
    "design": lambda t: ["--model", LENS, "--max-evals", "20", "-o", t / "d.json"],
    "plot": lambda t: ["zernike", "-o", t],
    "compare": lambda t: ["paper:spherical", f"paper:{LENS}"],
    "export": lambda t: ["spherical", "--stl", "--chord-tol", "0.02", "--no-slicer", "-o", t],
    "estimate-study": lambda t: [LENS, "--trials", "2", "-o", t],
    "scenario": lambda t: [LENS, "--runs", "1", "--poses", "oed", "-o", t],
    "handeye": lambda t: [Path(__file__).resolve().parents[1] / "examples" / "handeye_poses.json"],
    "plan": lambda t: [LENS, "-n", "4", "-o", t],
    "study": lambda t: [LENS, "--lenses", "2", "--poses", "8", "--workers", "0", "--calibration", "two-stage", "-o", t],
}
BENCH_CHAIN = ("simulate-session", "estimate", "calibrate")  # one session, in test_bench_chain_outputs
SLOW = {"budget"}  # a budget bisects every tolerance component: minutes even at 2 lenses


@pytest.mark.parametrize("command", sorted(CASES))
def test_real_output_validates_and_is_documented(command, tmp_path, monkeypatch, capsys):
    check(command, CASES[command](tmp_path / "out"), monkeypatch, capsys)


def test_bench_chain_outputs(tmp_path, monkeypatch, capsys):
    """simulate-session writes the files that estimate and calibrate (two-stage, the fast method) read."""
    d = check("simulate-session", [LENS, "-t", "none", "-n", "5", "-o", tmp_path / "s"], monkeypatch, capsys)
    f = d["files"]
    check("estimate", [LENS, "-m", f["wfs_zernike.csv"], "--pose", d["poses"][0]], monkeypatch, capsys)
    c = check("calibrate", [LENS, "-m", f["wfs_zernike.csv"], "-r", f["robot_poses.csv"], "--method", "two-stage",
                            "-o", tmp_path / "c"], monkeypatch, capsys)
    assert c["poses_used"] == d["poses"] and set(c["Z"]["std"]) == {"tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg",
                                                                    "rz_deg"}


@pytest.mark.slow
def test_budget_output_validates_and_is_documented(tmp_path, monkeypatch, capsys):
    check("budget", [LENS, "--lenses", "2", "--poses", "8", "--workers", "0", "--relative-to-noise", "3",
                     "-o", tmp_path], monkeypatch, capsys)


def test_budget_library_output_validates():
    """The fast stand-in for the slow CLI budget run: the dict budget --json prints, from the library types."""
    from lensforge.verification.budget import Budget, BudgetRow, SensitivityRow

    rows = (BudgetRow("index", 0.5, 1e-4, 2e-4, "1", 1.0, "ok", ((1.0, 2.0),)),)
    bud = Budget(rows, 0.3, "index", 0.1, 0.01, 95.0, 4, 0)
    fields = [f for f in SensitivityRow.__dataclass_fields__]
    sens = SensitivityRow(**{f: (0.1 if f != "component" else "all") for f in fields})
    d = {"schema_version": 1, "design": "x.json", "calibration": "two-stage", **bud.to_dict(),
         "sensitivity": [sens.to_dict()], "tolerances": {}}
    jsonschema.validate(d, load_schema("budget"))
    assert not undocumented(d, load_schema("budget"))


def test_calibrate_joint_keys_are_documented():
    """The joint method's own keys (lens parameters, model check) are in the schema too."""
    s = load_schema("calibrate")["properties"]
    for k in ("tolerances", "p_value", "lens_parameters", "Z_std_known_lens", "iterations", "converged"):
        assert k in s, k


def test_export_report_validates(tmp_path):
    import lensforge as lf
    from lensforge.manufacturing.report import export_lens

    rep = export_lens(lf.paper_lens("spherical"), tmp_path, "s", stl=True, step=False, layer_mm=0.1,
                      chord_tol_mm=0.01, run_slicer=False)
    jsonschema.validate(rep.to_dict(), load_schema("export"))
    bad = rep.to_dict()
    del bad["checks"]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, load_schema("export"))
