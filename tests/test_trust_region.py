"""The shared step policy (calibration/trust_region.py): the radius rule, the exact
eigenbasis step and the structured-solve step agree with their definitions."""

import numpy as np
import pytest

from lensforge.calibration.trust_region import (GROW_ABOVE, SHRINK_BELOW, damped_step, eigen_step, gain_ratio,
                                                next_radius, predicted_decrease)


def _problem(seed, n=8, cond=1e6):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    w = np.logspace(0, np.log10(cond), n)
    return Q @ np.diag(w) @ Q.T, rng.normal(size=n) * 10


def test_radius_rule():
    r = next_radius(np.array([1.0, 1.0, 1.0, 1.0, 1.0]), np.array([1.0, 0.5, 1.0, 1.0, 0.2]),
                    np.array([0.9, 0.9, 0.5, 0.1, 0.9]), np.array([True, True, True, True, False]))
    # grow on the boundary, keep inside, keep a fair step, quarter a poor one, quarter a rejected one
    np.testing.assert_allclose(r, [2.0, 1.0, 1.0, 0.25, 0.05])
    assert next_radius(1.0, 1.0, 0.9, True, cap=1.5) == 1.5
    assert SHRINK_BELOW < GROW_ABOVE
    np.testing.assert_allclose(gain_ratio([1.0, 1.0], [2.0, 0.0]), [0.5, 0.0])


@pytest.mark.parametrize("seed", range(4))
def test_eigen_step_is_the_constrained_minimiser(seed):
    A, g = _problem(seed)
    gn = -np.linalg.solve(A, g)
    du, lam = eigen_step(A[None], g[None], np.array([np.inf]))
    np.testing.assert_allclose(du[0], gn, rtol=1e-8, atol=1e-12 * np.linalg.norm(gn))
    assert lam[0] == 0.0
    delta = 0.1 * np.linalg.norm(gn)
    du, lam = eigen_step(A[None], g[None], np.array([delta]))
    assert abs(np.linalg.norm(du[0]) - delta) <= 1e-6 * delta
    # the LM step for that lambda, and no shorter step inside the region has a lower model value
    d_lm = -np.linalg.solve(A + lam[0] * np.eye(len(g)), g)
    np.testing.assert_allclose(du[0], d_lm, rtol=1e-5, atol=1e-6 * delta)
    m = lambda d: g @ d + 0.5 * d @ A @ d  # noqa: E731
    rng = np.random.default_rng(seed + 100)
    for _ in range(200):
        v = rng.normal(size=len(g))
        v *= delta * rng.uniform() ** (1 / len(g)) / np.linalg.norm(v)
        assert m(v) >= m(du[0]) - 1e-9 * abs(m(du[0]))


@pytest.mark.parametrize("seed", range(4))
def test_damped_step_matches_the_dense_trust_region(seed):
    """A structured solve with Marquardt's scaling gives the step the dense eigenbasis
    solution gives in scaled coordinates, with its length within MINPACK's 10 %."""
    A, g = _problem(seed)
    D = np.sqrt(np.diag(A))
    calls = []

    def solve(lam):
        calls.append(lam)
        d = -np.linalg.solve(A + lam * np.diag(np.diag(A)), g)
        return d, float(np.linalg.norm(D * d))

    d_gn, L_gn, lam = damped_step(solve, np.inf)
    assert lam == 0.0 and len(calls) == 1
    for frac in (0.5, 0.1, 1e-3):
        delta = frac * L_gn
        d, L, lam = damped_step(solve, delta)
        assert abs(L - delta) <= 0.1 * delta and lam > 0
        np.testing.assert_allclose(d, solve(lam)[0], rtol=1e-10)
        u, lam_e = eigen_step((A / np.outer(D, D))[None], (g / D)[None], np.array([L]))
        np.testing.assert_allclose(D * d, u[0], rtol=1e-4, atol=1e-6 * L)
        # a descent direction whose predicted decrease is positive
        assert predicted_decrease(g, d, A @ d) > 0
