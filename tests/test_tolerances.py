"""As-built tolerance model: TOML validation, zero -> nominal, exact shrinkage, sampler statistics."""

import math

import numpy as np
import pytest

import lensforge as lf
from lensforge.errors import ConfigError
from lensforge.asbuilt.tolerances import (
    DEFAULT_TOLERANCES_FILE,
    Tolerances,
    load_tolerances,
    sample_as_built,
    scale_canonical,
)
from lensforge.optics.lens import Lens
from lensforge.optics.surfaces import CanonicalSurface

N = 2000  # Monte Carlo draws; bounds below are 4.5 standard errors


@pytest.fixture(scope="module")
def lens():
    return lf.paper_lens("zernike")


def _check_mean_sd(x, mean, sd):
    x = np.asarray(x)
    se_mean = sd / math.sqrt(len(x))
    se_sd = sd / math.sqrt(2 * (len(x) - 1))
    assert abs(x.mean() - mean) <= 4.5 * se_mean + 1e-15, (x.mean(), mean)
    assert abs(x.std(ddof=1) - sd) <= 4.5 * se_sd + 1e-15, (x.std(ddof=1), sd)


def _draws(lens, tol, n=N, seed=7):
    rng = np.random.default_rng(seed)
    return [sample_as_built(lens, tol, rng, validate=False) for _ in range(n)]


def test_default_file_is_the_documented_defaults(tmp_path):
    t = load_tolerances(DEFAULT_TOLERANCES_FILE)
    assert t == Tolerances()
    assert lf.load_tolerances is load_tolerances and lf.Tolerances is Tolerances
    t2 = Tolerances().scaled("index", 2.0).scaled("form", 0.5)
    t2.save(tmp_path / "t.toml")
    assert load_tolerances(tmp_path / "t.toml") == t2
    assert t2.to_dict()["index"]["sigma"] == "material" and t2.index_factor == 2.0


@pytest.mark.parametrize("text, field", [
    ("[form]\nrms_mm = -0.001\n", "form.rms_mm"),
    ("[thickness]\nsigma_mm = nan\n", "thickness.sigma_mm"),
    ("[thickness]\nsigam_mm = 0.1\n", "thickness.sigam_mm"),
    ("[warp]\namount = 1\n", "warp"),
    ("[polishing]\nrolloff_power = 3\n", "polishing.rolloff_power"),
    ("[polishing]\nsurfaces = ['front', 'side']\n", "polishing.surfaces"),
    ("[form]\nmodes = [1, 2]\n", "form.modes"),
    ("[index]\nsigma = 'lots'\n", "index.sigma"),
    ("[ripple]\nperiod_mm = 0\n", "ripple.period_mm"),
    ("[polishing]\ndepth_mm = 0\ndepth_sigma_mm = 0.01\n", "polishing.depth_sigma_mm"),
    ("schema_version = 2\n", "schema_version"),
    ("[form\n", "not valid TOML"),
])
def test_bad_tolerance_files(tmp_path, text, field):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=field.replace("[", r"\[").replace(".", r"\.")):
        load_tolerances(p)


def test_helpers():
    assert Tolerances.component_names() == ("polishing", "form", "thickness", "index", "shrinkage", "ripple")
    only = Tolerances().only("thickness")
    assert only.thickness_sigma_mm == 0.05 and only.form_rms_mm == 0 and only.index_sigma == 0
    assert only.shrinkage_mean == 0 and only.polish_depth_mm == 0 and only.ripple_amplitude_mm == 0
    assert Tolerances().scaled("polishing", 2).polish_depth_mm == pytest.approx(0.05)
    with pytest.raises(ConfigError, match="unknown"):
        Tolerances().only("warp")
    with pytest.raises(ConfigError, match="factor"):
        Tolerances().scaled("form", -1)


def test_zero_tolerances_give_the_nominal_lens(lens, rng):
    assert sample_as_built(lens, Tolerances.zero(), rng) is lens
    for name in Tolerances.component_names():
        assert sample_as_built(lens, Tolerances.zero().scaled(name, 5.0), rng) is lens


def test_shrinkage_scales_the_canonical_form_exactly():
    cs = CanonicalSurface(0.03, -0.5, np.array([1e-4, -2e-6, 3e-9, 0, 0, 0, 0, 0]),
                          np.array([[0.01, 2e-3, 1e-4], [3e-3, -2e-4, 0], [5e-4, 0, 0]]), 1e-3, 0.05)
    s = 0.987
    sc = scale_canonical(cs, s)
    x, y = np.meshgrid(np.linspace(-9, 9, 13), np.linspace(-8, 8, 11))
    assert np.allclose(sc.sag(x, y), s * cs.sag(x / s, y / s), rtol=1e-13, atol=1e-15)


