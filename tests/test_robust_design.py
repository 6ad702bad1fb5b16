"""Tolerance-robust design: robust cost, common random numbers, reproducibility, design file, CLI."""

import json

import numpy as np
import pytest

import lensforge as lf
from lensforge.design import robust as robust_mod
from lensforge.design.design_file import load_design, save_design
from lensforge.design.optimize import DesignProblem, optimize_design
from lensforge.design.parameterisation import parameterisation
from lensforge.design.robust import FAIL_VALUE, RobustSpec, compare_robust, robust_value
from lensforge.errors import ConfigError
from lensforge.asbuilt.tolerances import (
    DEFAULT_TOLERANCES_FILE,
    Tolerances,
    load_tolerances,
    scale_canonical,
)


@pytest.fixture(scope="module")
def setup():
    bench = lf.Bench.default()
    par = parameterisation("zernike", free="full")
    prob = DesignProblem(bench, par, "A")
    p = par.from_unit(prob.random_feasible_start(np.random.default_rng(0)))
    return bench, par, p, load_tolerances(DEFAULT_TOLERANCES_FILE)


def test_zero_tolerances_robust_cost_equals_nominal(setup):
    bench, par, p, _ = setup
    nominal = DesignProblem(bench, par, "A").evaluate_p(p)[0]
    assert nominal < 1e3
    for stat in ("mean", "max", "mean+std"):
        prob = DesignProblem(bench, par, "A", robust=RobustSpec(Tolerances.zero(), n_samples=3, statistic=stat))
        assert prob.evaluate_p(p)[0] == nominal
    rv = robust_value(bench, par.to_lens(p), RobustSpec(Tolerances.zero(), 3), "A")
    assert rv.n_failed == 0 and rv.nominal == nominal and np.all(rv.values == nominal)


def test_robust_cost_reproducible_and_finite_on_failure(setup):
    bench, par, p, tol = setup
    spec = RobustSpec(tol, n_samples=4, seed=3)
    a = DesignProblem(bench, par, "A", robust=spec).evaluate_p(p)[0]
    b = DesignProblem(bench, par, "A", robust=RobustSpec(tol, n_samples=4, seed=3)).evaluate_p(p)[0]
    c = DesignProblem(bench, par, "A", robust=RobustSpec(tol, n_samples=4, seed=4)).evaluate_p(p)[0]
    assert a == b and a != c
    # absurd tolerances: draws become unmeasurable -> large finite penalty, never an exception
    wild = Tolerances(form_rms_mm=0.5, thickness_sigma_mm=3.0)
    rv = robust_value(bench, par.to_lens(p), RobustSpec(wild, n_samples=4), "A")
    assert rv.n_failed > 0 and np.isfinite(rv.cost) and rv.values.max() == FAIL_VALUE


def test_common_random_numbers_across_candidates(setup, monkeypatch):
    bench, par, p1, tol = setup
    p2 = p1.copy()
    i = par.names.index("front.coefficients[3]")
    p2[i] += 0.05  # another candidate, same thickness
    calls = []
    real = robust_mod.sample_as_built

    def recording(lens, tolerances, rng, validate=True):
        state = rng.bit_generator.state
        ab = real(lens, tolerances, rng, validate=validate)
        calls.append((state, lens, ab))
        return ab

    monkeypatch.setattr(robust_mod, "sample_as_built", recording)
    prob = DesignProblem(bench, par, "A", robust=RobustSpec(tol, n_samples=5, seed=11))
    c1 = prob.evaluate_p(p1)[0]
    first = list(calls)
    calls.clear()
    c2 = prob.evaluate_p(p2)[0]
    second = list(calls)
    assert len(first) == len(second) == 5 and c1 != c2
    # the same generator states, distinct across the draws
    assert [s for s, _, _ in first] == [s for s, _, _ in second]
    assert len({json.dumps(s, sort_keys=True, default=str) for s, _, _ in first}) == 5

    def perturbation(nom, ab):
        s = ab.aperture / nom.aperture
        out = [s, ab.thickness - nom.thickness * s, ab.index_offset - nom.index_offset]
        for side in ("front", "back"):
            cs_ab, cs_nom = getattr(ab, side).canonical(), scale_canonical(getattr(nom, side).canonical(), s)
            n = max(cs_ab.poly.shape[0], cs_nom.poly.shape[0])
            d = np.zeros((n, n))
            d[: cs_ab.poly.shape[0], : cs_ab.poly.shape[1]] += cs_ab.poly
            d[: cs_nom.poly.shape[0], : cs_nom.poly.shape[1]] -= cs_nom.poly
            out.append(d)
            out.append(cs_ab.alpha - cs_nom.alpha)
        return out

    for (_, n1, a1), (_, n2, a2) in zip(first, second):
        assert not np.allclose(n1.front.canonical().poly, n2.front.canonical().poly)  # two different lenses
        for x, y in zip(perturbation(n1, a1), perturbation(n2, a2)):
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-15)
    # and the draws really perturb: index and thickness offsets differ between draws
    dn = [a.index_offset - n.index_offset for _, n, a in first]
    assert len(set(np.round(dn, 12))) == 5


