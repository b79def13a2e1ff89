"""Ground estimation for any platform: vehicle, drone at altitude, quadruped.

Method (deterministic, vectorised, no learned prior):

1. Level the cloud: rotate the sensor frame by the mount pitch
   (``sensor.mount_pitch_deg``, nose-down positive) so that +z is (nearly) up.
   Clouds stored already levelled (the synthetic world does so) are detected:
   both frames go through steps 2-4 and the one whose cell minima put more
   cells on the fitted plane wins.
2. Bird's-eye grid (``cell_size`` metres, within ``sensor.max_range``): the lowest
   point of each cell is its ground candidate (a cell holding any ground return
   has a ground return as its minimum, whatever stands on top of it).
3. Ground height prior: ``-sensor.mount_height``. A fallback search takes the
   densest height layer of the cell minima instead when that layer lies below
   the sensor, spans at least 20 cells and holds more than twice the cells of
   the prior's window (wrong or unknown mount height).
4. Robust plane through the cell minima: least squares, re-fitted with a
   shrinking inlier band (1.0 -> 0.5 -> 0.3 m scaled by the prior's spread). This
   absorbs residual tilt (roll, pitch error, a road on a slope).
5. Local ground: cells whose minimum lies within a band around the plane (wider
   with distance, for gentle hills) are smoothed into a local reference height
   (normalised box filter). A cell is a ground cell when its minimum is within
   ``step`` of its neighbourhood's reference (curbs pass, a car roof or a bumper
   whose cell hides the road does not); other cells take the reference height.
6. A point is ground iff its height above the local ground of its cell is in
   [-below, above]. Points beyond the grid use the plane alone.

Differences from the anchors (LiDAR_snow_sim / Robo3D ``calculate_plane``):
their RANSAC plane fit on a hard-coded box in front of a car (z < -1.55, 10-70 m
ahead) fails silently on scikit-learn >= 1.2 and falls back to a plane *above*
the sensor; its 1.73 m car prior is useless for drones and quadrupeds. This
module has no hard-coded platform box, handles pitch and height per sensor and
follows local ground (slopes, curbs) instead of one global plane.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec

# Raw SemanticKITTI ids that are ground: road, parking, sidewalk, other-ground,
# lane-marking, terrain.
GROUND_LABELS = (40, 44, 48, 49, 60, 72)

# Tunables (metres unless noted); estimate_ground takes overrides.
CELL_SIZE = 1.0
ABOVE = 0.2  # max height above local ground
BELOW = 0.5  # max depth below local ground (only where the cell's ground is interpolated)
STEP = 0.3  # max jump of a cell's minimum from its neighbourhood's reference
MAX_SLOPE = 0.5  # |dz/dx|, |dz/dy| limit of the global plane (about 27 deg)
MIN_FALLBACK_CELLS = 20  # cells a height layer needs to override the mount-height prior


def ground_truth_mask(semantic: np.ndarray) -> np.ndarray:
    """Ground mask from raw SemanticKITTI ids (``label & 0xFFFF``)."""
    return np.isin(np.asarray(semantic), GROUND_LABELS)


def up_vector(sensor: SensorSpec) -> np.ndarray:
    """World 'up' expressed in the sensor frame, from the mount pitch.

    A sensor pitched nose-down by phi has its x axis pointing forward-down, so
    world up is (-sin phi, 0, cos phi) in sensor coordinates.
    """
    phi = np.deg2rad(sensor.mount_pitch_deg)
    return np.array([-np.sin(phi), 0.0, np.cos(phi)])


def level(xyz: np.ndarray, sensor: SensorSpec) -> np.ndarray:
    """Rotate sensor-frame points (N, 3) into the levelled frame (+z up), float64."""
    return _level_pitch(np.asarray(xyz, np.float64), sensor.mount_pitch_deg)


def fit_plane_normal(xyz: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Unit normal of the least-squares plane through points (N, 3), oriented
    like ``prior`` (a unit vector); ``prior`` itself when the points do not
    define a plane (fewer than 3, collinear, or a normal more than 60 deg off)."""
    xyz = np.asarray(xyz, np.float64)
    prior = np.asarray(prior, np.float64) / np.linalg.norm(prior)
    if len(xyz) < 3:
        return prior
    centred = xyz - xyz.mean(axis=0)
    cov = centred.T @ centred / len(xyz)
    if not np.all(np.isfinite(cov)):
        return prior
    evals, evecs = np.linalg.eigh(cov)  # ascending
    # Degenerate: no clear smallest direction (a line or a blob, not a plane).
    if evals[1] <= 1e-12 or evals[0] > 0.5 * evals[1]:
        return prior
    n = evecs[:, 0]
    if n @ prior < 0:
        n = -n
    return n if n @ prior > 0.5 else prior


