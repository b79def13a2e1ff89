"""Feature-free BEV metrics: histograms, JSD, MMD (R2Flow protocol) and LiDM's variants."""

from __future__ import annotations

import random

import numpy as np
import pytest
from scipy.spatial.distance import jensenshannon

import omnilidar.metrics.bev as bev
from omnilidar.errors import InputError
from omnilidar.lidar.scan import Scan
from omnilidar.metrics.bev import (
    BevScores,
    bev_histogram,
    bev_histograms,
    bev_jsd,
    between_scan_distance,
    bev_mmd,
    bev_scores,
    bev_scores_from_histograms,
    js_distance,
    lidm_bev_occupancies,
    lidm_bev_occupancy,
    lidm_cells,
    lidm_jsd,
    lidm_mmd,
    lidm_occupancy_sum,
    mmd_in_report_units,
    protocol_subset,
)


@pytest.fixture(scope="module")
def kitti_scans(synthetic_sweeps) -> list[np.ndarray]:
    """The points of two full HDL-64E sweeps (synthetic, KITTI's sensor)."""
    return [np.array(s.points) for s in synthetic_sweeps]


def _random_points(rng, n, extent=90.0):
    pts = rng.uniform(-extent, extent, (n, 4))
    pts[:, 2] = rng.uniform(-3, 3, n)
    return pts


# --------------------------------------------------------------------------- histogram


def test_histogram_matches_numpy_histogram2d_including_edges():
    rng = np.random.default_rng(0)
    pts = _random_points(rng, 20_000)
    edges = np.linspace(-80.0, 80.0, 101)
    # points exactly on bin edges, the outer edges included
    on_edges = np.stack([rng.choice(edges, 500), rng.choice(edges, 500), np.zeros(500), np.zeros(500)], axis=1)
    pts = np.concatenate([pts, on_edges])
    hist = bev_histogram(pts, max_range=1e9)  # no upper range cut: exercise the field bounds
    r = np.linalg.norm(pts[:, :3], axis=1)
    keep = r > 3.0
    expected, _, _ = np.histogram2d(pts[keep, 0], pts[keep, 1], bins=100, range=[[-80, 80], [-80, 80]])
    assert hist.dtype == np.float64 and hist.shape == (100, 100)
    np.testing.assert_array_equal(hist, expected)


