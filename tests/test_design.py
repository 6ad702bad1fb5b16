"""Design module: optimisers, criteria, constraints, design file (small budgets)."""

import json

import numpy as np
import pytest

import lensforge as lf
from lensforge.design.constraints import Constraints, check_design, working_poses
from lensforge.design.criteria import criterion_value
from lensforge.design.design_file import Design, load_design, save_design
from lensforge.design.optimize import METHODS, optimize_design
from lensforge.design.parameterisation import FREE_PRESETS, parameterisation
from lensforge.errors import ConfigError, DesignError
from lensforge.optics.sensitivity import RANK_PENALTY, metrics_from_S

MODELS = ("polynomial", "extended_polynomial", "zernike")


def _run(bench, model, method, seed=0, evals=60, **kw):
    kw.setdefault("start", "random")
    kw.setdefault("criterion", "J")
    if model == "zernike":
        kw.setdefault("free", "base")  # the small free set: these tests are about the optimisers, not the lens
    return optimize_design(bench, model=model, method=method, seed=seed, max_evals=evals, progress=False,
                           particles=6, population=6, **kw)


def _check_returned(d: Design, bench):
    lo = np.array([d.bounds[n][0] for n in d.free])
    hi = np.array([d.bounds[n][1] for n in d.free])
    p = d.parameter_vector()
    assert np.all(p >= lo) and np.all(p <= hi)
    assert d.feasibility["feasible"] is True
    f = check_design(bench, d.lens, Constraints.from_dict(d.constraints))
    assert f.ok, f.message()
    assert d.lens.min_thickness >= 1.0 - 1e-9


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("method", METHODS)
def test_optimiser_lowers_J_from_random_feasible_start(bench, model, method):
    d = _run(bench, model, method)
    assert d.start["kind"] == "random"
    assert d.metrics["J"] < d.start["cost"]
    assert d.metrics["rank"] == 6
    assert d.n_evals <= 60 and len(d.history) >= 2
    _check_returned(d, bench)


@pytest.mark.parametrize("method", METHODS)
def test_same_seed_same_result(bench, method):
    a = _run(bench, "extended_polynomial", method, seed=3, evals=24)
    b = _run(bench, "extended_polynomial", method, seed=3, evals=24)
    assert a.parameters == b.parameters
    assert a.metrics == b.metrics and a.n_evals == b.n_evals
    assert [h["best"] for h in a.history] == [h["best"] for h in b.history]


def test_global_numpy_state_restored(bench):
    np.random.seed(7)
    before = np.random.get_state()[1].copy()
    _run(bench, "extended_polynomial", "pso", evals=14)
    assert np.array_equal(np.random.get_state()[1], before)


def test_rank_penalty_for_rotationally_symmetric_lens(bench):
    d = optimize_design(bench, model="conic", method="nelder-mead", max_evals=12, progress=False, start="random")
    assert d.lens.is_rotationally_symmetric()
    assert d.metrics["rank"] == 5
    assert d.metrics["J"] >= RANK_PENALTY
    assert d.metrics["crlb_std"]["rz_urad"] is None
    m = lf.metrics(bench, lf.paper_lens("spherical"))
    full = lf.metrics(bench, lf.paper_lens("polynomial"))
    for crit in ("J", "D", "A"):
        assert np.isfinite(criterion_value(crit, m))
        assert criterion_value(crit, m) > criterion_value(crit, full) + 0.5 * RANK_PENALTY


def test_d_criterion_unit_independent(bench, rng):
    S = rng.normal(size=(14, 6))
    R = np.eye(14) * 1e-6
    m1 = metrics_from_S(S, R, bench)
    m2 = metrics_from_S(S * np.array([10, 10, 10, 1, 1, 1]), R, bench)  # other length unit
    S2 = rng.normal(size=(14, 6))
    n1 = metrics_from_S(S2, R, bench)
    n2 = metrics_from_S(S2 * np.array([10, 10, 10, 1, 1, 1]), R, bench)
    d1 = criterion_value("D", m1) - criterion_value("D", n1)
    d2 = criterion_value("D", m2) - criterion_value("D", n2)
    assert d1 == pytest.approx(d2, rel=1e-9, abs=1e-9)


def test_infeasible_problem_clear_error(bench):
    with pytest.raises(DesignError, match="center_thickness"):
        optimize_design(bench, model="zernike", method="nelder-mead", progress=False,
                        bounds={"thickness": (3.0, 4.0)}, constraints=Constraints(min_center_mm=8.0, min_edge_mm=1.0))