def _fit_height_plane(x, y, z, z0, bands):
    """z = a x + b y + c through (x, y, z), starting at the level plane z = z0
    and refitting on the points within each successive band. Returns (a, b, c)."""
    a = b = 0.0
    c = z0
    for band in bands:
        inl = np.abs(z - (a * x + b * y + c)) < band
        if inl.sum() < 3:
            break
        xi, yi, zi = x[inl], y[inl], z[inl]
        A = np.stack([xi, yi, np.ones_like(xi)], axis=1)
        sol, *_ = np.linalg.lstsq(A, zi, rcond=None)
        # x and y spread too small to tilt (e.g. points on a line): level plane.
        if np.ptp(xi) < 2.0 or np.ptp(yi) < 2.0 or not np.all(np.isfinite(sol)):
            a, b, c = 0.0, 0.0, float(np.median(zi))
            continue
        a, b = np.clip(sol[:2], -MAX_SLOPE, MAX_SLOPE)
        c = float(np.median(zi - a * xi - b * yi))
    return float(a), float(b), float(c)


def _prior_height(m: np.ndarray, z0: float, window: float) -> float:
    """The ground height to start from: the prior z0 unless the densest layer of
    cell minima lies below the sensor, spans at least MIN_FALLBACK_CELLS cells
    and holds more than twice as many cells as the prior's window."""
    support_prior = np.count_nonzero(np.abs(m - z0) < window)
    lo, hi = float(m.min()), float(m.max())
    nbins = max(1, int(np.ceil((hi - lo) / window)))
    hist, edges = np.histogram(m, bins=nbins, range=(lo, lo + nbins * window))
    k = int(np.argmax(hist))
    mode = float(np.median(m[(m >= edges[k]) & (m <= edges[k + 1])]))
    support_mode = np.count_nonzero(np.abs(m - mode) < window)
    use_mode = mode < 0 and support_mode >= MIN_FALLBACK_CELLS and support_mode > 2 * support_prior
    return mode if use_mode else z0


