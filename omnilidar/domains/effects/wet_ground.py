"""Wet ground: a water film darkens ground returns and drops the ones it pushes
under the sensor's detection floor (Bijelic's model, as used by LiDAR_snow_sim
and SemanticKITTI-C / Robo3D).

Per ground point (all quantities in physical units, reflectance 0..1):

* incidence: cos(theta) = -u . n, u the unit beam direction, n the ground
  normal (least-squares plane through the ground points; the sensor's mount
  prior when they do not define one);
* laser power: linear fit a d + b of I / cos(theta) over range d,
  P_out(d) = 15 (a d + b);
* diffuse reflectivity: rho = I / cos(theta) / P_out, clipped to [0.05, 1];
* water film (air n = 1.0003, water n = 1.33): per polarisation x in {s, p}
  the Fresnel reflectance R_x(theta) and T_x = 1 - R_x; light enters, scatters
  off the pavement and leaves through the film, reflecting back and forth:
  T_tot,x = T_x rho T_x / (1 - rho R_x) (T and R are the same in both directions
  for a refracted pair, Stokes relations); T_tot = max(T_tot,s, T_tot,p);
* water fraction f = clip(h / 1.2 mm, 0, 1) of the pavement texture depth;
* wet intensity I_new = P_out cos(theta) [(1 - f) rho + f T_tot]
                      = I [(1 - f) + f T_tot / rho]  <= I (never brighter);
* detection floor: thr(d) = noise_floor * L(d), L(d) the lower envelope of the
  scan's own dry normalised ground intensity I / cos(theta) (the 5 % quantile
  per equal-count range bin, interpolated piecewise-linearly in d); a darkened
  point is kept iff I_new > thr(d) cos(theta).

Differences from the anchor and why:

1. cos(theta), not theta: the anchor mixes ``f * t / theta`` (divides the wet
   reflectivity by the incidence angle in radians). The wet return obeys the
   same Lambertian cos(theta) as the dry one, so the wet reflectivity is T_tot
   and the cosine cancels against rho's. (Dividing T_tot by cos(theta) instead
   would make every wet point except near-nadir ones brighter than the dry
   one, and the "never brighter" clip would erase the effect.)
2. Scale-free detection floor. The anchor's histogram (range bins 10-70 m,
   intensity bins from 5 to the max, "min_vals > 5") assumes 0..255
   intensities: fed 0..1 it removes 37-84 % of the ground. Here L(d) is a 5 %
   quantile of the scan's own positive ground intensities per range bin, so
   the floor scales with the data: multiplying all intensities by any gain
   gives the same kept/lost decision. The anchor's estimator (the
   least-populated intensity bin per range bin, then a straight line) is
   noise-driven: on our KITTI scans its 0..255 envelope ranges from negative
   to several times the median ground return. On real scans the envelope rises
   and then saturates with range, so a straight line overshoots; bins are
   interpolated instead. The SemanticKITTI-C noise floors
   0.3 / 0.3 / 0.7 keep their meaning "fraction of the dimmest dry ground
   return at that range that the receiver still detects". Range bins adapt to
   the scan (equal counts), not to a car's 10-70 m.
3. Ratio form ``I [(1 - f) + f T_tot / rho]``: identical to the anchor's mix
   for 0.05 <= rho <= 1, and keeps the darkening independent of errors in the
   absolute P_out fit (below rho = 0.05 the anchor's mix brightens and is then
   clipped, so its dimmest points are never darkened). P_out is clamped
   positive (the linear fit can cross zero at far range).
4. Only water loses points: a point is lost iff the film takes it from above
   the floor to at or below it. A dry return at or under the estimated floor
   (the real sensor did detect it, so the estimate is too high there; zero
   remission, 8-10 % of KITTI points, is one case) is never dropped. The
   anchor's rule drops every dry-ground return under its estimated floor as
   soon as any water dims it: 179-249 points of a real KITTI scan at 1e-6 mm
   of water, 89-95 % of what 0.2 mm loses. Here the loss grows monotonically
   and continuously from none at zero water (which needs no ground estimate:
   ``is_identity``).
5. Ground comes from the caller (``ground=`` mask, see omnilidar.domains.ground),
   not from a RANSAC box in front of a car; the incidence normal is fitted to
   those points (pitched drones, slopes) instead of assuming z is up.
6. Point order is kept (the anchor moves ground points to the end); labels
   follow their points; fewer than 1000 ground points still get the effect
   (the anchor silently returns the input), with constant fits when there are
   too few points for a range trend.
"""

