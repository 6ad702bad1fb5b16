import json

import pytest
from conftest import run_cli as run


def test_evaluate_json():
    r = run("evaluate", "spherical", "zernike", "--json")
    assert r.returncode == 0, r.stderr
    data = json.loads(r.stdout)
    rows = {row["lens"]: row for row in data["lenses"]}
    assert rows["spherical"]["rank"] == 5
    assert rows["spherical"]["crlb_std"]["rz_urad"] is None  # unobservable
    assert rows["zernike"]["rank"] == 6
    assert set(rows["zernike"]["crlb_std"]) == {"tx_um", "ty_um", "tz_um", "rx_urad", "ry_urad", "rz_urad"}


@pytest.mark.parametrize(
    "args, fragment",
    [
        (("evaluate", "nonesuch"), "neither a paper lens"),
        (("evaluate", "zernike", "--bench", "missing.toml"), "not found"),
    ],
)
def test_evaluate_errors_one_line(args, fragment):
    r = run(*args)
    assert r.returncode != 0
    lines = [l for l in r.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and fragment in lines[0], r.stderr


def test_evaluate_bad_bench_value(tmp_path):
    b = tmp_path / "bench.toml"
    b.write_text("[sensor]\npupil_radius_mm = -1\n")
    r = run("evaluate", "zernike", "--bench", str(b))
    assert r.returncode == 2
    assert r.stderr.strip().startswith("error: bench.toml:bench.sensor.pupil_radius_mm")  # names the file