def test_same_seed_identical_robust_design_and_file_round_trip(tmp_path):
    tol = load_tolerances(DEFAULT_TOLERANCES_FILE)
    kw = dict(model="zernike", free="full", criterion="A", method="cmaes", seed=2, max_evals=24, start="random",
              progress=False)
    d1 = optimize_design(robust=RobustSpec(tol, n_samples=3, seed=5), **kw)
    d2 = optimize_design(robust=RobustSpec(tol, n_samples=3, seed=5), **kw)
    assert d1.parameters == d2.parameters and d1.robust == d2.robust and d1.metrics == d2.metrics
    r = d1.robust
    assert r["tolerances"] == tol.to_dict() and (r["n_samples"], r["seed"], r["statistic"]) == (3, 5, "mean")
    assert r["nominal"] == d1.metrics["criterion_value"] and len(r["values"]) == 3
    assert r["cost"] == pytest.approx(np.mean(r["values"]), rel=1e-12)
    # the recorded robust cost is the best cost the optimiser saw
    assert r["cost"] == min(h["best"] for h in d1.history if h["best"] is not None)
    path = save_design(d1, tmp_path / "r.json")
    back = load_design(path)
    assert back.to_dict() == d1.to_dict()
    assert back.robust_spec() == RobustSpec(tol, 3, 5)
    # a nominal design has no robust key (files stay as before)
    d0 = optimize_design(**kw)
    assert d0.robust is None and "robust" not in d0.to_dict()
    assert load_design(save_design(d0, tmp_path / "n.json")).robust is None


def test_robust_spec_validation_and_compare(setup):
    bench, par, p, tol = setup
    with pytest.raises(ConfigError, match="n_samples"):
        RobustSpec(tol, n_samples=0)
    with pytest.raises(ConfigError, match="statistic"):
        RobustSpec(tol, statistic="median-ish")
    with pytest.raises(ConfigError, match="robust"):
        optimize_design(robust="tol.toml", max_evals=30, progress=False)
    lens = par.to_lens(p)
    res = compare_robust({"a": lens, "b": lens}, tol, bench, "A", n_samples=4, seed=9)
    a, b = res["designs"]["a"], res["designs"]["b"]
    assert a == b and a["p95"] >= a["median"] and set(a["crlb_std_nominal"]) == {
        "tx_um", "ty_um", "tz_um", "rx_urad", "ry_urad", "rz_urad"}
    with pytest.raises(ConfigError, match="seed"):
        compare_robust({"a": lens}, tol, bench, "A", n_samples=2, seed=9, exclude_seeds=(9,))


from conftest import run_cli as _run


def test_cli_robust_design(tmp_path):
    out = tmp_path / "rd.json"
    r = _run("design", "--model", "zernike", "--free", "full", "--criterion", "A", "--method", "cmaes",
             "--max-evals", "24", "--start", "random", "--robust", str(DEFAULT_TOLERANCES_FILE),
             "--robust-samples", "3", "--robust-seed", "7", "-o", str(out), "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["robust"]["n_samples"] == 3 and s["robust"]["seed"] == 7 and s["n_evals"] <= 24
    d = load_design(out)
    assert d.robust["cost"] == s["robust"]["cost"] and d.robust_spec().seed == 7


@pytest.mark.parametrize("body, fragment", [("[thickness]\nsigma_mm = -1\n", "thickness.sigma_mm"),
                                            ("[thickness\n", "not valid TOML"), (None, "not found")])
def test_cli_bad_tolerance_file(tmp_path, body, fragment):
    p = tmp_path / "t.toml"
    if body is not None:
        p.write_text(body)
    r = _run("design", "--robust", str(p), "-o", str(tmp_path / "x.json"), cwd=tmp_path)
    assert r.returncode == 2
    lines = [l for l in r.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and fragment in lines[0], r.stderr
    assert not (tmp_path / "x.json").exists()
