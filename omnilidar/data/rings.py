"""Ring (beam index) recovery from geometry, and Beam-32 style beam reduction.

Points are in the sensor frame, so a point's elevation says which laser fired it.
Two facts of real spinning LiDARs make plain nearest-angle binning against the data
sheet unreliable, and both are measured on the KITTI HDL-64E scans shipped with the
tests:

* each unit's beam angles differ from the nominal table (KITTI: by up to 0.7 deg,
  more than the 0.33 / 0.5 deg beam pitch);
* each laser sits at a height offset ``h_b`` on the spinning head (KITTI: about
  0.20 m upper block, 0.12 m lower block), so the apparent elevation seen from the
  origin is ``tan(phi) = tan(theta_b) + h_b / rho`` (rho = horizontal distance):
  about +2 deg for a wall 5 m away.

So the default is a per-scan calibration that needs neither point order nor a
full sweep: in the plane (s = 1 / rho, y = z / rho) every laser is a straight line
``y = t_b + h_b s``. A Hough transform over the slope ``h`` finds the lines
(peaks of the intercept histogram), they are matched to the sensor's beams in
elevation order, refined by a few rounds of assignment + per-line least squares,
and each point takes the nearest line.

Before that, a scan whose file order is the sensor's firing order (raw KITTI,
SemanticKITTI and KITTI-360 ``.bin`` files are stored laser by laser, each laser one
revolution starting at azimuth 0, top laser first) gets its lasers from that order:
the unwrapped azimuth counts revolutions. The order is accepted only when it
checks out (exactly one revolution per beam, azimuth running forward, per-laser
median elevations strictly descending), so cropped, thinned or shuffled scans go
to the calibration. SemanticKITTI sweeps need it: they are ego-motion compensated,
so near returns of the lower lasers move off their line by up to a beam pitch and
the line model fails (measured on sequence 00 scan 0: 28 % of the points over a
quarter pitch from their line).

Only if both fail (too few points, beams missing) does nearest-angle binning
against the nominal table decide, with a :class:`RingRecoveryWarning`;
:func:`ring_recovery` says which method labelled the scan.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter

from omnilidar.errors import InputError
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec, levelled_to_sensor

# Hough search over the per-laser height offset h (metres).
_H_MAX = 0.4
_H_STEP = 0.01
# Points closer than this (horizontally) are evaluated as if at this distance: their
# elevation is dominated by the laser's offset, and the origin has none.
_RHO_FLOOR = 0.5
# Calibration needs this many usable points per beam on average.
_MIN_POINTS_PER_BEAM = 20
_REFINE_ITERS = 3
_CHUNK = 16384
# Firing order: azimuth steps backwards by more than this (radians) are allowed
# only this often per beam (ego-motion compensation nudges a few points back).
_BACKSTEP = np.deg2rad(5.0)
_MAX_BACKSTEPS_PER_BEAM = 0.25

# How a scan's rings were found (recorded by the domain builder).
RING_METHODS = ("scan", "unit_calibration", "firing_order", "scan_calibration", "scan_calibration_partial_view",
                "nominal")
# A sweep whose points fill less than this share of the 1-degree azimuth bins is a partial view
# (a camera-view crop): its per-scan calibration sees each beam over a short arc and, measured on a
# +-45 deg crop of a real KITTI sweep, agrees with the firing order on only 97.5 % of the points.
FULL_VIEW_AZIMUTH_SHARE = 0.9


class RingRecoveryWarning(UserWarning):
    """Ring recovery fell back to the nominal beam table (rings are unreliable)."""


def _elevation_points(points: np.ndarray, pitch_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """finite mask, s = 1 / max(rho, floor), y = z / max(rho, floor) (float64), in the
    sensor's own frame (levelled points of a pitched sensor are rotated back)."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4, 5):
        raise InputError(None, f"recover_rings: points must be (N, 3|4|5), got shape {pts.shape}")
    xyz = pts[:, :3].astype(np.float64)
    finite = np.isfinite(xyz).all(axis=1)
    xyz[~finite] = 0.0
    xyz = levelled_to_sensor(xyz, pitch_deg)
    rho = np.maximum(np.hypot(xyz[:, 0], xyz[:, 1]), _RHO_FLOOR)
    return finite, 1.0 / rho, xyz[:, 2] / rho