from __future__ import annotations

import time

import numpy as np

from omnilidar.domains.effects.base import unchanged
from omnilidar.domains.point_checks import effect_scale
from omnilidar.errors import InputError
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec

NEEDS_GROUND = True

# SemanticKITTI-C (Robo3D) severities: water height (mm) and noise floor.
SEVERITIES: dict[str, dict] = {
    "light": {"water_height_mm": 0.2, "noise_floor": 0.3},
    "moderate": {"water_height_mm": 1.0, "noise_floor": 0.3},
    "heavy": {"water_height_mm": 1.2, "noise_floor": 0.7},
}

PAVEMENT_DEPTH_MM = 1.2  # texture depth a film must fill to be fully wet
POWER_FACTOR = 15.0  # P_out / fitted ground return (mean ground rho ~ 1/15)
N_AIR = 1.0003
N_WATER = 1.33
RHO_MIN, RHO_MAX = 0.05, 1.0
ENVELOPE_QUANTILE = 0.05  # lower envelope of dry ground intensity per range bin
MIN_PER_BIN = 64  # points per range bin for the envelope
COS_MIN = 0.01  # grazing-incidence clamp (~89.4 deg)
R_MIN = 1e-3  # points closer than this (m) have no direction and are left alone

# fit_points: ground points used for the P_out and floor fits (0 = all; a random
# subset drawn from rng otherwise); range_bins: bins of the lower envelope (finer
# bins resolve the per-laser rings of the ground, whose floors differ).
# Defaults (see benchmarks/bench_effect_wet_ground.py): all points, because a
# subset saves only ~20 % of ~25 ms and costs 0.2-1 % of ground in the lost
# fraction, and leaves the result independent of rng; 64 bins, within ~1 % of
# ground of 128 bins at the same cost.
FIDELITY_LEVELS: dict[str, list] = {
    "fit_points": [1024, 4096, 16384, 0],
    "range_bins": [8, 16, 32, 64, 128],
}
DEFAULT_FIDELITY: dict = {"fit_points": 0, "range_bins": 64}
HIGHEST_FIDELITY: dict = {"fit_points": 0, "range_bins": 128}


def draw_params(severity: str, rng: np.random.Generator) -> dict:
    """Parameters of one scan for a named severity (fixed per severity, as in
    SemanticKITTI-C; ``rng`` is not used)."""
    if severity not in SEVERITIES:
        raise InputError(None, f"wet_ground: unknown severity {severity!r}; known: {', '.join(SEVERITIES)}")
    return {**SEVERITIES[severity], "pavement_depth_mm": PAVEMENT_DEPTH_MM}


def _check_params(params: dict) -> tuple[float, float, float]:
    try:
        h = float(params["water_height_mm"])
        nf = float(params.get("noise_floor", 0.3))
        depth = float(params.get("pavement_depth_mm", PAVEMENT_DEPTH_MM))
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(None, f"wet_ground: bad params {params!r} ({err})") from None
    if not (np.isfinite(h) and h >= 0 and np.isfinite(nf) and nf >= 0 and np.isfinite(depth) and depth > 0):
        raise InputError(
            None, f"wet_ground: params need water_height_mm >= 0, noise_floor >= 0, pavement_depth_mm > 0; got {params!r}"
        )
    return h, nf, depth


def is_identity(params: dict) -> bool:
    """Zero water: the effect returns its input, so no ground is needed."""
    h_mm, _, _ = _check_params(params)
    return h_mm == 0.0


def _fidelity(fidelity: dict | None) -> tuple[int, int]:
    fid = {**DEFAULT_FIDELITY, **(fidelity or {})}
    unknown = set(fid) - set(DEFAULT_FIDELITY)
    if unknown:
        raise InputError(None, f"wet_ground: unknown fidelity knobs {sorted(unknown)}")
    fit_points, range_bins = int(fid["fit_points"]), int(fid["range_bins"])
    if fit_points < 0 or range_bins < 1:
        raise InputError(None, f"wet_ground: fidelity needs fit_points >= 0 and range_bins >= 1, got {fid}")
    return fit_points, range_bins