def test_constraint_reports_violations(bench):
    f = check_design(bench, lf.paper_lens("spherical"), Constraints(min_center_mm=6.0))
    assert not f.ok and "center_thickness" in [v.constraint for v in f.violations]
    # the f = 50 mm sphere walks the beam off the pupil at +-1 mm but not at +-0.25 mm
    assert not check_design(bench, lf.paper_lens("spherical"), Constraints()).ok
    assert check_design(bench, lf.paper_lens("spherical"), Constraints(range_mm=0.25, range_rad=0.004)).ok
    assert len(working_poses(Constraints())) == 29


def test_bad_settings(bench):
    with pytest.raises(ConfigError, match="model"):
        optimize_design(bench, model="nope", progress=False)
    with pytest.raises(ConfigError, match="method"):
        optimize_design(bench, method="simulated-annealing", progress=False)
    with pytest.raises(ConfigError, match="bounds"):
        optimize_design(bench, bounds="thickness=5:3", progress=False)
    with pytest.raises(ConfigError, match="criterion"):
        optimize_design(bench, criterion="E", progress=False)
    with pytest.raises(ConfigError, match="range"):
        optimize_design(bench, constraints=Constraints(range_mm=50.0), progress=False)


@pytest.mark.parametrize("model", ["polynomial", "extended_polynomial", "zernike"])
def test_parameterisation_paper_vectors(model):
    par = parameterisation(model, free="paper")
    p = par.from_lens(lf.paper_lens(model))
    assert par.in_bounds(p), dict(zip(par.names, p))
    assert par.to_lens(p).to_dict() == lf.paper_lens(model).to_dict()
    assert np.allclose(par.from_unit(par.to_unit(p)), p)
    for preset in FREE_PRESETS[model]:
        parameterisation(model, free=preset)
    with pytest.raises(ConfigError):
        parameterisation(model, free=["front.nonsense[0]"])


def test_design_file_round_trip(bench, tmp_path):
    d = _run(bench, "zernike", "cmaes", evals=16, criterion="D")
    path = save_design(d, tmp_path / "z.json")
    e = load_design(path)
    assert e.to_dict() == d.to_dict()
    assert e.lens == d.lens or e.lens.to_dict() == d.lens.to_dict()
    save_design(e, tmp_path / "z2.json")
    assert (tmp_path / "z.json").read_text() == (tmp_path / "z2.json").read_text()
    data = json.loads(path.read_text())
    assert data["schema_version"] == 1 and data["criterion"] == "D"
    assert set(data["metrics"]["crlb_std"]) == {"tx_um", "ty_um", "tz_um", "rx_urad", "ry_urad", "rz_urad"}
    assert lf.Lens.from_dict(data["lens"]).to_dict() == d.lens.to_dict()
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ConfigError, match="not valid JSON"):
        load_design(bad)


def test_slope_constraint_reported():
    import lensforge as lf
    from lensforge.design.constraints import Constraints, check_design

    bench = lf.Bench.default()
    poly = lf.paper_lens("polynomial")  # back rim slope 46.8 deg
    assert check_design(bench, poly, Constraints()).ok
    f = check_design(bench, poly, Constraints(max_slope_deg=45.0))
    assert not f.ok
    (v,) = [v for v in f.violations if v.constraint == "back_slope"]
    x = 12.7  # steepest at the rim along x: dz/dx = 2 zeta2 x + 4 zeta4 x^3 (paper Eq. 11, back surface)
    expected = np.degrees(np.arctan(abs(2 * -4.16e-2 * x + 4 * -9.15e-7 * x**3)))
    assert v.value == pytest.approx(expected, abs=0.05) and "max_slope_deg" in v.message


def test_cmaes_narrows_its_step_in_a_thin_feasible_region():
    # a feasible set 0.004 wide around the start (like fixed spot windows): at the default step no lens
    # of the first generation is feasible, so CMA-ES restarts 10x narrower and then improves on its start
    from lensforge.design.optimize import INFEASIBLE, OPTIMISERS

    class Thin:
        max_evals, n_evals = 400, 0
        best = np.inf

        def batch(self, U):
            U = np.atleast_2d(U)
            self.n_evals += len(U)
            d = np.abs(U - 0.5).max(axis=1)
            f = np.where(d < 0.002, np.sum((U - 0.501) ** 2, axis=1), INFEASIBLE + d)
            self.best = min(self.best, f.min())
            return f  # the budget is CMA-ES's maxfevals

    prob = Thin()
    info = OPTIMISERS["cmaes"].run(prob, np.full(6, 0.5), np.random.default_rng(0), 0, {"sigma0": 0.1})
    assert info["narrowed"] >= 2 and info["sigma_used"] <= 0.001 + 1e-12
    assert prob.best < 6 * 0.001**2  # feasible and better than the start (6e-6)
