"""Frechet distance: analytic cases, rank-deficient covariances, agreement with scipy's sqrtm."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from omnilidar.errors import InputError
from omnilidar.metrics.frechet import (
    feature_statistics,
    frechet_distance,
    frechet_from_features,
    trace_sqrt_product,
)

METHODS = ("gram", "covariance")


def _scipy_frechet(mu1, s1, mu2, s2) -> float:
    """The anchors' formula, for comparison where it is well conditioned."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        root = scipy.linalg.sqrtm(s1 @ s2)
    return float(np.real(np.sum((mu1 - mu2) ** 2) + np.trace(s1 + s2 - 2.0 * root)))


def _random_spd(rng, d, floor=0.1):
    a = rng.standard_normal((d, d)) / np.sqrt(d)
    return a @ a.T + floor * np.eye(d)


def test_identical_inputs_give_exactly_zero():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((40, 16)) * 3.0 + 1.0
    mu, s = feature_statistics(x)
    assert frechet_distance(mu, s, mu, s) == 0.0
    assert frechet_distance(mu, s, mu.copy(), s.copy()) == 0.0
    for method in METHODS:
        assert frechet_from_features(x, x.copy(), method=method) == 0.0


def test_pure_mean_shift_gives_squared_shift():
    rng = np.random.default_rng(1)
    d = 24
    s = _random_spd(rng, d)
    mu1 = rng.standard_normal(d)
    shift = rng.standard_normal(d)
    assert frechet_distance(mu1, s, mu1 + shift, s) == pytest.approx(shift @ shift, rel=1e-14)
    # features shifted by a constant have identical covariances up to round-off only
    x = rng.standard_normal((500, d))
    for method in METHODS:
        got = frechet_from_features(x, x + shift, method=method)
        assert got == pytest.approx(shift @ shift, rel=1e-9)


@pytest.mark.parametrize("a, b, d", [(1.0, 4.0, 8), (0.25, 9.0, 64), (2.0, 2.0 + 1e-6, 5)])
def test_isotropic_gaussians(a, b, d):
    got = frechet_distance(np.zeros(d), a * np.eye(d), np.zeros(d), b * np.eye(d))
    # Tr S1 + Tr S2 - 2 Tr sqrt(.) cancels: absolute round-off ~ eps * (Tr S1 + Tr S2)
    assert got == pytest.approx(d * (np.sqrt(a) - np.sqrt(b)) ** 2, rel=1e-9, abs=1e-14 * d * (a + b))


def test_commuting_diagonal_covariances_with_mean_shift():
    rng = np.random.default_rng(2)
    d = 50
    a = rng.uniform(0.01, 5.0, d)
    b = rng.uniform(0.01, 5.0, d)
    b[:10] = 0.0  # singular second covariance
    mu1, mu2 = rng.standard_normal(d), rng.standard_normal(d)
    expected = np.sum((mu1 - mu2) ** 2) + np.sum((np.sqrt(a) - np.sqrt(b)) ** 2)
    assert frechet_distance(mu1, np.diag(a), mu2, np.diag(b)) == pytest.approx(expected, rel=1e-12)
    # and with the singular one first (eigh route instead of Cholesky)
    assert frechet_distance(mu2, np.diag(b), mu1, np.diag(a)) == pytest.approx(expected, rel=1e-12)


def test_non_commuting_2x2_closed_form():
    # for 2 x 2, Tr sqrt(M) = sqrt(tr M + 2 sqrt(det M)) with M = S1 S2
    s1 = np.array([[2.0, 0.7], [0.7, 1.0]])
    s2 = np.array([[0.5, -0.3], [-0.3, 3.0]])
    m = s1 @ s2
    tr_sqrt = np.sqrt(np.trace(m) + 2.0 * np.sqrt(np.linalg.det(m)))
    assert trace_sqrt_product(s1, s2) == pytest.approx(tr_sqrt, rel=1e-13)
    expected = np.trace(s1) + np.trace(s2) - 2.0 * tr_sqrt + 1.0
    assert frechet_distance([0.0, 0.0], s1, [1.0, 0.0], s2) == pytest.approx(expected, rel=1e-13)