def _box_mean(values: np.ndarray, weights: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Weighted box-filter mean of a 2-D grid; returns (mean, weight sum)."""
    num = ndimage.uniform_filter(values * weights, size=size, mode="constant")
    den = ndimage.uniform_filter(weights, size=size, mode="constant")
    mean = np.where(den > 1e-9, num / np.maximum(den, 1e-9), 0.0)
    return mean, den


def _level_pitch(xyz: np.ndarray, pitch_deg: float) -> np.ndarray:
    phi = np.deg2rad(pitch_deg)
    c, s = np.cos(phi), np.sin(phi)
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    return np.stack([c * x + s * z, y, -s * x + c * z], axis=1)


def _grid_plane(p: np.ndarray, sensor: SensorSpec, cell_size: float):
    """Cell minima of levelled points p and the robust plane through them.
    Returns (cell index per point or -1, cell minima, grid side, plane (a, b, c),
    window, score = cells within the final band of the plane)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    half = int(np.ceil(sensor.max_range / cell_size)) + 1
    side = 2 * half
    ix = np.floor(x / cell_size).astype(np.int64) + half
    iy = np.floor(y / cell_size).astype(np.int64) + half
    in_grid = (ix >= 0) & (ix < side) & (iy >= 0) & (iy < side)
    cell = np.where(in_grid, ix * side + iy, -1)
    cmin = np.full(side * side, np.inf)
    np.minimum.at(cmin, cell[in_grid], z[in_grid])
    occ = np.flatnonzero(np.isfinite(cmin))
    cx = (occ // side - half + 0.5) * cell_size
    cy = (occ % side - half + 0.5) * cell_size
    m = cmin[occ]
    h0 = max(sensor.mount_height, 0.1)
    window = max(0.5, 0.25 * h0)
    z0 = _prior_height(m, -h0, window) if len(m) else -h0
    plane = _fit_height_plane(cx, cy, m, z0, (2 * window, window, 0.6 * window))
    a, b, c = plane
    score = int(np.count_nonzero(np.abs(m - (a * cx + b * cy + c)) < 0.6 * window))
    return cell, cmin, side, half, plane, window, score


def estimate_ground(
    scan: Scan,
    sensor: SensorSpec,
    rng: np.random.Generator | None = None,
    *,
    cell_size: float = CELL_SIZE,
    above: float = ABOVE,
    below: float = BELOW,
    step: float = STEP,
) -> np.ndarray:
    """Boolean ground mask (N,) for a scan from any platform.

    The cloud may be in the pitched sensor frame or already levelled (the
    synthetic world and some datasets store levelled clouds): both frames are
    tried and the one whose cell minima fit a plane best is used.
    ``rng`` is accepted for interface symmetry with the effects; the method is
    deterministic and draws nothing. Non-finite points are never ground.
    """
    n = len(scan)
    mask = np.zeros(n, bool)
    if n == 0:
        return mask
    xyz = np.asarray(scan.xyz, np.float64)
    ok = np.all(np.isfinite(xyz), axis=1)
    if not ok.any():
        return mask
    idx_ok = np.flatnonzero(ok)
    xyz = xyz[ok]

    # Level with the mount pitch, or take the cloud as already levelled.
    pitches = [sensor.mount_pitch_deg] + ([0.0] if sensor.mount_pitch_deg != 0.0 else [])
    best = None
    for pitch in pitches:
        p = _level_pitch(xyz, pitch)
        fit = _grid_plane(p, sensor, cell_size)
        if best is None or fit[-1] > best[1][-1]:
            best = (p, fit)
    p, (cell, cmin, side, half, (a, b, c), window, _) = best
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    in_grid = cell >= 0
    occ = np.flatnonzero(np.isfinite(cmin))
    cx = (occ // side - half + 0.5) * cell_size
    cy = (occ % side - half + 0.5) * cell_size

    # Local ground relative to the plane: band cells -> neighbourhood reference ->
    # ground cells (within `step` of the reference) -> interpolated elsewhere.
    res = np.zeros(side * side)
    res[occ] = cmin[occ] - (a * cx + b * cy + c)
    band = np.zeros(side * side, bool)
    band[occ] = np.abs(res[occ]) < np.minimum(0.6 * window + 0.02 * np.hypot(cx, cy), 2 * window)
    grid_res = res.reshape(side, side)
    ref, _ = _box_mean(grid_res, band.reshape(side, side).astype(np.float64), 5)
    ground_cell = band & (np.abs(res - ref.ravel()) <= step)
    weights = ground_cell.reshape(side, side).astype(np.float64)
    ref2, den = _box_mean(grid_res, weights, 5)
    ref_wide, den_wide = _box_mean(grid_res, weights, 11)
    local = np.where(den > 1e-9, ref2, np.where(den_wide > 1e-9, ref_wide, 0.0)).ravel()
    local = np.where(ground_cell, res, local)

    # Per-point height above local ground.
    h = z - (a * x + b * y + c)
    h = h - np.where(in_grid, local[np.maximum(cell, 0)], 0.0)
    mask[idx_ok] = (h <= above) & (h >= -below)
    return mask


def mask_scores(pred: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Precision, recall and IoU of a predicted boolean mask against the truth
    (1.0 where the denominator is empty)."""
    pred = np.asarray(pred, bool)
    truth = np.asarray(truth, bool)
    tp = np.count_nonzero(pred & truth)
    fp = np.count_nonzero(pred & ~truth)
    fn = np.count_nonzero(~pred & truth)
    div = lambda a, b: float(a / b) if b else 1.0  # noqa: E731
    return {"precision": div(tp, tp + fp), "recall": div(tp, tp + fn), "iou": div(tp, tp + fp + fn)}
