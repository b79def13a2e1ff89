"""Frechet distance between Gaussians fitted to feature sets (FRD, FRID, FSVD, FPVD, FPD).

    d^2 = |mu1 - mu2|^2 + Tr(S1) + Tr(S2) - 2 Tr(sqrtm(S1 S2)),

with covariances from ``np.cov`` (N - 1 denominator), as in the protocol.

The anchors take ``scipy.linalg.sqrtm(S1 @ S2)`` (a Schur decomposition of a
non-symmetric matrix: complex round-off, minutes at 4096-d, unreliable when the
covariances are singular, i.e. when there are fewer samples than dimensions).
Only the trace of the square root is needed, and it is a symmetric problem:
S1 S2 is similar to F^T S2 F for any factor S1 = F F^T, whose eigenvalues are
real and non-negative, so

    Tr(sqrtm(S1 S2)) = sum_i sqrt(lambda_i(F^T S2 F)).

``trace_sqrt_product`` takes F from a Cholesky factorisation when S1 is
positive definite and from ``eigh`` (eigenvalues below the round-off level
dropped) when it is singular, then needs one symmetric eigenvalue solve. With
the features themselves at hand (``frechet_from_features``) an even better
route exists when samples are fewer than dimensions: with centred features
X1, X2, the eigenvalues of S1 S2 are the squared singular values of
X1 X2^T / sqrt((n1 - 1)(n2 - 1)), an n1 x n2 matrix, so no D x D matrix is
ever formed and no square root of round-off noise enters the sum.

Tiny negative eigenvalues from round-off are clipped; clearly negative ones
mean the input is not a covariance and raise ``InputError``. The result is
clamped at 0 (it is a squared distance) and is exactly 0 for identical
inputs.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
from scipy.linalg.blas import dtrmm

from omnilidar.errors import InputError

_EPS = np.finfo(np.float64).eps
# Eigenvalues below -_NEGATIVE_TOL * max|lambda| are not round-off: not a covariance.
_NEGATIVE_TOL = 1e-8


def _noise_floor(eigenvalues: np.ndarray) -> float:
    """Round-off level of a symmetric eigenvalue solve: dimension x eps x |A|."""
    top = float(np.max(np.abs(eigenvalues))) if eigenvalues.size else 0.0
    return 10.0 * max(1, eigenvalues.size) * _EPS * top


def _check_psd(eigenvalues: np.ndarray, what: str) -> None:
    top = float(np.max(np.abs(eigenvalues))) if eigenvalues.size else 0.0
    if eigenvalues.size and eigenvalues.min() < -_NEGATIVE_TOL * top:
        raise InputError(
            None, f"{what} is not positive semi-definite (eigenvalue {eigenvalues.min():.3g}, largest {top:.3g})"
        )


def _sum_sqrt(eigenvalues: np.ndarray, what: str) -> float:
    """Sum of square roots of eigenvalues that are PSD up to round-off; those
    at the round-off level count as zero."""
    _check_psd(eigenvalues, what)
    ev = eigenvalues[eigenvalues > _noise_floor(eigenvalues)]
    return float(np.sqrt(ev).sum())


def _psd_factor(s: np.ndarray, what: str) -> tuple[np.ndarray, bool]:
    """F with S = F F^T and whether it is triangular: Cholesky (D x D, lower)
    when S is numerically positive definite, else V sqrt(Lambda) over the
    eigenvalues above round-off (D x r)."""
    try:
        return np.linalg.cholesky(s), True
    except np.linalg.LinAlgError:
        pass
    lam, vec = np.linalg.eigh(s)
    _check_psd(lam, what)
    keep = lam > _noise_floor(lam)
    return vec[:, keep] * np.sqrt(lam[keep]), False


def trace_sqrt_product(s1: np.ndarray, s2: np.ndarray) -> float:
    """Tr(sqrtm(S1 S2)) for symmetric positive semi-definite S1, S2 (D x D)."""
    f, triangular = _psd_factor(s1, "the first covariance")
    if triangular:
        # F^T S2 F with triangular products: half the flops of two general ones
        lf = np.asfortranarray(f)
        m = dtrmm(1.0, lf, np.array(s2, order="F"), side=0, lower=1, trans_a=1)
        m = dtrmm(1.0, lf, m, side=1, lower=1, trans_a=0, overwrite_b=1)
    else:
        m = f.T @ s2 @ f
    m = (m + m.T) * 0.5  # symmetric up to round-off; make it exactly so for eigvalsh
    return _sum_sqrt(np.linalg.eigvalsh(m), "the second covariance (projected)")


def _as_vector(mu, what: str) -> np.ndarray:
    v = np.asarray(mu, dtype=np.float64)
    if v.ndim != 1:
        raise InputError(None, f"{what} must be a vector, got shape {v.shape}")
    if not np.isfinite(v).all():
        raise InputError(None, f"{what} contains NaN or Inf")
    return v


def _as_covariance(s, d: int, what: str) -> np.ndarray:
    m = np.asarray(s, dtype=np.float64)
    if m.shape != (d, d):
        raise InputError(None, f"{what} must be {d} x {d}, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise InputError(None, f"{what} contains NaN or Inf")
    scale = float(np.max(np.abs(m))) if m.size else 0.0
    if np.max(np.abs(m - m.T), initial=0.0) > 1e-8 * scale:
        raise InputError(None, f"{what} is not symmetric")
    return (m + m.T) * 0.5


def frechet_distance(mu1, sigma1, mu2, sigma2) -> float:
    """Squared Frechet distance between N(mu1, sigma1) and N(mu2, sigma2).

    Exact up to round-off, real-valued, valid for singular covariances (fewer
    samples than dimensions), and fast (a Cholesky or ``eigh`` and one
    ``eigvalsh`` of a D x D matrix). Identical covariances give exactly the
    squared mean distance.
    """
    m1 = _as_vector(mu1, "mu1")
    m2 = _as_vector(mu2, "mu2")
    if m1.shape != m2.shape:
        raise InputError(None, f"mean vectors differ in size: {m1.size} and {m2.size}")
    d = m1.size
    s1 = _as_covariance(sigma1, d, "sigma1")
    s2 = _as_covariance(sigma2, d, "sigma2")
    diff = m1 - m2
    mean_term = float(diff @ diff)
    if np.array_equal(s1, s2):
        return mean_term  # the covariance term of a Gaussian with itself is 0
    cov_term = float(np.trace(s1) + np.trace(s2)) - 2.0 * trace_sqrt_product(s1, s2)
    return max(mean_term + cov_term, 0.0)


def _as_features(x, what: str) -> np.ndarray:
    f = np.asarray(x, dtype=np.float64)
    if f.ndim != 2:
        raise InputError(None, f"{what} must be an (N, D) array, got shape {f.shape}")
    if len(f) < 2:
        raise InputError(None, f"{what} needs at least 2 samples for a covariance, got {len(f)}")
    if not np.isfinite(f).all():
        raise InputError(None, f"{what} contains NaN or Inf")
    return f


def feature_statistics(features) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and covariance (D, D) of features (N, D), float64, N - 1
    denominator (``np.cov``). Cache these for a real set used many times."""
    f = _as_features(features, "features")
    return f.mean(axis=0), np.atleast_2d(np.cov(f, rowvar=False))