def test_shrinkage_statistics_and_geometry(lens):
    t = Tolerances().only("shrinkage")
    mat = lens.material_data
    lenses = _draws(lens, t)
    s = np.array([L.thickness / lens.thickness for L in lenses])
    _check_mean_sd(1 - s, mat.shrinkage, mat.shrinkage_sigma)
    L = lenses[0]
    si = L.aperture / lens.aperture
    assert si == pytest.approx(s[0]) and L.edge_diameter == pytest.approx(si * lens.edge_diameter)
    x, y = np.array([1.0, -4.0, 7.5]), np.array([2.0, 3.0, -6.0])
    assert np.allclose(L.front.sag(x, y), si * lens.front.sag(x / si, y / si), atol=1e-14)


def test_thickness_and_index_statistics(lens):
    t = Tolerances.zero()
    t = t.__class__(**{**t.__dict__, "thickness_mean_mm": 0.01, "thickness_sigma_mm": 0.04,
                       "index_mean": -0.002, "index_sigma": 0.003, "index_batch_sigma": 0.004})
    lenses = _draws(lens, t)
    _check_mean_sd([L.thickness - lens.thickness for L in lenses], 0.01, 0.04)
    _check_mean_sd([L.index_offset for L in lenses], -0.002, 0.005)
    assert lenses[0].index(532.0) == pytest.approx(lens.index(532.0) + lenses[0].index_offset)
    # material defaults: index sigma combines the material's index_sigma and batch_sigma
    mat = lens.material_data
    sd = math.hypot(mat.index_sigma, mat.batch_sigma)
    _check_mean_sd([L.index_offset for L in _draws(lens, Tolerances().only("index"))], 0.0, sd)


def test_polishing_statistics(lens):
    t = Tolerances().only("polishing")
    lenses = _draws(lens, t)
    front_depth = [L.front.canonical().poly[0, 0] - lens.front.canonical().poly[0, 0] for L in lenses]
    back_depth = [lens.back.canonical().poly[0, 0] - L.back.canonical().poly[0, 0] for L in lenses]
    _check_mean_sd(front_depth, t.polish_depth_mm, t.polish_depth_sigma_mm)
    _check_mean_sd(back_depth, t.polish_depth_mm, t.polish_depth_sigma_mm)
    assert min(front_depth) > 0 and min(back_depth) > 0  # removal never adds material
    Ra = 0.5 * lens.aperture
    roll = [(L.front.canonical().alpha[1] - lens.front.canonical().alpha[1]) * Ra**4 for L in lenses]
    _check_mean_sd(roll, t.polish_rolloff_mm, t.polish_rolloff_sigma_mm)
    # removal thins the lens at the centre by both depths
    L = lenses[0]
    assert L.thickness_at(0, 0) == pytest.approx(lens.thickness_at(0, 0) - front_depth[0] - back_depth[0])


def test_form_error_rms_over_the_clear_aperture(lens):
    t = Tolerances().only("form")
    Ra = 0.5 * lens.aperture
    g, w = np.polynomial.legendre.leggauss(24)
    r = Ra * 0.5 * (g + 1)
    wr = 0.5 * Ra * w * r
    phi = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    x, y = r[:, None] * np.cos(phi), r[:, None] * np.sin(phi)
    area = np.pi * Ra**2
    ms = []
    for L in _draws(lens, t, n=1000):
        d = L.front.sag(x, y) - lens.front.sag(x, y)
        mean = np.sum(wr[:, None] * d) * (2 * np.pi / 48) / area
        ms.append(np.sum(wr[:, None] * (d - mean) ** 2) * (2 * np.pi / 48) / area)
    ms = np.array(ms)
    n = len(t.form_modes)
    se = math.sqrt(2 * n) * (t.form_rms_mm**2 / n) / math.sqrt(len(ms))  # sd of a mean of chi^2 draws
    assert abs(ms.mean() - t.form_rms_mm**2) <= 4.5 * se


def test_ripple_only_on_unpolished_surfaces(lens, rng):
    t = Tolerances().only("ripple").__class__(**{**Tolerances().only("ripple").__dict__,
                                                  "polished_surfaces": ("back",)})
    L = sample_as_built(lens, t, rng)
    assert L.front.ripple_amplitude == pytest.approx(t.ripple_amplitude_mm) and L.front.ripple_period == 0.025
    assert L.back is lens.back
    assert sample_as_built(lens, Tolerances().only("ripple"), rng) is lens  # both polished: no ripple


def test_full_model_draw_is_a_usable_lens(lens):
    rng = np.random.default_rng(11)
    L = sample_as_built(lens, Tolerances(), rng)
    assert isinstance(L, Lens) and L.front.kind == "freeform"
    assert Lens.from_dict(L.to_dict()).to_dict() == L.to_dict()
    L2 = sample_as_built(lens, Tolerances(), np.random.default_rng(11))
    assert L2.to_dict() == L.to_dict()  # seeded: reproducible
    # common random numbers: only(name) uses the same draws as the full model
    a = sample_as_built(lens, Tolerances().only("index"), np.random.default_rng(11))
    assert a.index_offset == L.index_offset