def _nominal_rings(y: np.ndarray, sensor: SensorSpec) -> np.ndarray:
    """Nearest nominal beam by elevation angle (no calibration)."""
    elev = np.sort(sensor.elevations_rad)  # ascending
    mids = 0.5 * (elev[1:] + elev[:-1])
    ascending = np.searchsorted(mids, np.arctan(y))
    return (sensor.num_beams - 1 - ascending).astype(np.int64)


def _hough_lines(s: np.ndarray, y: np.ndarray, sensor: SensorSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate lines (intercept t, slope h, votes) from the Hough accumulator."""
    t_nom = np.tan(np.sort(sensor.elevations_rad))
    pitch = float(np.min(np.diff(t_nom))) if len(t_nom) > 1 else 0.01
    width = pitch / 12.0  # intercept bin width
    lo = t_nom[0] - 0.05
    hi = t_nom[-1] + 0.05
    nbins = int(np.ceil((hi - lo) / width)) + 1
    slopes = np.arange(-_H_MAX, _H_MAX + 0.5 * _H_STEP, _H_STEP)
    acc = np.zeros((len(slopes), nbins), np.float64)
    for k, h in enumerate(slopes):
        b = np.floor((y - h * s - lo) / width).astype(np.int64)
        b = b[(b >= 0) & (b < nbins)]
        acc[k] = np.bincount(b, minlength=nbins)
    # Smooth along the intercept so a line split across two bins still peaks.
    acc = acc[:, :-2] + 2.0 * acc[:, 1:-1] + acc[:, 2:]
    # Slope per intercept: the one that makes the neighbourhood (a few beams) sharpest.
    # Choosing it per bin instead would let any intercept find some slope at which
    # unrelated points happen to line up.
    half = max(1, int(3.0 * pitch / width))
    csum = np.cumsum(np.pad(acc * acc, ((0, 0), (half + 1, half))), axis=1)
    sharp = csum[:, 2 * half + 1 :] - csum[:, : -2 * half - 1]
    best_k = np.argmax(sharp, axis=0)
    # Ground returns of a beam sit at one distance, so they are sharp at any slope
    # and leave the choice nearly flat there: take the running median so the slope
    # varies smoothly with elevation and a peak is read at one consistent slope.
    best_k = median_filter(best_k, size=4 * half + 1, mode="nearest")
    profile = acc[best_k, np.arange(acc.shape[1])]
    # Local maxima of the best-slope profile, at least 0.6 of the local nominal beam
    # pitch apart (shoulders of a slightly mis-sloped line are not lines).
    centres = lo + (np.arange(len(profile)) + 1.5) * width
    local_pitch = np.interp(centres, 0.5 * (t_nom[1:] + t_nom[:-1]), np.diff(t_nom)) if len(t_nom) > 1 else None
    sep = np.maximum(1, (0.6 * (pitch if local_pitch is None else local_pitch) / width).astype(np.int64))
    order = np.argsort(-profile, kind="stable")
    taken = np.zeros(len(profile), bool)
    peaks = []
    for i in order:
        if profile[i] <= 0:
            break
        if taken[i]:
            continue
        peaks.append(i)
        taken[max(0, i - sep[i]) : i + sep[i] + 1] = True
        if len(peaks) >= 4 * sensor.num_beams:
            break
    peaks = np.asarray(sorted(peaks), np.int64)
    t = lo + (peaks + 1.5) * width  # centre of the smoothed bin
    return t, slopes[best_k[peaks]], profile[peaks]


def _match_to_beams(t_peaks: np.ndarray, votes: np.ndarray, sensor: SensorSpec) -> tuple[np.ndarray, np.ndarray]:
    """Pick the lines that are beams and say which beam each is.

    If at least ``num_beams`` clear lines exist, the strongest ones in elevation
    order are the beams. Otherwise (beams missing, e.g. an already thinned scan) a
    monotone alignment (peaks and beams in elevation order, either may be
    skipped) against the nominal angles under an affine correction
    ``alpha + beta * nominal`` that is refitted from the matches: real units deviate
    from the data sheet by more than a beam pitch, but almost affinely (KITTI:
    residual < 0.15 deg). Returns the intercepts of the matched lines (ascending)
    and their beam ids (0 = top).
    """
    n_beams = sensor.num_beams
    strong = votes >= 0.25 * np.median(np.sort(votes)[::-1][:n_beams])
    if strong.sum() >= n_beams:
        # Every beam shows: the strongest num_beams lines in elevation order are the
        # beams (measured on KITTI, this beats the alignment, whose affine model is
        # off by up to 0.15 deg at the bottom of the HDL-64E).
        keep = np.argsort(-votes, kind="stable")[:n_beams]
        t_keep = np.sort(t_peaks[keep])
        return t_keep, np.arange(n_beams - 1, -1, -1)
    order = np.argsort(t_peaks)
    a = np.arctan(t_peaks[order])
    v = votes[order]
    b = np.sort(sensor.elevations_rad)  # ascending
    pitch = np.gradient(b) if n_beams > 1 else np.ones(1)
    # Skipping a strong line costs more than skipping a weak one (noise peaks).
    skip_peak = np.clip(v / max(np.median(np.sort(v)[::-1][:n_beams]), 1.0), 0.05, 2.0)
    best = None
    for shift in np.deg2rad(np.arange(-1.0, 1.0001, 0.1)):
        alpha, beta = shift, 1.0
        for _ in range(4):
            cost, match = _align(a, alpha + beta * b, pitch, skip_peak, 1.0)
            hit = match >= 0
            if hit.sum() < 2:
                break
            w = v[hit]
            design = np.stack([np.ones(hit.sum()), b[match[hit]]], axis=1) * w[:, None]
            alpha, beta = np.linalg.lstsq(design, a[hit] * w, rcond=None)[0]
        if best is None or cost < best[0]:
            best = (cost, match)
    match = best[1]
    hit = match >= 0
    return t_peaks[order][hit], n_beams - 1 - match[hit]


def _align(a, c, pitch, skip_peak, skip_beam):
    """Monotone alignment of sorted peaks ``a`` (P) to sorted beam angles ``c`` (B).

    Cost: squared offset in local pitches (capped at 1) per match, ``skip_peak[i]``
    per unmatched peak, ``skip_beam`` per unmatched beam. Returns (cost, beam index
    per peak or -1).
    """
    p, n = len(a), len(c)
    match_cost = np.minimum(((a[:, None] - c[None, :]) / pitch[None, :]) ** 2, 1.0)
    ramp = np.arange(n + 1) * skip_beam
    d_prev = ramp.copy()
    from_diag = np.zeros((p, n + 1), bool)
    back = np.zeros((p, n + 1), np.int64)
    for i in range(p):
        diag = np.full(n + 1, np.inf)
        diag[1:] = d_prev[:-1] + match_cost[i]
        up = d_prev + skip_peak[i]
        e = np.minimum(diag, up)
        from_diag[i] = diag < up
        shifted = e - ramp
        run = np.minimum.accumulate(shifted)
        # index of the running minimum (first occurrence)
        idx = np.arange(n + 1)
        back[i] = np.maximum.accumulate(np.where(shifted == run, idx, 0))
        d_prev = run + ramp
    out = np.full(p, -1, np.int64)
    j = n
    for i in range(p - 1, -1, -1):
        j = back[i, j]
        if from_diag[i, j]:
            out[i] = j - 1
            j -= 1
    return float(d_prev[n]), out


def _nearest_line(s: np.ndarray, y: np.ndarray, t: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Index of the nearest line y = t + h s for every point (chunked N x L)."""
    out = np.empty(len(s), np.int64)
    for start in range(0, len(s), _CHUNK):
        sl = slice(start, start + _CHUNK)
        resid = np.abs(y[sl, None] - (t[None, :] + s[sl, None] * h[None, :]))
        out[sl] = np.argmin(resid, axis=1)
    return out


def _refit_lines(s, y, line, t, h):
    """Per-line least squares y = t + h s, with a ridge pulling h to its previous value
    (lines seen only far away barely constrain the slope)."""
    n_lines = len(t)
    w = np.bincount(line, minlength=n_lines).astype(np.float64)
    ss = np.bincount(line, s, n_lines)
    sy = np.bincount(line, y, n_lines)
    sss = np.bincount(line, s * s, n_lines)
    ssy = np.bincount(line, s * y, n_lines)
    lam = np.maximum(w, 1.0) * 1e-4
    a11, a12, a22 = w, ss, sss + lam
    b1, b2 = sy, ssy + lam * h
    det = a11 * a22 - a12 * a12
    ok = (w >= 3) & (det > 1e-12 * np.maximum(a11 * a22, 1e-300))
    new_t = np.where(ok, (a22 * b1 - a12 * b2) / np.where(ok, det, 1.0), t)
    new_h = np.where(ok, (a11 * b2 - a12 * b1) / np.where(ok, det, 1.0), h)
    return new_t, np.clip(new_h, -2 * _H_MAX, 2 * _H_MAX)


def _lines_explain(s, y, line, t, h, sensor: SensorSpec) -> bool:
    """Does the line model hold? False when more than 5 % of the points lie over a
    quarter of the nominal beam pitch from their line (e.g. motion-compensated
    sweeps, where a laser's returns no longer share one line)."""
    elev = np.sort(sensor.elevations_rad)
    pitch = float(np.median(np.diff(elev)))
    resid = np.abs(np.arctan(y) - np.arctan(t[line] + h[line] * s))
    return bool(np.mean(resid > 0.25 * pitch) <= 0.05)


@dataclass(frozen=True)
class RingCalibration:
    """Per-beam lines z/rho = intercept + slope / rho of one sensor unit (index = beam id,
    0 = top), fitted on a full sweep by :func:`calibrate_rings`. A unit's beam angles
    and laser heights do not change between sweeps, so the calibration of one full
    sweep recovers the rings of cropped or thinned sweeps of the same unit, where
    beams are missing and a per-scan fit cannot tell which line is which beam."""

    intercept: np.ndarray
    slope: np.ndarray


def _fit_lines(s_f: np.ndarray, y_f: np.ndarray, sensor: SensorSpec):
    """Per-scan line fit: (line intercepts, slopes, beam id per line), or None when the
    scan cannot be calibrated (too few points, or the line model does not hold)."""
    if len(s_f) < _MIN_POINTS_PER_BEAM * sensor.num_beams or sensor.num_beams < 2:
        return None
    rng = np.abs(y_f / s_f) * np.sqrt(1.0 + 1.0 / (y_f * y_f + 1e-300))  # |z|, rho -> range
    fit = (rng > sensor.min_range) & (rng < sensor.max_range)  # drop no-return / body points
    if fit.sum() < _MIN_POINTS_PER_BEAM * sensor.num_beams:
        return None
    t_peaks, h_peaks, votes = _hough_lines(s_f[fit], y_f[fit], sensor)
    if len(t_peaks) < 2:
        return None
    order = np.argsort(t_peaks)
    t_peaks, h_peaks, votes = t_peaks[order], h_peaks[order], votes[order]
    t_lines, beam = _match_to_beams(t_peaks, votes, sensor)
    h_lines = h_peaks[np.searchsorted(t_peaks, t_lines)]
    s_fit, y_fit = s_f[fit], y_f[fit]
    for _ in range(_REFINE_ITERS):
        line = _nearest_line(s_fit, y_fit, t_lines, h_lines)
        t_lines, h_lines = _refit_lines(s_fit, y_fit, line, t_lines, h_lines)
    line = _nearest_line(s_fit, y_fit, t_lines, h_lines)
    if not _lines_explain(s_fit, y_fit, line, t_lines, h_lines, sensor):
        return None
    return t_lines, h_lines, beam


def firing_order_rings(points: np.ndarray, sensor: SensorSpec) -> np.ndarray | None:
    """Ring per point from the file order, or None when the order is not the firing order.

    Firing order (raw KITTI / SemanticKITTI / KITTI-360 files): laser after laser,
    top first, each one revolution that starts at azimuth 0 and runs forward, so
    ``floor(unwrapped azimuth / 2 pi)`` counts lasers. Accepted only if that gives
    exactly ``num_beams`` revolutions, every one with points, the azimuth rarely
    steps back by more than 5 deg, and the revolutions' median elevations strictly
    descend (top laser first). Non-finite points get -1.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4, 5):
        raise InputError(None, f"firing_order_rings: points must be (N, 3|4|5), got shape {pts.shape}")
    n_beams = sensor.num_beams
    xyz = pts[:, :3].astype(np.float64)
    finite = np.isfinite(xyz).all(axis=1)
    if finite.sum() < _MIN_POINTS_PER_BEAM * n_beams or n_beams < 2:
        return None
    xyz = levelled_to_sensor(xyz[finite], sensor.mount_pitch_deg)
    azimuth = np.unwrap(np.arctan2(xyz[:, 1], xyz[:, 0]))
    if np.count_nonzero(np.diff(azimuth) < -_BACKSTEP) > _MAX_BACKSTEPS_PER_BEAM * n_beams:
        return None
    turn = np.floor(azimuth / (2.0 * np.pi)).astype(np.int64)
    turn -= turn.min()
    counts = np.bincount(turn)
    if len(counts) != n_beams or counts.min() == 0:
        return None
    elevation = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))
    order = np.argsort(turn, kind="stable")
    medians = [np.median(part) for part in np.split(elevation[order], np.cumsum(counts)[:-1])]
    if not np.all(np.diff(medians) < 0):
        return None
    rings = np.full(len(pts), -1, np.int16)
    rings[finite] = turn
    return rings


def _lines_of_rings(s: np.ndarray, y: np.ndarray, rings: np.ndarray, sensor: SensorSpec):
    """Per-beam lines (intercept, slope) fitted to points whose beam is known:
    least squares, then once more without the points over a quarter of the beam
    pitch from their line (ego-motion compensated near returns)."""
    n_beams = sensor.num_beams
    rng = np.abs(y / s) * np.sqrt(1.0 + 1.0 / (y * y + 1e-300))
    fit = (rng > sensor.min_range) & (rng < sensor.max_range) & (rings >= 0)
    s, y, line = s[fit], y[fit], rings[fit].astype(np.int64)
    counts = np.bincount(line, minlength=n_beams)
    if counts.min() < 3:
        return None
    t = np.bincount(line, y, n_beams) / counts
    h = np.zeros(n_beams)
    t, h = _refit_lines(s, y, line, t, h)
    pitch = float(np.median(np.abs(np.diff(np.sort(sensor.elevations_rad)))))
    inlier = np.abs(np.arctan(y) - np.arctan(t[line] + h[line] * s)) <= 0.25 * pitch
    return _refit_lines(s[inlier], y[inlier], line[inlier], t, h)


def calibrate_rings(points: np.ndarray, sensor: SensorSpec) -> RingCalibration | None:
    """Fit every beam's line on a full sweep (all beams visible); None if that fails.

    A sweep in firing order (:func:`firing_order_rings`) gives every point its
    beam, and the lines are fitted to those; otherwise the per-scan Hough
    calibration (module docstring) finds them.
    """
    finite, s, y = _elevation_points(points, sensor.mount_pitch_deg)
    fired = firing_order_rings(points, sensor)
    if fired is not None:
        lines = _lines_of_rings(s, y, fired, sensor)
        if lines is not None:
            return RingCalibration(intercept=lines[0], slope=lines[1])
    fitted = _fit_lines(s[finite], y[finite], sensor)
    if fitted is None or len(fitted[0]) != sensor.num_beams:
        return None
    t_lines, h_lines, beam = fitted
    intercept, slope = np.empty(sensor.num_beams), np.empty(sensor.num_beams)
    intercept[beam], slope[beam] = t_lines, h_lines
    return RingCalibration(intercept=intercept, slope=slope)


def azimuth_share(points: np.ndarray) -> float:
    """Share of the 360 one-degree azimuth bins that hold at least one finite point."""
    xyz = np.asarray(points)[:, :3].astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if len(xyz) == 0:
        return 0.0
    bins = np.floor(np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0])) + 180.0).astype(np.int64) % 360
    return float(len(np.unique(bins)) / 360.0)


def ring_recovery(points: np.ndarray, sensor: SensorSpec, calibrate: bool = True,
                  calibration: RingCalibration | None = None) -> tuple[np.ndarray, str]:
    """Ring index per point, (N,) int16 (0 = top beam), and the method that found it
    (one of :data:`RING_METHODS`).

    With a ``calibration`` of this sensor unit (:func:`calibrate_rings` on one full
    sweep), each point goes to the nearest calibrated beam line ("unit_calibration"):
    this also holds for cropped and thinned sweeps. Otherwise, with ``calibrate``
    (default), a scan in firing order takes its lasers from that order
    ("firing_order"), else the beam angles and per-laser height offsets are fitted
    to this scan ("scan_calibration", independent of point order; on a partial view,
    under :data:`FULL_VIEW_AZIMUTH_SHARE` of the azimuth, a :class:`RingRecoveryWarning`
    and "scan_calibration_partial_view"). When both fail
    (too few points per beam, beams missing so the lines cannot be told apart),
    the nearest nominal beam angle decides ("nominal") and a
    :class:`RingRecoveryWarning` says so; ``calibrate=False`` asks for that
    directly, without a warning. Points closer than 0.5 m horizontally are treated
    as at 0.5 m. Points with a non-finite coordinate get -1.
    """
    finite, s, y = _elevation_points(points, sensor.mount_pitch_deg)
    rings = np.full(len(s), -1, np.int16)
    if not finite.any():
        return rings, "nominal"
    s_f, y_f = s[finite], y[finite]
    if calibration is not None:
        if len(calibration.intercept) != sensor.num_beams:
            raise InputError(None, f"recover_rings: calibration has {len(calibration.intercept)} beams, "
                                   f"the sensor {sensor.num_beams}")
        rings[finite] = _nearest_line(s_f, y_f, calibration.intercept, calibration.slope)
        return rings, "unit_calibration"
    if calibrate:
        fired = firing_order_rings(points, sensor)
        if fired is not None:
            return fired, "firing_order"
        fitted = _fit_lines(s_f, y_f, sensor)
        if fitted is not None:
            t_lines, h_lines, beam = fitted
            rings[finite] = beam[_nearest_line(s_f, y_f, t_lines, h_lines)]
            share = azimuth_share(points)
            if share >= FULL_VIEW_AZIMUTH_SHARE:
                return rings, "scan_calibration"
            warnings.warn(
                f"ring recovery: the points cover {100 * share:.0f} % of the azimuth (a partial view); the rings "
                f"calibrated on it may put a few percent of the points on a neighbouring beam (recorded as "
                f"scan_calibration_partial_view); calibrate on a full sweep of the unit instead (calibrate_rings)",
                RingRecoveryWarning, stacklevel=2)
            return rings, "scan_calibration_partial_view"
        warnings.warn(
            f"ring recovery: {int(finite.sum())} points are neither in firing order nor calibratable as a "
            f"{sensor.num_beams}-beam {sensor.name} sweep; rings come from the nominal beam table and may be "
            "off by several beams", RingRecoveryWarning, stacklevel=2)
    rings[finite] = _nominal_rings(y_f, sensor)
    return rings, "nominal"


def recover_rings(points: np.ndarray, sensor: SensorSpec, calibrate: bool = True,
                  calibration: RingCalibration | None = None) -> np.ndarray:
    """Ring index per point, (N,) int16, 0 = top beam: :func:`ring_recovery` without
    the method."""
    return ring_recovery(points, sensor, calibrate, calibration)[0]


def beam_reduce(scan: Scan, sensor: SensorSpec, keep_every: int = 2,
                calibration: RingCalibration | None = None) -> Scan:
    """Keep the rings whose id is a multiple of ``keep_every`` (Beam-32 from 64 beams).

    Uses ``scan.ring`` when set, else :func:`recover_rings`. Returns a new scan with
    labels following their points, in the original order; its ``ring`` holds the
    original ring ids of the kept points.
    """
    if isinstance(keep_every, bool) or int(keep_every) != keep_every or keep_every < 1:
        raise InputError(None, f"beam_reduce: keep_every must be a positive integer, got {keep_every!r}")
    rings = scan.ring if scan.ring is not None else recover_rings(scan.points, sensor, calibration=calibration)
    keep = (rings >= 0) & (rings % int(keep_every) == 0)
    out = scan.select(keep)
    if out.ring is None:
        from dataclasses import replace

        out = replace(out, ring=rings[keep])
    return out
