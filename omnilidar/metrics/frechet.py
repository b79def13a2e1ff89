"""Frechet distance between Gaussians fitted to feature sets (FRD, FRID, FSVD, FPVD, FPD).

    d^2 = |mu1 - mu2|^2 + Tr(S1) + Tr(S2) - 2 Tr(sqrtm(S1 S2)),

with covariances from ``np.cov`` (N - 1 denominator), as in the protocol.

The anchors take ``scipy.linalg.sqrtm(S1 @ S2)`` (a Schur decomposition of a
non-symmetric matrix: complex round-off, minutes at 4096-d, unreliable when the
covariances are singular, i.e. when there are fewer samples than dimensions).
Only the trace of the square root is needed, and it is a symmetric problem:
for factors S1 = F1 F1^T and S2 = F2 F2^T, S1 S2 is similar to
(F1^T F2)(F1^T F2)^T, so its eigenvalues are the squared singular values of
F1^T F2 and

    Tr(sqrtm(S1 S2)) = sum_i sigma_i(F1^T F2)      (the nuclear norm).

``trace_sqrt_product`` restricts both covariances to their common support (rows
exactly zero in either, dead feature units, add only zero eigenvalues), then
takes each factor from a Cholesky factorisation when the covariance is positive
definite, else from ``eigh`` over the eigenvalues above the round-off level of
that solve (below it the computed covariance carries no information; this keeps
round-off noise of a singular covariance out of the sum). The squared singular
values of G = F1^T F2 are, when both factors are Cholesky factors, the
eigenvalues of the smaller of G G^T and G^T G, positive semi-definite by
construction: negative ones are round-off and count as 0, and no positive one
is dropped. (An earlier version dropped eigenvalues of F1^T S2 F1 below
10 D eps x the largest: at 1024-d with feature standard deviations spread over
three decades it lost genuine ones and was 1e-5 relative off; now 1e-14.) When
a covariance is singular, G has singular values near 0 (where the two supports
meet at wide angles) and squaring them would leave sqrt(eps)-sized round-off in
the sum (1e-11 relative with 300 samples in 512-d); there the singular values
come from ``svdvals(G)``, two to three times the cost of that last step.

With the features themselves at hand (``frechet_from_features``) the same
identity gives the Gram route when samples are fewer than dimensions: with
centred features X1, X2, F_i = X_i^T / sqrt(n_i - 1), so
F1^T F2 = X1 X2^T / sqrt((n1 - 1)(n2 - 1)), an n1 x n2 matrix whose singular
values are summed; no D x D matrix is ever formed.

Clearly negative eigenvalues of a covariance raise ``InputError``. The result
is clamped at 0 (it is a squared distance) and is exactly 0 for identical
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
    """Round-off level of a symmetric eigenvalue solve: 10 x dimension x eps x |A|
    (the numerical rank of a singular covariance)."""
    top = float(np.max(np.abs(eigenvalues))) if eigenvalues.size else 0.0
    return 10.0 * max(1, eigenvalues.size) * _EPS * top


def _check_psd(eigenvalues: np.ndarray, what: str) -> None:
    top = float(np.max(np.abs(eigenvalues))) if eigenvalues.size else 0.0
    if eigenvalues.size and eigenvalues.min() < -_NEGATIVE_TOL * top:
        raise InputError(
            None, f"{what} is not positive semi-definite (eigenvalue {eigenvalues.min():.3g}, largest {top:.3g})"
        )


def _psd_factor(s: np.ndarray, what: str) -> tuple[np.ndarray, bool]:
    """F with S = F F^T (D x r) and whether it is a plain Cholesky factor:
    Cholesky when S is numerically positive definite (nothing dropped), else
    V sqrt(Lambda) over the eigenvalues above the round-off level of ``eigh``."""
    try:
        return np.linalg.cholesky(s), True
    except np.linalg.LinAlgError:
        pass
    lam, vec = np.linalg.eigh(s)
    _check_psd(lam, what)
    keep = lam > _noise_floor(lam)
    return vec[:, keep] * np.sqrt(lam[keep]), False


def trace_sqrt_product(s1: np.ndarray, s2: np.ndarray) -> float:
    """Tr(sqrtm(S1 S2)) for symmetric positive semi-definite S1, S2 (D x D):
    the sum of singular values of G = F1^T F2: from ``svdvals(G)`` when a
    covariance is singular, else from the eigenvalues of the smaller of G G^T
    and G^T G (positive semi-definite by construction, so negative eigenvalues
    are round-off and count as 0; nothing else dropped)."""
    for s, what in ((s1, "the first covariance"), (s2, "the second covariance")):
        if np.any(np.diagonal(s) < 0.0):
            raise InputError(None, f"{what} is not positive semi-definite (negative variance)")
    # A row that is exactly zero in either (a dead feature unit) adds only zero
    # eigenvalues to S1 S2: restrict both to the common support, so that such
    # rows neither push a covariance off the Cholesky route nor leave round-off
    # zeros in G G^T whose square roots would count.
    common = np.flatnonzero(np.any(s1 != 0.0, axis=1) & np.any(s2 != 0.0, axis=1))
    if common.size < len(s1):
        s1, s2 = s1[np.ix_(common, common)], s2[np.ix_(common, common)]
    f1, lower1 = _psd_factor(s1, "the first covariance")
    f2, lower2 = _psd_factor(s2, "the second covariance")
    if f1.shape[1] == 0 or f2.shape[1] == 0:
        return 0.0
    # a triangular product where a factor is a plain Cholesky factor: half the flops
    if lower1:
        g = dtrmm(1.0, np.asfortranarray(f1), np.array(f2, order="F"), side=0, lower=1, trans_a=1)
    elif lower2:
        g = dtrmm(1.0, np.asfortranarray(f2), np.array(f1, order="F"), side=0, lower=1, trans_a=1).T
    else:
        g = f1.T @ f2
    if not (lower1 and lower2):
        # a singular covariance: G has singular values near 0 wherever the two
        # supports meet at a wide angle, and squaring them (G G^T) would put
        # sqrt(eps)-sized round-off into the sum; the SVD keeps them exact
        return float(scipy.linalg.svdvals(g).sum())
    gram = g @ g.T if g.shape[0] <= g.shape[1] else g.T @ g
    return float(np.sqrt(np.clip(np.linalg.eigvalsh(gram), 0.0, None)).sum())


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
    ``eigvalsh``, or for a singular covariance ``svdvals``, of a D x D matrix).
    Identical covariances give exactly the squared mean distance.
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
