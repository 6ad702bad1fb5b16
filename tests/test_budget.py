"""Tolerance budget search and a small real budget / sensitivity run."""

from __future__ import annotations

import math

import pytest

from lensforge.asbuilt.tolerances import Tolerances
from lensforge.verification.budget import (
    scaled_all,
    search_scale,
    sensitivity_analysis,
    tolerance_budget,
)
from lensforge.verification.study import StudyConfig


@pytest.mark.parametrize("f0,a", [(0.3, 0.05), (0.9, 2.0), (0.0, 1.0), (0.5, 1e-3)])
def test_search_finds_the_largest_passing_scale(f0, a):
    def f(s):
        return math.sqrt(f0 * f0 + (a * s) ** 2)

    s_true = math.sqrt(1 - f0 * f0) / a
    s, r, status, evals = search_scale(f, f0, rel_tol=0.05)
    assert status == "ok" and r <= 1.0
    assert s <= s_true * (1 + 1e-9) and s >= s_true / 1.05
    assert len(evals) <= 5  # the secant on scale^2 is exact for this model


def test_search_edge_cases():
    assert search_scale(lambda s: 2.0, 1.5)[2] == "noise floor exceeds target"
    s, _, status, _ = search_scale(lambda s: 0.5, 0.5)
    assert s is None and status.startswith("not limiting")
    # failures (inf) above some scale act as a wall
    s, r, status, _ = search_scale(lambda s: 0.5 if s < 3.0 else math.inf, 0.5, rel_tol=0.05)
    assert status == "ok" and 3.0 / 1.06 <= s < 3.0


def test_scaled_all_scales_every_component():
    t = scaled_all(Tolerances(), 0.5)
    assert t.form_rms_mm == pytest.approx(0.5 * Tolerances().form_rms_mm)
    assert t.thickness_sigma_mm == pytest.approx(0.5 * Tolerances().thickness_sigma_mm)


def test_small_budget_and_sensitivity_run():
    cfg = StudyConfig(n_poses=8, min_poses=4)
    tol = Tolerances()
    b = tolerance_budget("extended_polynomial", tol, n_lenses=2, seed=0, config=cfg, relative_to_noise=3.0,
                         components=["thickness"], max_evals=3, workers=0)
    row = b.rows[0]
    assert row.component == "thickness" and b.noise_ratio == pytest.approx(1 / 3.0)
    assert row.max_scale is None or row.max_scale > 0
    d = b.to_dict()
    assert d["rows"][0]["unit"].startswith("mm")
    rows = sensitivity_analysis("extended_polynomial", tol.only("thickness"), 2, 0, config=cfg, workers=0)
    names = [r.component for r in rows]
    assert names[0] == "none" and names[-1] == "all" and "form" in names
    # components zeroed by only("thickness") reproduce the noise-only row exactly (CRN)
    none, form = rows[0], rows[names.index("form")]
    assert none.p95_rot_deg == form.p95_rot_deg
