"""D-optimal design of calibration poses."""

import numpy as np
import pytest

from lensforge.errors import ConfigError
from lensforge.calibration.pose_design import (
    candidate_poses,
    design_poses,
    predicted_uncertainty,
    z_translation_std,
)
from lensforge.calibration.handeye import handeye_fisher
from lensforge.calibration.robot import (
    lens_pose_matrix,
    paper_scene,
    random_lens_poses,
)

COV_B = np.diag([1e-3] * 3 + [1e-5] * 3) ** 2  # ASSUMPTION: ~pose-estimation CRLB


def test_predicted_uncertainty_matches_fisher():
    s = paper_scene()
    x = random_lens_poses(np.random.default_rng(0), 12)
    p = predicted_uncertainty(s, x, COV_B)
    F = handeye_fisher(lens_pose_matrix(s, x), s.X, s.noise, COV_B)
    assert np.allclose(p["cov"], np.linalg.inv(F), rtol=1e-8)
    assert p["Z_translation_mm"] == pytest.approx(np.sqrt(np.trace(np.linalg.inv(F)[6:9, 6:9])))


def test_design_beats_random_poses():
    s = paper_scene()
    d = design_poses(s, COV_B, n=12, rng=np.random.default_rng(1), n_random_sets=30)
    assert d.x.shape == (12, 6) and d.A.shape == (12, 4, 4)
    assert d.chosen["logdet"] > d.random["logdet"]
    assert d.chosen["Z_translation_mm"] < d.random["Z_translation_mm"]
    assert d.chosen["Z_rotation_rad"] < d.random["Z_rotation_rad"]
    assert d.ratio_Z_translation > 1.3
    # the chosen poses stay in the working box
    assert np.all(np.abs(d.x[:, :3]) <= 1.0 + 1e-12)
    assert np.all(np.abs(d.x[:, 3:]) <= np.radians(1.0) + 1e-12)


def test_design_not_worse_than_any_candidate_subset_start():
    s = paper_scene()
    rng = np.random.default_rng(2)
    cand = candidate_poses(rng, 100)
    d = design_poses(s, COV_B, n=8, rng=rng, candidates=cand, n_random_sets=5, check_reach=False)
    for _ in range(20):
        idx = rng.choice(len(cand), 8, replace=False)
        assert predicted_uncertainty(s, cand[idx], COV_B)["logdet"] <= d.chosen["logdet"] + 1e-9


def test_design_errors():
    s = paper_scene()
    with pytest.raises(ConfigError, match="rng"):
        design_poses(s, COV_B)
    with pytest.raises(ConfigError, match="n must be"):
        design_poses(s, COV_B, n=2, rng=np.random.default_rng(0))
    with pytest.raises(ConfigError, match="candidates"):
        design_poses(s, COV_B, rng=np.random.default_rng(0), candidates=np.zeros((5, 6)))


def test_z_translation_std_is_inf_where_a_random_plan_loses_z():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 14, 20))
    F = A @ A.transpose(0, 2, 1)
    want = [np.sqrt(np.trace(np.linalg.inv(f)[6:9, 6:9])) for f in F]
    np.testing.assert_allclose(z_translation_std(F), want, rtol=1e-9)
    B = rng.normal(size=(2, 14, 10))  # rank 10 < 14: Z's translation is not observable
    assert np.all(np.isinf(z_translation_std(B @ B.transpose(0, 2, 1))))
    # lost only in X's rotation: Z keeps its finite sigma (the pinv's value there)
    G = F[0].copy()
    G[3, :] = G[:, 3] = 0.0
    sub = np.delete(np.delete(G, 3, 0), 3, 1)
    assert z_translation_std(G[None])[0] == pytest.approx(np.sqrt(np.trace(np.linalg.inv(sub)[5:8, 5:8])), rel=1e-9)