def _gram_cost(n1: int, n2: int, d: int) -> float:
    return 2.0 * n1 * n2 * d + 4.0 * min(n1, n2) ** 2 * max(n1, n2)


def _covariance_cost(n1: int, n2: int, d: int) -> float:
    # two covariances, Cholesky, two products, eigvalsh (~4 d^3 with its data movement)
    return (n1 + n2) * d * d + d**3 / 3.0 + 4.0 * d**3 + 4.0 * d**3


def frechet_from_features(features_a, features_b, *, method: str = "auto") -> float:
    """Squared Frechet distance between the Gaussians fitted to two feature
    sets (N_a, D) and (N_b, D) (same value as ``frechet_distance`` on
    ``feature_statistics`` of each).

    ``method``: ``"gram"`` uses the singular values of the n_a x n_b cross
    product of centred features (best when samples are fewer than dimensions),
    ``"covariance"`` the D x D route, ``"auto"`` whichever costs fewer flops.
    """
    a = _as_features(features_a, "features_a")
    b = _as_features(features_b, "features_b")
    if a.shape[1] != b.shape[1]:
        raise InputError(None, f"feature dimensions differ: {a.shape[1]} and {b.shape[1]}")
    if method not in ("auto", "gram", "covariance"):
        raise InputError(None, f"unknown Frechet method {method!r}; use auto, gram or covariance")
    n1, n2, d = len(a), len(b), a.shape[1]
    if method == "auto":
        method = "gram" if _gram_cost(n1, n2, d) < _covariance_cost(n1, n2, d) else "covariance"
    if method == "covariance":
        return frechet_distance(*feature_statistics(a), *feature_statistics(b))

    mu_a, mu_b = a.mean(axis=0), b.mean(axis=0)
    diff = mu_a - mu_b
    mean_term = float(diff @ diff)
    if np.array_equal(a, b):
        return mean_term
    xa = (a - mu_a) / np.sqrt(n1 - 1)
    xb = (b - mu_b) / np.sqrt(n2 - 1)
    cross = scipy.linalg.svdvals(xa @ xb.T)  # singular values = sqrt(eig(S_a S_b))
    cov_term = float(np.einsum("ij,ij->", xa, xa) + np.einsum("ij,ij->", xb, xb)) - 2.0 * float(cross.sum())
    return max(mean_term + cov_term, 0.0)