def fresnel_reflectance(cos_i: np.ndarray, n1: float = N_AIR, n2: float = N_WATER) -> tuple[np.ndarray, np.ndarray]:
    """Power reflectances (R_s, R_p) at a flat n1 -> n2 interface for incidence
    cosines ``cos_i`` (n1 < n2: no total internal reflection)."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin_t = (n1 / n2) * np.sqrt(1.0 - cos_i**2)
    cos_t = np.sqrt(1.0 - sin_t**2)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return rs**2, rp**2


def wet_transmittance(cos_i: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Return of a Lambertian surface (albedo rho) under a water film, relative
    to the incident power: max over s/p of T rho T / (1 - rho R)."""
    rs, rp = fresnel_reflectance(cos_i)

    def total(r):
        # T^2 rho / (1 - rho R); at grazing incidence with rho = 1 both vanish: 0.
        den = 1.0 - rho * r
        return np.where(den > 1e-12, (1.0 - r) ** 2 * rho / np.maximum(den, 1e-12), 0.0)

    return np.maximum(total(rs), total(rp))


def _linear_fit(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None) -> tuple[float, float]:
    """Least-squares y = a x + b (a = 0 when x has no spread)."""
    w = np.ones_like(x) if w is None else w
    sw = w.sum()
    if len(x) == 0 or sw <= 0:
        return 0.0, 0.0
    mx, my = (w * x).sum() / sw, (w * y).sum() / sw
    vx = (w * (x - mx) ** 2).sum()
    a = (w * (x - mx) * (y - my)).sum() / vx if vx > 1e-12 * max(1.0, mx * mx) * sw else 0.0
    return float(a), float(my - a * mx)