@pytest.mark.parametrize("n, d", [(30, 200), (199, 200), (12, 400)])
def test_fewer_samples_than_dimensions_analytic(n, d):
    """B = k A + c: S_B = k^2 S_A (both rank n - 1 < d), so
    d^2 = |mean difference|^2 + Tr(S_A) (1 - k)^2 exactly."""
    rng = np.random.default_rng(n)
    a = rng.standard_normal((n, d)) * rng.uniform(0.1, 3.0, d)
    k, c = 2.5, rng.standard_normal(d)
    b = k * a + c
    mu_a, s_a = feature_statistics(a)
    expected = np.sum((mu_a - b.mean(axis=0)) ** 2) + np.trace(s_a) * (1.0 - k) ** 2
    for method in METHODS:
        assert frechet_from_features(a, b, method=method) == pytest.approx(expected, rel=1e-10)
        assert frechet_from_features(b, a, method=method) == pytest.approx(expected, rel=1e-10)


def test_rank_deficient_gram_and_covariance_routes_agree():
    rng = np.random.default_rng(3)
    a = rng.standard_normal((60, 300)) * 2.0
    b = rng.standard_normal((80, 300)) + 0.2
    gram = frechet_from_features(a, b, method="gram")
    cov = frechet_from_features(a, b, method="covariance")
    assert np.isfinite(gram) and gram > 0
    assert cov == pytest.approx(gram, rel=1e-11)


def test_zero_covariance_set():
    """All samples equal: S = 0, d^2 = |mu1 - mu2|^2 + Tr(S2)."""
    rng = np.random.default_rng(4)
    a = np.tile(rng.standard_normal(20), (10, 1))
    b = rng.standard_normal((15, 20))
    mu_a, _ = feature_statistics(a)
    mu_b, s_b = feature_statistics(b)
    expected = np.sum((mu_a - mu_b) ** 2) + np.trace(s_b)
    for method in METHODS:
        assert frechet_from_features(a, b, method=method) == pytest.approx(expected, rel=1e-12)
    assert frechet_distance(mu_a, np.zeros((20, 20)), mu_b, s_b) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("d", [8, 64, 160])
def test_agrees_with_scipy_sqrtm_when_well_conditioned(d):
    rng = np.random.default_rng(d)
    a = rng.standard_normal((4 * d + 50, d)) @ rng.standard_normal((d, d))
    b = rng.standard_normal((3 * d + 70, d)) * 1.5 + 0.3
    mu_a, s_a = feature_statistics(a)
    mu_b, s_b = feature_statistics(b)
    reference = _scipy_frechet(mu_a, s_a, mu_b, s_b)
    assert frechet_distance(mu_a, s_a, mu_b, s_b) == pytest.approx(reference, rel=1e-9)
    for method in METHODS:
        assert frechet_from_features(a, b, method=method) == pytest.approx(reference, rel=1e-9)


def test_feature_statistics_match_numpy():
    rng = np.random.default_rng(5)
    x = rng.standard_normal((33, 7)).astype(np.float32)
    mu, s = feature_statistics(x)
    assert mu.dtype == np.float64 and s.shape == (7, 7)
    np.testing.assert_allclose(s, np.cov(x.astype(np.float64), rowvar=False), rtol=1e-14)
    np.testing.assert_allclose(mu, x.astype(np.float64).mean(axis=0), rtol=1e-14)
    _, s1 = feature_statistics(np.arange(6.0).reshape(3, 2)[:, :1])  # D = 1 stays 2-D
    assert s1.shape == (1, 1)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    d=st.integers(1, 12),
    n1=st.integers(2, 20),
    n2=st.integers(2, 20),
    scale=st.floats(1e-3, 1e3),
)
def test_properties_symmetric_nonnegative_finite(seed, d, n1, n2, scale):
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((n1, d)) * scale
    b = rng.standard_normal((n2, d)) * scale * rng.uniform(0.2, 5.0)
    ab_gram = frechet_from_features(a, b, method="gram")
    ab_cov = frechet_from_features(a, b, method="covariance")
    ba_cov = frechet_from_features(b, a, method="covariance")
    for v in (ab_gram, ab_cov, ba_cov):
        assert np.isfinite(v) and v >= 0.0
    tol = 1e-8 * (scale * scale * d * 25 + 1e-300)
    assert ab_cov == pytest.approx(ab_gram, abs=tol)
    assert ba_cov == pytest.approx(ab_cov, abs=tol)


