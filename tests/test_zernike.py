import numpy as np
import pytest

from lensforge.optics import zernike as zk


def test_noll_table_first_modes():
    # Noll (1976): j -> (n, m), even j cosine (m > 0), odd j sine (m < 0)
    expected = {1: (0, 0), 2: (1, 1), 3: (1, -1), 4: (2, 0), 5: (2, -2), 6: (2, 2), 7: (3, -1), 8: (3, 1),
                9: (3, -3), 10: (3, 3), 11: (4, 0), 12: (4, 2), 13: (4, -2), 14: (4, 4), 15: (4, -4)}
    for j, nm in expected.items():
        assert zk.noll_to_nm(j) == nm


def test_index_round_trips():
    for j in range(1, 67):
        assert zk.osa_to_noll(zk.noll_to_osa(j)) == j
        assert zk.thorlabs_to_noll(zk.noll_to_thorlabs(j)) == j
        n, m = zk.noll_to_nm(j)
        assert zk.nm_to_noll(n, m) == j
    assert sorted(zk.noll_to_osa(j) for j in range(1, 67)) == list(range(66))
    # OSA: j = (n(n+2) + m) / 2; defocus is OSA 4, Thorlabs 5
    assert zk.noll_to_osa(4) == 4 and zk.noll_to_thorlabs(4) == 5
    assert zk.noll_to_osa(3) == 1 and zk.noll_to_osa(2) == 2


def test_osa_vector_round_trip():
    noll = np.arange(1, 22)
    c = np.random.default_rng(0).normal(size=21)
    back_j, back_c = zk.from_osa_vector(zk.to_osa_vector(noll, c))
    np.testing.assert_array_equal(back_j, noll)
    np.testing.assert_array_equal(back_c, c)


def test_orthonormality_by_quadrature():
    # Gauss-Legendre in r (exact for the polynomial degree) x uniform trapezoid in phi
    nr, nphi = 40, 64
    xg, wg = np.polynomial.legendre.leggauss(nr)
    r = 0.5 * (xg + 1.0)
    wr = 0.5 * wg * r
    phi = np.linspace(0, 2 * np.pi, nphi, endpoint=False)
    R, PHI = np.meshgrid(r, phi, indexing="ij")
    W = np.outer(wr, np.full(nphi, 2 * np.pi / nphi)) / np.pi
    x, y = R * np.cos(PHI), R * np.sin(PHI)
    Z = np.array([zk.zernike(j, x, y) for j in range(1, 67)])
    gram = np.einsum("iab,jab,ab->ij", Z, Z, W)
    np.testing.assert_allclose(gram, np.eye(66), atol=1e-10)


def test_known_closed_forms():
    x, y = 0.3, -0.4
    r2 = x * x + y * y
    assert zk.zernike(4, x, y) == pytest.approx(np.sqrt(3) * (2 * r2 - 1), abs=1e-14)
    assert zk.zernike(6, x, y) == pytest.approx(np.sqrt(6) * (x * x - y * y), abs=1e-14)
    assert zk.zernike(5, x, y) == pytest.approx(np.sqrt(6) * 2 * x * y, abs=1e-14)
    assert zk.zernike(11, x, y) == pytest.approx(np.sqrt(5) * (6 * r2**2 - 6 * r2 + 1), abs=1e-14)


def test_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-0.7, 0.7, 20), rng.uniform(-0.7, 0.7, 20)
    h = 1e-6
    for j in range(2, 67):
        gx, gy = zk.zernike_gradient(j, x, y)
        fx = (zk.zernike(j, x + h, y) - zk.zernike(j, x - h, y)) / (2 * h)
        fy = (zk.zernike(j, x, y + h) - zk.zernike(j, x, y - h)) / (2 * h)
        np.testing.assert_allclose(gx, fx, atol=1e-6)
        np.testing.assert_allclose(gy, fy, atol=1e-6)