def lower_envelope(d: np.ndarray, y: np.ndarray, range_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Lower envelope of y (> 0 only) against range d: the ENVELOPE_QUANTILE of
    y in up to ``range_bins`` equal-count range bins (at least MIN_PER_BIN
    points each). Returns (bin median ranges, bin quantiles), ascending in range,
    for piecewise-linear interpolation (flat beyond the ends); empty when no
    y > 0."""
    pos = y > 0
    d, y = d[pos], y[pos]
    if len(y) == 0:
        return np.zeros(0), np.zeros(0)
    nb = int(max(1, min(range_bins, len(y) // MIN_PER_BIN)))
    order = np.argsort(d, kind="stable")
    d, y = d[order], y[order]
    edges = np.linspace(0, len(y), nb + 1).astype(np.int64)
    centres = np.empty(nb)
    qs = np.empty(nb)
    for k in range(nb):  # at most range_bins small slices
        lo, hi = edges[k], edges[k + 1]
        centres[k] = d[(lo + hi) // 2]
        qs[k] = np.quantile(y[lo:hi], ENVELOPE_QUANTILE)
    return centres, qs


def _normal(xyz: np.ndarray, sensor: SensorSpec) -> np.ndarray:
    from omnilidar.domains.ground import fit_plane_normal, up_vector

    return fit_plane_normal(xyz, up_vector(sensor))



def apply(
    scan: Scan,
    params: dict,
    sensor: SensorSpec,
    rng: np.random.Generator,
    *,
    ground: np.ndarray | None = None,
    fidelity: dict | None = None,
    return_info: bool = False,
):
    """Wet the ground of ``scan`` (see the module docstring).

    ``ground``: boolean mask (N,) of ground points; estimated with
    omnilidar.domains.ground.estimate_ground when None. Only ground points change:
    darker intensity, or lost. Nothing is added. Returns a new Scan (or the input
    itself when nothing changes), with ``return_info`` also
    {"lost", "changed", "weather"} boolean masks.
    """
    h_mm, noise_floor, depth_mm = _check_params(params)
    fit_points, range_bins = _fidelity(fidelity)
    n = len(scan)
    f = min(h_mm / depth_mm, 1.0)
    if f <= 0.0 or n == 0:
        return unchanged(scan, return_info)
    scale = effect_scale(scan, sensor, "wet_ground")
    if ground is None:
        from omnilidar.domains.ground import estimate_ground

        ground = estimate_ground(scan, sensor, rng)
    ground = np.asarray(ground)
    if ground.dtype != bool or ground.shape != (n,):
        raise InputError(None, f"wet_ground: ground mask must be bool of shape ({n},), got {ground.dtype} {ground.shape}")

    # Work on the ground points only (the rest is never read twice).
    idx = np.flatnonzero(ground)
    gp = scan.points[idx]
    xyz = gp[:, :3].astype(np.float64)
    r = np.sqrt(np.einsum("ij,ij->i", xyz, xyz))
    usable = r > R_MIN
    if not usable.all():
        idx, gp, xyz, r = idx[usable], gp[usable], xyz[usable], r[usable]
    if len(idx) == 0:
        return unchanged(scan, return_info)

    d = r
    u = xyz / d[:, None]
    normal = _normal(xyz, sensor)
    cos_t = np.clip(-(u @ normal), COS_MIN, 1.0)
    inten = np.clip(gp[:, 3].astype(np.float64) / scale, 0.0, None)
    norm_i = inten / cos_t

    # Fits on all ground points or a random subset of them.
    if 0 < fit_points < len(idx):
        sub = np.sort(rng.choice(len(idx), size=fit_points, replace=False))
        fd, fy = d[sub], norm_i[sub]
    else:
        fd, fy = d, norm_i

    # Laser power P_out(d) = 15 (a d + b), clamped to a positive floor.
    a, b = _linear_fit(fd, fy)
    positive = fy[fy > 0]
    floor = 0.05 * float(np.median(positive)) if len(positive) else 1.0
    p_out = POWER_FACTOR * np.maximum(a * d + b, floor)

    rho = np.clip(norm_i / p_out, RHO_MIN, RHO_MAX)
    darkening = (1.0 - f) + f * wet_transmittance(cos_t, rho) / rho
    new_i = np.minimum(inten * darkening, inten)

    centres, qs = lower_envelope(fd, fy, range_bins)
    thr = noise_floor * np.interp(d, centres, qs) if len(qs) else np.zeros_like(d)
    floor_i = thr * cos_t
    lost_g = (inten > floor_i) & (new_i <= floor_i)

    out_i = np.clip(new_i * scale, 0.0, scale).astype(np.float32)
    lost = np.zeros(n, bool)
    lost[idx[lost_g]] = True
    changed = np.zeros(n, bool)
    changed[idx] = (out_i != gp[:, 3]) & ~lost_g
    if not lost.any() and not changed.any():
        return unchanged(scan, return_info)
    # One copy of the points: select the kept ones, then write the new
    # intensities at the kept ground points' output positions.
    out = scan.select(~lost) if lost.any() else scan.with_points(scan.points.copy())
    position = np.cumsum(~lost) - 1
    out.points[position[idx[~lost_g]], 3] = out_i[~lost_g]
    if not return_info:
        return out
    return out, {"lost": lost, "changed": changed, "weather": np.zeros(len(out), bool)}


def fidelity_summary(scan: Scan, out: Scan, info: dict) -> dict:
    """Statistics of one application: fractions of points lost / changed /
    added, and the mean intensity shift (physical units) of changed points."""
    n = max(len(scan), 1)
    kept = ~info["lost"]
    scale = float(scan.intensity_scale) or 1.0
    shift = (out.intensity.astype(np.float64) - scan.intensity[kept].astype(np.float64)) / scale
    ch = info["changed"][kept]
    return {
        "lost": float(info["lost"].sum() / n),
        "changed": float(info["changed"].sum() / n),
        "added": float(info["weather"].sum() / n),
        "mean_shift": float(shift[ch].mean()) if ch.any() else 0.0,
    }


def accuracy_time_curve(scan: Scan, sensor: SensorSpec, severity: str, seeds, repeats: int = 3) -> list[dict]:
    """Accuracy/time sweep over FIDELITY_LEVELS, one knob at a time (the other
    at its highest-fidelity value). For each knob value: median time per scan
    and the absolute error, averaged over ``seeds``, of the lost fraction and of
    the mean intensity shift against HIGHEST_FIDELITY."""
    from omnilidar.domains.ground import estimate_ground

    ground = estimate_ground(scan, sensor)
    params = draw_params(severity, np.random.default_rng(0))

    def run(fid, seed):
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out, info = apply(scan, params, sensor, np.random.default_rng(seed), ground=ground, fidelity=fid, return_info=True)
            times.append(time.perf_counter() - t0)
        return float(np.median(times)), fidelity_summary(scan, out, info)

    ref = {s: run(HIGHEST_FIDELITY, s)[1] for s in seeds}
    rows = []
    for knob, values in FIDELITY_LEVELS.items():
        for value in values:
            fid = {**HIGHEST_FIDELITY, knob: value}
            res = [run(fid, s) for s in seeds]
            rows.append(
                {
                    "severity": severity,
                    "knob": knob,
                    "value": value,
                    "time_s": float(np.median([t for t, _ in res])),
                    "lost": float(np.mean([st["lost"] for _, st in res])),
                    "err_lost": float(np.mean([abs(st["lost"] - ref[s]["lost"]) for s, (_, st) in zip(seeds, res)])),
                    "err_mean_shift": float(
                        np.mean([abs(st["mean_shift"] - ref[s]["mean_shift"]) for s, (_, st) in zip(seeds, res)])
                    ),
                }
            )
    return rows