def test_tracer_uses_the_as_built_lens(lens, bench):
    pose = np.zeros(6)
    z0 = np.asarray(lf.measure(bench, lens, pose))
    L = sample_as_built(lens, Tolerances().only("index").scaled("index", 0.1), np.random.default_rng(2))
    z1 = np.asarray(lf.measure(bench, L, pose))
    assert z1.shape == z0.shape and np.all(np.isfinite(z1)) and not np.allclose(z1, z0)
    zn = np.asarray(lf.measure(bench, sample_as_built(lens, Tolerances.zero(), np.random.default_rng(2)), pose))
    assert np.array_equal(zn, z0)


def _fingerprint(L):
    """Every float of an as-built lens (exact: compared with ==)."""
    out = {"thickness": L.thickness, "aperture": L.aperture, "edge": float(L.edge_diameter), "dn": L.index_offset}
    for side in ("front", "back"):
        cs = getattr(L, side).canonical()
        out[side] = [float(cs.c), float(cs.k), [float(a) for a in cs.alpha], [float(a) for a in np.ravel(cs.poly)],
                     list(np.shape(cs.poly)), float(cs.ripple_amplitude), float(cs.ripple_period)]
    return out


def test_seeded_draws_are_identical_to_the_recorded_ones():
    """tests/data/as_built_draws_v1.json was written by the sampler before the components
    became registry entries (commit 568adb3): the same seeds must give the same as-built
    lenses (studies and budgets stay reproducible across the refactor), to rounding: numpy
    2.4 sums one polynomial coefficient in another order than the recording's numpy (1 ulp,
    2e-16 relative); a changed draw or component differs at O(1e-3) or more."""
    import json
    from pathlib import Path

    want = json.loads((Path(__file__).parent / "data" / "as_built_draws_v1.json").read_text())
    base = load_tolerances(DEFAULT_TOLERANCES_FILE)
    tols = {"default_file": base,
            "front_only_ripple": Tolerances(polished_surfaces=("front",), form_modes=(2, 4, 7, 11, 22)),
            "scaled": base.scaled("form", 3).scaled("index", 2).scaled("shrinkage", 1.5).scaled("polishing", 0.5),
            **{f"only_{n}": base.only(n) for n in Tolerances.component_names()}}
    got = {}
    for lname in ("zernike", "extended_polynomial"):
        for tn, t in tols.items():
            rng = np.random.default_rng(12345)
            got[f"{lname}|{tn}"] = [_fingerprint(sample_as_built(lf.paper_lens(lname), t, rng, validate=False))
                                    for _ in range(2)]
    got = json.loads(json.dumps(got))
    assert got.keys() == want.keys()

    def same(a, b):
        if isinstance(a, dict):
            return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
        if isinstance(a, list):
            return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
        if isinstance(a, float):
            return a == pytest.approx(b, rel=1e-12, abs=1e-300)
        return a == b

    assert [k for k in want if not same(got[k], want[k])] == []


def test_registry_builds_tolerances_ranges_and_file_layout():
    """One registry entry per component: the dataclass fields, the TOML layout of the
    default file and the input ranges all come from it."""
    import dataclasses
    import tomllib

    from lensforge.asbuilt.tolerances import COMPONENT_SPECS, TOLERANCE_RANGES

    attrs = [f.attr for c in COMPONENT_SPECS.values() for f in c.fields]
    assert [f.name for f in dataclasses.fields(Tolerances)] == attrs
    doc = tomllib.loads(DEFAULT_TOLERANCES_FILE.read_text())
    layout = {k: set(v) for k, v in Tolerances().to_dict().items() if isinstance(v, dict)}
    assert layout == {k: set(v) for k, v in doc.items() if isinstance(v, dict)}
    numeric = {f"{c.name}.{f.key}" for c in COMPONENT_SPECS.values() for f in c.fields if f.check is None}
    assert numeric <= set(TOLERANCE_RANGES)
    for c in COMPONENT_SPECS.values():
        assert c.main[0] in attrs and set(c.scaled) <= set(attrs)
    import pickle

    t = Tolerances().scaled("form", 2.0)
    assert pickle.loads(pickle.dumps(t)) == t  # studies ship it to Dask workers


def test_tolerances_fields_are_typed_and_are_the_registrys():
    """Tolerances declares one typed field per registry field, in the registry's order, with
    the registry's default; a default instance's values have the declared types."""
    import dataclasses
    import types
    import typing

    from lensforge.asbuilt.tolerances import COMPONENT_SPECS, Tolerances

    reg = [f for c in COMPONENT_SPECS.values() for f in c.fields]
    fs = dataclasses.fields(Tolerances)
    assert [f.name for f in fs] == [f.attr for f in reg]
    assert [f.default for f in fs] == [f.default for f in reg]
    hints = typing.get_type_hints(Tolerances)
    assert all(hints[f.name] is not typing.Any for f in fs)
    t = Tolerances()
    for f in fs:
        hint = hints[f.name]
        v = getattr(t, f.name)
        if isinstance(hint, types.UnionType):
            assert v is None or isinstance(v, typing.get_args(hint)[0]), f.name
        elif typing.get_origin(hint) is tuple:
            item = typing.get_args(hint)[0]
            assert isinstance(v, tuple) and all(isinstance(x, item) for x in v), f.name
        else:
            assert isinstance(v, hint) and not isinstance(v, bool), f.name