def test_histogram_uses_3d_norm_open_band_and_x_first_orientation():
    pts = np.array(
        [
            [10.0, -20.0, 0.0],  # bin (floor(90 / 1.6), floor(60 / 1.6)) = (56, 37)
            [2.9, 0.0, 1.0],  # |xy| < 3 but |p| = 3.07 > 3: counted
            [69.9, 0.0, 5.0],  # |xy| < 70 but |p| > 70: dropped
            [3.0, 0.0, 0.0],  # |p| = 3 exactly: open interval, dropped
            [0.0, 0.0, 0.0],  # masked range-image pixel: dropped
        ]
    )
    hist = bev_histogram(pts)
    assert hist.sum() == 2
    assert hist[56, 37] == 1
    assert hist[int((2.9 + 80) // 1.6), 50] == 1


def test_histogram_accepts_scans_and_names_bad_input(kitti_scans):
    scan = Scan(kitti_scans[0])
    np.testing.assert_array_equal(bev_histogram(scan), bev_histogram(kitti_scans[0]))
    stacked = bev_histograms([scan, kitti_scans[1]])
    assert stacked.shape == (2, 100, 100)
    bad = kitti_scans[0].copy()
    bad[5, 1] = np.nan
    with pytest.raises(InputError, match="seq/000123.bin: 1 of .* non-finite"):
        bev_histograms([kitti_scans[1], bad], names=["ok.bin", "seq/000123.bin"])
    with pytest.raises(InputError, match=r"scan #0: points must be an \(N, >=3\)"):
        bev_histograms([np.zeros((10, 2))])
    assert bev_histograms([]).shape == (0, 100, 100)


def test_full_sweep_histogram_counts_the_band(kitti_scans):
    for pts in kitti_scans:
        r = np.linalg.norm(pts[:, :3].astype(np.float64), axis=1)
        hist = bev_histogram(pts)
        assert hist.sum() == np.count_nonzero((r > 3) & (r < 70))
        assert hist.sum() > 100_000


# --------------------------------------------------------------------------- JSD


def test_js_distance_matches_scipy_and_bounds():
    rng = np.random.default_rng(1)
    for _ in range(5):
        p = rng.random(10_000) * (rng.random(10_000) > 0.3)
        q = rng.random(10_000) * (rng.random(10_000) > 0.3)
        assert js_distance(p, q) == pytest.approx(float(jensenshannon(p, q)), rel=1e-12)
        assert js_distance(p, q) == pytest.approx(js_distance(q, p), rel=1e-12)
    # disjoint supports: the maximum, sqrt(ln 2)
    assert js_distance([1.0, 0.0], [0.0, 3.0]) == pytest.approx(np.sqrt(np.log(2.0)), rel=1e-15)


def test_bev_jsd_identical_sets_exactly_zero_and_scaled_sets_too(kitti_scans):
    hists = bev_histograms(kitti_scans)
    assert bev_jsd(hists, hists.copy()) == 0.0
    # JSD compares summed distributions: repeating the set changes nothing
    assert bev_jsd(hists, np.concatenate([hists, hists])) == 0.0
    assert 0.0 < bev_jsd(hists[:1], hists[1:]) < np.sqrt(np.log(2.0))


def test_bev_jsd_hand_made_case():
    a = np.zeros((2, 4))
    a[0, 0], a[1, 1] = 3.0, 1.0  # set distribution (3/4, 1/4, 0, 0)
    b = np.zeros((1, 4))
    b[0, 1] = 5.0  # (0, 1, 0, 0)
    p, q = np.array([0.75, 0.25, 0, 0]), np.array([0, 1.0, 0, 0])
    m = (p + q) / 2
    kl = lambda x, y: sum(xi * np.log(xi / yi) for xi, yi in zip(x, y) if xi > 0)  # noqa: E731
    assert bev_jsd(a, b) == pytest.approx(np.sqrt((kl(p, m) + kl(q, m)) / 2), rel=1e-14)


def test_bev_jsd_rejects_empty_set_and_bad_histograms():
    with pytest.raises(InputError, match="set B: no scan has a point"):
        bev_jsd(np.ones((2, 5)), np.zeros((3, 5)))
    with pytest.raises(InputError, match="negative"):
        bev_jsd(np.ones((2, 5)), -np.ones((3, 5)))
    with pytest.raises(InputError, match="NaN or Inf"):
        bev_jsd(np.full((2, 5), np.nan), np.ones((3, 5)))
    with pytest.raises(InputError, match="sizes differ"):
        bev_jsd(np.ones((2, 5)), np.ones((3, 6)))


# --------------------------------------------------------------------------- MMD


def _naive_mmd(a, b, sigma=0.5):
    """Direct pairwise distances (no |a|^2 + |b|^2 - 2ab expansion, no chunking)."""
    a = a.reshape(len(a), -1)
    b = b.reshape(len(b), -1)
    a = a / a.sum(axis=1, keepdims=True)
    b = b / b.sum(axis=1, keepdims=True)

    def kmean(x, y):
        d2 = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)
        return np.exp(-d2 / (2 * sigma**2)).mean()

    return kmean(a, a) + kmean(b, b) - 2 * kmean(a, b)


def test_mmd_two_point_masses_closed_form():
    a = np.zeros((1, 10, 10))
    b = np.zeros((1, 10, 10))
    a[0, 1, 2] = 7.0
    b[0, 5, 5] = 2.0
    # normalised: unit vectors at distance^2 = 2 -> 1 + 1 - 2 exp(-2 / 0.5)
    assert bev_mmd(a, b) == pytest.approx(2.0 - 2.0 * np.exp(-4.0), rel=1e-14)


def test_mmd_matches_naive_and_chunking_changes_nothing(monkeypatch):
    rng = np.random.default_rng(2)
    a = rng.poisson(3.0, (13, 20, 20)).astype(float)
    b = rng.poisson(3.0, (9, 20, 20)).astype(float) * (rng.random((9, 20, 20)) > 0.5)
    expected = _naive_mmd(a, b)
    assert bev_mmd(a, b) == pytest.approx(expected, rel=1e-10)
    monkeypatch.setattr(bev, "_BLOCK_BYTES", 8 * 20)  # a few rows per block
    assert bev_mmd(a, b) == pytest.approx(expected, rel=1e-10)


def test_mmd_terms_add_up_to_the_mmd_and_a_less_varied_set_scores_worse():
    rng = np.random.default_rng(5)
    real = rng.poisson(3.0, (12, 20, 20)).astype(float)
    varied = rng.poisson(3.0, (8, 20, 20)).astype(float)
    # The terms of the histograms bev_mmd compares (per-scan normalised; cells empty everywhere add nothing).
    def terms(a, b):
        return bev.mmd_terms(bev.normalise_per_scan(a)[0], bev.normalise_per_scan(b)[0])

    t = terms(varied, real)
    assert t["within_x"] + t["within_y"] - 2.0 * t["across"] == pytest.approx(bev_mmd(varied, real), rel=1e-12)
    # Every scan of ``alike`` is one of ``varied``'s, so each is as close to the real set as before,
    # but the set varies less: its within term rises and so does its MMD.
    alike = np.repeat(varied[:2], 4, axis=0)
    assert between_scan_distance(alike) < between_scan_distance(varied)
    assert terms(alike, real)["within_x"] > t["within_x"]
    assert bev_mmd(alike, real) > bev_mmd(varied, real)


def test_between_scan_distance_matches_naive_pairs():
    rng = np.random.default_rng(6)
    hists = rng.poisson(2.0, (7, 10, 10)).astype(float)
    flat = (hists / hists.sum(axis=(1, 2), keepdims=True)).reshape(7, -1)
    naive = np.mean([np.sum((flat[i] - flat[j]) ** 2) for i in range(7) for j in range(7) if i != j])
    assert between_scan_distance(hists) == pytest.approx(naive, rel=1e-10)
    across = np.mean([np.sum((flat[i] - flat[j]) ** 2) for i in range(3) for j in range(3, 7)])
    assert between_scan_distance(hists[:3], hists[3:]) == pytest.approx(across, rel=1e-10)
    assert between_scan_distance(np.repeat(hists[:1], 3, axis=0)) == pytest.approx(0.0, abs=1e-12)  # rounding only
    with pytest.raises(InputError, match="2 non-empty scans"):
        between_scan_distance(np.concatenate([hists[:1], np.zeros((2, 10, 10))]))


def test_mmd_identical_sets_about_zero_and_never_negative(kitti_scans):
    hists = bev_histograms(kitti_scans)
    value = bev_mmd(hists, hists.copy())
    assert 0.0 <= value < 1e-15
    assert bev_mmd(hists[:1], hists[1:]) > 1e-8


def test_mmd_empty_scans_are_left_out_and_counted():
    rng = np.random.default_rng(3)
    real = rng.poisson(2.0, (6, 10, 10)).astype(float)
    gen = rng.poisson(2.0, (4, 10, 10)).astype(float)
    with_empty = np.concatenate([gen, np.zeros((2, 10, 10))])
    assert bev_mmd(real, with_empty) == bev_mmd(real, gen)
    scores = bev_scores_from_histograms(real, with_empty)
    assert scores.empty_generated == 2 and scores.n_generated == 6 and scores.empty_real == 0
    assert np.isfinite(scores.mmd) and np.isfinite(scores.jsd)
    with pytest.raises(InputError, match="every scan is empty"):
        bev_mmd(real, np.zeros((3, 10, 10)))


def test_report_units():
    assert mmd_in_report_units(1.12e-4) == pytest.approx(1.12)
    s = BevScores("r2flow", 0.03, 2.5e-4, 10, 10, 0, 0)
    assert s.mmd_1e4 == pytest.approx(2.5) and s.to_dict()["mmd_1e4"] == pytest.approx(2.5)


# --------------------------------------------------------------------------- real subset


def test_protocol_subset_reproduces_r2flow_shuffle():
    n = 12_345
    perm = list(range(n))
    random.Random(0).shuffle(perm)
    np.testing.assert_array_equal(protocol_subset(n), perm[:10_000])
    small = protocol_subset(50, seed=3)
    assert sorted(small.tolist()) == list(range(50))
    np.testing.assert_array_equal(small, protocol_subset(50, seed=3))
    assert not np.array_equal(small, protocol_subset(50, seed=4))


def test_scores_use_the_subset_of_the_real_set():
    rng = np.random.default_rng(4)
    real = rng.poisson(2.0, (30, 8, 8)).astype(float)
    gen = rng.poisson(2.0, (5, 8, 8)).astype(float)
    scores = bev_scores_from_histograms(real, gen, real_limit=10, seed=7)
    pick = protocol_subset(30, 10, 7)
    assert scores.n_real == 10
    assert scores.jsd == bev_jsd(real[pick], gen)
    assert scores.mmd == pytest.approx(bev_mmd(real[pick], gen), rel=1e-14)


# --------------------------------------------------------------------------- LiDM variants


def test_lidm_cells_open_box_and_indexing():
    pts = np.array(
        [
            [0.01, 0.01, 0.0],  # 5 cm cell (1000, 1000) on the 2000 x 2000 64-beam grid
            [0.02, 0.03, 9.0],  # same cell (no range filter, z ignored)
            [-49.99, 49.99, 0.0],  # (0, 1999)
            [50.0, 0.0, 0.0],  # on the open bound: dropped
            [0.0, -60.0, 0.0],  # outside: dropped
        ]
    )
    flat, shape = lidm_cells(pts)
    assert shape == (2000, 2000)
    assert flat.tolist() == sorted([1000 * 2000 + 1000, 0 * 2000 + 1999])
    occ = lidm_bev_occupancy(pts, grid="32")  # 0.5 m cells, +-30 m
    assert occ.shape == (120, 120) and occ.sum() == 1 and occ[60, 60]


def test_lidm_occupancy_sum_counts_scans_not_points():
    a = np.array([[1.0, 1.0, 0.0], [1.01, 1.01, 0.0]])  # one 5 cm cell twice
    b = np.array([[1.0, 1.0, 0.0]])
    total = lidm_occupancy_sum([a, b])
    assert total.sum() == 2 and total.max() == 2


def test_lidm_jsd_identical_and_disjoint():
    a = [np.array([[1.0, 1.0, 0.0]])]
    b = [np.array([[-7.0, 3.0, 0.0]])]
    sa, sb = lidm_occupancy_sum(a), lidm_occupancy_sum(b)
    assert lidm_jsd(sa, sa.copy()) == 0.0
    assert lidm_jsd(sa, sb) == pytest.approx(np.sqrt(np.log(2.0)), rel=1e-15)
    with pytest.raises(InputError, match="no scan has a point"):
        lidm_jsd(sa, np.zeros_like(sa))
    with pytest.raises(InputError, match="unknown LiDM grid"):
        lidm_occupancy_sum(a, grid="128")


def _brute_force_lidm_mmd(ref, smp):
    def cells(o):
        i, j = np.nonzero(o)
        return np.stack([i / o.shape[0], j / o.shape[1]], axis=1)

    def chamfer(p, q):
        d2 = ((p[:, None, :] - q[None, :, :]) ** 2).sum(-1)
        return 0.5 * (d2.min(axis=1).mean() + d2.min(axis=0).mean())

    return np.mean([min(chamfer(cells(r), cells(s)) for s in smp) for r in ref])


def test_lidm_mmd_single_cells_closed_form():
    ref = np.zeros((1, 120, 120), bool)
    smp = np.zeros((1, 120, 120), bool)
    ref[0, 10, 20] = True
    smp[0, 13, 24] = True  # 3-4-5 triangle: squared distance 25 cells^2 both ways
    value, empty_ref, empty_smp = lidm_mmd(ref, smp)
    assert value == pytest.approx(25.0 / 120**2, rel=1e-15)
    assert (empty_ref, empty_smp) == (0, 0)


def test_lidm_mmd_matches_brute_force_chamfer(monkeypatch):
    rng = np.random.default_rng(5)
    ref = rng.random((5, 40, 40)) < 0.03
    smp = rng.random((7, 40, 40)) < 0.05
    expected = _brute_force_lidm_mmd(ref, smp)
    assert lidm_mmd(ref, smp)[0] == pytest.approx(expected, rel=1e-13)
    monkeypatch.setattr(bev, "_BLOCK_BYTES", 8 * 40 * 40 * 2 * 2)  # 2 x 2 blocks
    assert lidm_mmd(ref, smp)[0] == pytest.approx(expected, rel=1e-13)
    # non-square grid: the per-axis normalisation path
    ref2, smp2 = ref[:, :, :30], smp[:, :, :30]
    assert lidm_mmd(ref2, smp2)[0] == pytest.approx(_brute_force_lidm_mmd(ref2, smp2), rel=1e-12)


def test_lidm_mmd_identical_zero_and_empty_policy():
    rng = np.random.default_rng(6)
    occ = rng.random((4, 50, 50)) < 0.02
    assert lidm_mmd(occ, occ.copy())[0] == 0.0
    with_empty = np.concatenate([occ, np.zeros((1, 50, 50), bool)])
    value, empty_ref, empty_smp = lidm_mmd(with_empty, occ)
    assert value == 0.0 and empty_ref == 1 and empty_smp == 0
    with pytest.raises(InputError, match="sample set: every scan is empty"):
        lidm_mmd(occ, np.zeros((2, 50, 50), bool))


# --------------------------------------------------------------------------- both variants end to end


@pytest.mark.parametrize("variant", ["r2flow", "lidm"])
def test_bev_scores_on_full_sweeps(kitti_scans, variant):
    scans = [Scan(p) for p in kitti_scans]
    same = bev_scores(scans, scans, variant=variant)
    assert same.variant == variant and same.jsd == 0.0 and 0.0 <= same.mmd < 1e-15
    # a "generated" set: the second scan, plus a degenerate all-masked one
    masked = np.zeros((64 * 1024, 4), np.float32)
    other = bev_scores(scans[:1], [kitti_scans[1], masked], variant=variant)
    assert other.empty_generated == 1 and other.n_generated == 2 and other.n_real == 1
    for v in (other.jsd, other.mmd, other.mmd_1e4):
        assert np.isfinite(v) and v > 0.0


def test_bev_scores_rejects_unknown_variant(kitti_scans):
    with pytest.raises(InputError, match="unknown BEV metric variant"):
        bev_scores(kitti_scans, kitti_scans, variant="lidargen")


def test_lidm_occupancies_stack(kitti_scans):
    occ = lidm_bev_occupancies(kitti_scans)
    assert occ.shape == (2, 200, 200) and occ.dtype == bool
    assert lidm_bev_occupancies([]).shape == (0, 200, 200)