def test_auto_picks_covariance_route_for_many_samples():
    import omnilidar.metrics.frechet as fr

    assert fr._gram_cost(50, 60, 512) < fr._covariance_cost(50, 60, 512)
    assert fr._gram_cost(10_000, 10_000, 2048) > fr._covariance_cost(10_000, 10_000, 2048)
    rng = np.random.default_rng(6)
    a, b = rng.standard_normal((300, 4)), rng.standard_normal((200, 4))
    assert frechet_from_features(a, b) == pytest.approx(frechet_from_features(a, b, method="covariance"), rel=1e-12)


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: frechet_from_features(np.ones((1, 3)), np.ones((5, 3))), "at least 2 samples"),
        (lambda: frechet_from_features(np.ones((4, 3)), np.ones((5, 2))), "dimensions differ"),
        (lambda: frechet_from_features(np.full((4, 3), np.nan), np.ones((5, 3))), "NaN"),
        (lambda: frechet_from_features(np.ones(4), np.ones((5, 3))), "(N, D)"),
        (lambda: frechet_from_features(np.ones((4, 3)), np.ones((5, 3)), method="x"), "method"),
        (lambda: frechet_distance(np.zeros(2), np.eye(2), np.zeros(3), np.eye(3)), "differ in size"),
        (lambda: frechet_distance(np.zeros(2), [[1.0, 0.5], [0.0, 1.0]], np.zeros(2), np.eye(2)), "symmetric"),
        (lambda: frechet_distance(np.zeros(2), np.diag([1.0, -1.0]), np.zeros(2), np.eye(2)), "semi-definite"),
        (lambda: frechet_distance(np.zeros(2), np.eye(2), np.zeros(2), np.diag([1.0, -1.0])), "semi-definite"),
        (lambda: frechet_distance(np.zeros(2), np.eye(3), np.zeros(2), np.eye(2)), "2 x 2"),
        (lambda: frechet_distance([np.inf, 0.0], np.eye(2), np.zeros(2), np.eye(2)), "NaN or Inf"),
    ],
)
def test_bad_input_raises_input_error(call, message):
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        call()


def _graded_features(rng, n, d, decades):
    """Features whose variances span `decades` decades, correlated, with a mean shift."""
    scales = np.logspace(0.0, -decades / 2.0, d)
    a = rng.standard_normal((n, d)) * scales
    mix = rng.standard_normal((d, d)) / np.sqrt(d)
    b = (rng.standard_normal((n, d)) @ mix * 0.3 + rng.standard_normal((n, d))) * scales * 1.3 + 0.1
    return a, b


@pytest.mark.parametrize("n, d", [(900, 512), (300, 512)])
def test_routes_agree_on_graded_spectra(n, d):
    """Variances over six decades: eigenvalues of S1 S2 down to ~1e-13 of the
    largest are genuine and must all count (more and fewer samples than dims).
    With fewer samples both covariances are singular and S1 S2 has eigenvalues
    near 0: squaring them cost 1e-11 relative, depending on the BLAS build."""
    a, b = _graded_features(np.random.default_rng(7), n, d, decades=6)
    gram = frechet_from_features(a, b, method="gram")
    cov = frechet_from_features(a, b, method="covariance")
    assert cov == pytest.approx(gram, rel=1e-13)
    assert frechet_from_features(b, a, method="covariance") == pytest.approx(gram, rel=1e-13)


def test_dead_feature_units_keep_the_cholesky_route():
    """Exactly zero features (dead ReLU units) make the covariance singular only
    on those rows: the rest is still factored without dropping anything."""
    a, b = _graded_features(np.random.default_rng(8), 700, 256, decades=6)
    a[:, :40] = 0.0
    b[:, 20:50] = 0.0
    gram = frechet_from_features(a, b, method="gram")
    assert frechet_from_features(a, b, method="covariance") == pytest.approx(gram, rel=1e-11)


def _reflect(diagonal: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """H_k ... H_1 diag(d) H_1 ... H_k for Householder reflectors H = I - 2 v v^T:
    a dense covariance with known eigenvalues, in O(k D^2)."""
    s = np.diag(diagonal)
    for v in normals:
        sv = s @ v
        s += 4.0 * (v @ sv) * np.outer(v, v) - 2.0 * np.outer(v, sv) - 2.0 * np.outer(sv, v)
    return s


def test_commuting_covariances_at_4096_dims():
    """S1 = Q diag(a) Q^T, S2 = Q diag(b) Q^T with spectra over eight decades:
    d^2 = |mu1 - mu2|^2 + sum (sqrt(a_i) - sqrt(b_i))^2 exactly."""
    rng = np.random.default_rng(9)
    d = 4096
    normals = rng.standard_normal((2, d))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    a = rng.permutation(np.logspace(0.0, -8.0, d))
    b = rng.permutation(np.logspace(1.0, -7.0, d))
    mu1, mu2 = rng.standard_normal(d), rng.standard_normal(d) * 0.1
    expected = np.sum((mu1 - mu2) ** 2) + np.sum((np.sqrt(a) - np.sqrt(b)) ** 2)
    got = frechet_distance(mu1, _reflect(a, normals), mu2, _reflect(b, normals))
    assert got == pytest.approx(expected, rel=1e-11)
