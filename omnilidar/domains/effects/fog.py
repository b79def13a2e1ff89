"""Fog: the LiDAR-equation fog model of Hahner et al. (ICCV 2021), vectorised.

Physics
-------
The sensor emits a pulse ``P_T(t) = P_0 sin^2(pi t / (2 tau_H))`` for ``0 <= t <= 2 tau_H``
(``tau_H`` = 20 ns half-power width, so the pulse is ``c tau_H`` = 6 m long in range).
Homogeneous fog with extinction ``alpha`` (1/m) and backscatter ``beta`` (1/(m sr)) does two
things to a beam whose clear-weather hard target lies at range ``R0``:

* the hard echo is attenuated by the two-way transmission: ``I_hard = I exp(-2 alpha R0)``;
* the fog volume in front of the target returns a soft echo. With ``f(R') = xi(R')
  exp(-2 alpha R') / R'^2`` (``xi``: transmitter/receiver overlap, 0 below R1 = 0.9 m, linear
  to 1 at R2 = 1.0 m) its received power at receive range ``R`` is proportional to

      i(R) = int_0^{2 tau_H} sin^2(pi t / (2 tau_H)) f(R - c t / 2) dt
           = (2 / c) int_{R - c tau_H}^{R} sin^2(pi (R - R') / (c tau_H)) f(R') dR'   (s / m^2).

  The fog return sits at the strongest soft echo ``R_fog(R0)`` with strength
  ``i_fog(R0)``; relative to the clear hard echo it reads
  ``I_soft = i_fog(R0) I R0^2 beta / beta0`` with ``beta0 = 1e-6 / pi`` (the anchor's
  calibration of the target's differential reflectivity, which makes the hard- and
  soft-target equations commensurate). If ``I_soft > I_hard`` the point becomes a fog
  return at ``R_fog`` (raw label ``WEATHER_RETURN_LABEL``, instance 0).

``i(R)`` is computed here by Gauss-Legendre quadrature, split at the kinks of the overlap
function so every piece is smooth, vectorised over a range grid, and tabulated once per
``alpha`` (``lru_cache`` in memory, optionally an ``.npz`` under ``cache_dir``). Applying
fog to a scan is then interpolation only.

Because the truncation ``R' < R0`` never acts for ``R <= R0``, the strongest soft echo in
front of the target is a running maximum of the untruncated curve: ``R_fog(R0) =
min(R0, R*)`` and ``i_fog(R0) = i(min(R0, R*))``, where ``R*`` (about 4.64 m for every
``alpha`` we use) is the curve's peak, refined to quadrature precision. ``i(R)`` rises up
to ``R*`` and falls after it (for ``R > R2 + c tau_H`` the derivative is the pulse-weighted
integral of ``f' < 0``); the table build checks this.

Differences from the anchor (LiDAR_fog_sim / Robo3D) and why
-------------------------------------------------------------
1. Intensities: we work in 0..1 reflectance (``I / sensor.intensity_scale``) and return the
   sensor's scale clipped to its range. The anchor fed 0..1 remission through code written
   for 0..255 with the 255 clip removed, so intensities reached ~10.
2. Fog-return intensity: the anchor stores ``I_soft`` (the echo strength expressed as an
   intensity at the target's range R0). Dataset intensities are range-compensated
   (received power ~ I / R^2: the same surface reads the same remission near and far), so the
   intensity the sensor reports for an echo of that power at ``r_fog`` is
   ``I_soft (r_fog / R0)^2``. The decision ``I_soft > I_hard`` is a comparison of received
   powers along one beam and is unchanged.
3. Range jitter: the anchor scales fog returns by ``R0 / U(R0 - 10, R0 + 10)``, which crosses
   zero and throws points thousands of metres away or behind the sensor. We jitter the
   fog return within the soft echo's half-power width (the part of the broad echo where a
   noisy peak detector can fire), scaled by ``range_jitter`` in [0, 1]; the range stays in
   ``[R_lo, min(R_hi, R0)]``, inside ``(0.9 m, R0]``: never behind the sensor, never beyond
   the hard target.
4. Fog returns never beyond the hard target: the soft echo is only searched in front of it
   (``R <= R0``); the anchor's truncated-curve argmax can lie beyond ``R0`` for ``R0`` below
   ~4.6 m (such points never turn into fog at the severities used, so fractions agree).
5. Lost returns: the anchor never drops far returns. A hard return whose received power
   ``rho exp(-2 alpha R0) / R0^2`` falls below the sensor's detection floor is lost (unless
   its fog echo wins, then it is a fog return: the soft-echo level is calibrated only
   relative to the hard echo through ``beta0``, so the absolute floor is not applied to it).
   The floor is the weakest return the sensor reports:
   ``min(q/2 / max_range^2, min_i rho_i / R_i^2)`` over the clear scan, with ``q`` the
   reporting quantum of the intensity (the smallest positive reflectance in the scan, at most
   0.01). Zero-intensity points were detected but read below one quantum; they get
   ``rho = q/2`` for power and fog intensity, so they are neither always lost (LISA's flaw)
   nor never fogged (the anchor's ``I = 0`` points can never become fog, a bias towards
   dark far surfaces); their output intensity on the hard path stays 0.
6. The anchor rounds attenuated intensities to integers (meant for 0..255); we keep them
   continuous.
7. ``alpha = 0`` returns the input object unchanged (bit for bit); the anchor reprocesses it.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from omnilidar.domains.effects.base import WEATHER_RETURN_LABEL, unchanged
from omnilidar.domains.point_checks import effect_scale
from omnilidar.errors import InputError
from omnilidar.io.atomic import atomic_path
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec
from omnilidar.provenance import code_hash

NEEDS_GROUND = False

SPEED_OF_LIGHT = 299_792_458.0  # m/s
TAU_H = 20e-9  # half-power pulse width (s)
PULSE_LENGTH = SPEED_OF_LIGHT * TAU_H  # 6 m: the pulse's extent in range
OVERLAP_START = 0.9  # R1 (m): receiver FOV starts to see the transmitted beam
OVERLAP_FULL = 1.0  # R2 (m): receiver FOV covers the beam fully
BETA0 = 1e-6 / np.pi  # anchor's differential reflectivity of the hard target (1/sr)
TABLE_RANGE = 20.0  # m; the soft echo's peak lies below OVERLAP_FULL + PULSE_LENGTH = 7 m
MAX_ALPHA = 1.0  # 1/m (MOR ~3 m); denser fog is outside the model's validity here
MAX_QUANTUM = 0.01  # coarsest intensity reporting step we assume (KITTI remission: 0.01)

# Extinction coefficients SemanticKITTI-C draws per scan (MOR = ln(20) / alpha).
ALPHAS = (0.0, 0.005, 0.01, 0.02, 0.03, 0.06)

SEVERITIES: dict[str, dict] = {
    "light": {"beta": 0.008},
    "moderate": {"beta": 0.05},
    "heavy": {"beta": 0.2},
}

# r0_step: spacing (m) of the range grid on which i(R) is tabulated and interpolated;
# quad_nodes: Gauss-Legendre nodes per smooth piece of the soft-echo integral.
# Default from accuracy_time_curve on KITTI 000001: 8 nodes is the cheapest setting whose
# fog/lost decisions equal the 64-node reference (4 nodes: 2.6e-4 of points differ,
# 2 nodes: 8e-3), and 0.1 m keeps fog ranges within 0.1 mm of a 0.01 m grid; the table
# costs ~10-20 ms per alpha once per process at any setting, so accuracy wins.
DEFAULT_FIDELITY = {"r0_step": 0.1, "quad_nodes": 8}
FIDELITY_LEVELS = {
    "r0_step": [0.5, 0.2, 0.1, 0.05, 0.02, 0.01],
    "quad_nodes": [2, 4, 8, 16, 32, 64],
}
_HIGHEST_FIDELITY = {"r0_step": 0.01, "quad_nodes": 64}

_TABLE_VERSION = 1


# --------------------------------------------------------------------------- parameters


def draw_params(severity: str, rng: np.random.Generator) -> dict:
    """Draw one scan's fog parameters: backscatter ``beta`` from the severity and
    extinction ``alpha`` uniformly from ``ALPHAS`` (as SemanticKITTI-C)."""
    if severity not in SEVERITIES:
        raise InputError(None, f"unknown fog severity {severity!r}; known: {', '.join(SEVERITIES)}")
    alpha = float(ALPHAS[int(rng.integers(len(ALPHAS)))])
    return {"alpha": alpha, "beta": float(SEVERITIES[severity]["beta"]), "range_jitter": 1.0}


def _check_params(params: dict) -> tuple[float, float, float]:
    unknown = set(params) - {"alpha", "beta", "range_jitter"}
    if unknown:
        raise InputError(None, f"fog params: unknown keys {sorted(unknown)}")
    try:
        alpha = float(params["alpha"])
        beta = float(params["beta"])
        jitter = float(params.get("range_jitter", 1.0))
    except KeyError as err:
        raise InputError(None, f"fog params: missing {err.args[0]!r}") from None
    except (TypeError, ValueError):
        raise InputError(None, f"fog params: alpha, beta and range_jitter must be numbers, got {params!r}") from None
    if not (np.isfinite(alpha) and 0.0 <= alpha <= MAX_ALPHA):
        raise InputError(None, f"fog params: alpha must be in [0, {MAX_ALPHA}] 1/m, got {alpha}")
    if not (np.isfinite(beta) and beta >= 0.0):
        raise InputError(None, f"fog params: beta must be a finite number >= 0, got {beta}")
    if not (np.isfinite(jitter) and 0.0 <= jitter <= 1.0):
        raise InputError(None, f"fog params: range_jitter must be in [0, 1], got {jitter}")
    return alpha, beta, jitter


def _check_fidelity(fidelity: dict | None) -> tuple[float, int]:
    fid = dict(DEFAULT_FIDELITY)
    if fidelity:
        unknown = set(fidelity) - set(DEFAULT_FIDELITY)
        if unknown:
            raise InputError(None, f"fog fidelity: unknown keys {sorted(unknown)}")
        fid.update(fidelity)
    step, nodes = fid["r0_step"], fid["quad_nodes"]
    if not (isinstance(step, (int, float)) and np.isfinite(step) and 0.001 <= step <= 1.0):
        raise InputError(None, f"fog fidelity: r0_step must be in [0.001, 1] m, got {step!r}")
    if isinstance(nodes, bool) or not isinstance(nodes, (int, np.integer)) or not 1 <= nodes <= 256:
        raise InputError(None, f"fog fidelity: quad_nodes must be an integer in [1, 256], got {nodes!r}")
    return float(step), int(nodes)


# --------------------------------------------------------------------------- soft echo


def _fog_profile(r: np.ndarray, alpha: float) -> np.ndarray:
    """f(R') = xi(R') exp(-2 alpha R') / R'^2 (zero where the receiver sees no beam)."""
    overlap = np.clip((r - OVERLAP_START) / (OVERLAP_FULL - OVERLAP_START), 0.0, 1.0)
    safe = np.maximum(r, OVERLAP_START)  # xi = 0 below R1, so the clamp changes nothing
    return overlap * np.exp(-2.0 * alpha * safe) / (safe * safe)


@lru_cache(maxsize=16)
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.polynomial.legendre.leggauss(n)


def soft_echo(r: np.ndarray, alpha: float, quad_nodes: int = DEFAULT_FIDELITY["quad_nodes"]) -> np.ndarray:
    """Received soft (fog) power ``i(R)`` in s/m^2 at receive ranges ``r`` (untruncated:
    the fog extends beyond ``R``), by Gauss-Legendre quadrature over the fog volume.

    The integration range ``[R - c tau_H, R]`` is split at R1 and R2 so each piece has a
    smooth integrand (the pulse shape times ``f``)."""
    r = np.atleast_1d(np.asarray(r, dtype=np.float64))
    x, w = _gauss_legendre(int(quad_nodes))
    lo = np.maximum(r - PULSE_LENGTH, OVERLAP_START)
    total = np.zeros_like(r)
    for a, b in (
        (lo, np.minimum(r, OVERLAP_FULL)),  # ramp of the overlap function
        (np.maximum(lo, OVERLAP_FULL), r),  # full overlap
    ):
        half = 0.5 * np.maximum(b - a, 0.0)
        nodes = (0.5 * (a + b))[:, None] + half[:, None] * x[None, :]
        pulse = np.sin(np.pi * (r[:, None] - nodes) / PULSE_LENGTH) ** 2
        total += half * ((pulse * _fog_profile(nodes, alpha)) @ w)
    return total * (2.0 / SPEED_OF_LIGHT)


@dataclass(frozen=True)
class SoftReturnTable:
    """The fog return in front of a hard target at range ``r0`` (grid), for one alpha.

    r_fog: range of the strongest soft echo with ``R <= r0`` (m).
    i_fog: its strength (s/m^2), the anchor's integral.
    r_lo, r_hi: the echo's half-power interval in front of the target (m).
    All on the grid ``r0`` (0 to TABLE_RANGE); ``lookup`` interpolates.
    peak_range: the untruncated curve's peak R* (m).
    """

    alpha: float
    r0: np.ndarray
    r_fog: np.ndarray
    i_fog: np.ndarray
    r_lo: np.ndarray
    r_hi: np.ndarray
    peak_range: float

    def lookup(self, r0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Interpolate (r_fog, r_lo, r_hi, i_fog) at ranges ``r0`` (constant beyond the grid:
        the echo saturates once the target lies behind the whole echo)."""
        return tuple(np.interp(r0, self.r0, a) for a in (self.r_fog, self.r_lo, self.r_hi, self.i_fog))


def _refine_peak(alpha: float, grid: np.ndarray, values: np.ndarray, quad_nodes: int) -> tuple[float, float]:
    """Golden-section search for the maximum of i(R) around the grid maximum."""
    k = int(np.argmax(values))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    g = (np.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = soft_echo(np.array([c, d]), alpha, quad_nodes)
    for _ in range(60):  # interval shrinks by 0.618^60 ~ 3e-13
        if fc >= fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = soft_echo(np.array([c]), alpha, quad_nodes)[0]
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = soft_echo(np.array([d]), alpha, quad_nodes)[0]
    peak = 0.5 * (a + b)
    return float(peak), float(soft_echo(np.array([peak]), alpha, quad_nodes)[0])


def _build_table(alpha: float, r0_step: float, quad_nodes: int) -> SoftReturnTable:
    grid = np.arange(0.0, TABLE_RANGE + 0.5 * r0_step, r0_step)
    curve = soft_echo(grid, alpha, quad_nodes)
    peak, peak_value = _refine_peak(alpha, grid, curve, quad_nodes)
    curve = np.minimum(curve, peak_value)  # grid values cannot exceed the refined peak
    rising = (grid > OVERLAP_START) & (grid < peak)
    falling = grid > peak
    # Unimodality (rise to R*, then fall) is what makes R_fog = min(R0, R*) exact.
    if np.any(np.diff(curve[rising]) < 0) or np.any(np.diff(curve[falling]) > 0) or curve[-1] >= 0.5 * peak_value:
        raise RuntimeError(f"fog soft echo for alpha={alpha} is not unimodal on [0, {TABLE_RANGE}] m")

    r_fog = np.minimum(grid, peak)
    i_fog = np.where(grid < peak, curve, peak_value)
    # Rising and falling flanks with the exact peak inserted, for inverting i(R) = level.
    up_r = np.concatenate([[OVERLAP_START], grid[rising], [peak]])
    up_v = np.concatenate([[0.0], curve[rising], [peak_value]])
    down_r = np.concatenate([[peak], grid[falling]])
    down_v = np.concatenate([[peak_value], curve[falling]])
    level = 0.5 * i_fog
    r_lo = np.interp(level, up_v, up_r)
    r_hi_peak = np.interp(0.5 * peak_value, down_v[::-1], down_r[::-1])
    r_hi = np.where(grid < peak, grid, np.minimum(grid, r_hi_peak))
    no_fog = i_fog <= 0.0
    r_lo = np.where(no_fog, r_fog, np.minimum(r_lo, r_fog))
    r_hi = np.where(no_fog, r_fog, np.maximum(r_hi, r_fog))
    return SoftReturnTable(alpha, grid, r_fog, i_fog, r_lo, r_hi, peak)


def _cache_file(cache_dir: Path, alpha: float, r0_step: float, quad_nodes: int) -> Path:
    # Keyed by the code that builds the table too, so an edited module never reads an old table.
    physics = repr((_TABLE_VERSION, code_hash(__name__), TAU_H, OVERLAP_START, OVERLAP_FULL, TABLE_RANGE, alpha,
                    r0_step, quad_nodes))
    digest = hashlib.sha256(physics.encode()).hexdigest()[:16]
    return cache_dir / f"fog_soft_table_alpha{alpha:g}_{digest}.npz"


_FIELDS = ("r0", "r_fog", "i_fog", "r_lo", "r_hi", "peak_range")


@lru_cache(maxsize=128)
def _table(alpha: float, r0_step: float, quad_nodes: int, cache_dir: str | None) -> SoftReturnTable:
    path = None if cache_dir is None else _cache_file(Path(cache_dir), alpha, r0_step, quad_nodes)
    if path is not None and path.is_file():
        try:
            with np.load(path) as data:
                arrays = {k: np.asarray(data[k], dtype=np.float64) for k in _FIELDS}
            if all(np.all(np.isfinite(a)) for a in arrays.values()) and len(arrays["r0"]) > 1:
                peak = float(arrays.pop("peak_range"))
                return SoftReturnTable(alpha, peak_range=peak, **arrays)
        except (OSError, ValueError, KeyError):
            pass  # unreadable cache entry: rebuild and overwrite it
    table = _build_table(alpha, r0_step, quad_nodes)
    if path is not None:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **{k: getattr(table, k) for k in _FIELDS})
    return table


def soft_return_table(
    alpha: float,
    *,
    r0_step: float = DEFAULT_FIDELITY["r0_step"],
    quad_nodes: int = DEFAULT_FIDELITY["quad_nodes"],
    cache_dir: str | Path | None = None,
) -> SoftReturnTable:
    """The tabulated fog return (R_fog, i_fog, half-power interval) over R0 for one alpha,
    cached in memory and, if ``cache_dir`` is given, as an ``.npz`` there."""
    step, nodes = _check_fidelity({"r0_step": r0_step, "quad_nodes": quad_nodes})
    alpha, _, _ = _check_params({"alpha": alpha, "beta": 0.0})
    return _table(alpha, step, nodes, None if cache_dir is None else str(Path(cache_dir).resolve()))


# --------------------------------------------------------------------------- apply



def apply(
    scan: Scan,
    params: dict,
    sensor: SensorSpec,
    rng: np.random.Generator,
    *,
    ground: np.ndarray | None = None,
    fidelity: dict | None = None,
    cache_dir: str | Path | None = None,
    return_info: bool = False,
):
    """Apply fog with ``params`` (``alpha`` 1/m, ``beta`` 1/(m sr), ``range_jitter``).

    Every return is attenuated by ``exp(-2 alpha R0)``; a return whose fog echo is stronger
    becomes a fog return in front of it (same index, label ``WEATHER_RETURN_LABEL``,
    instance 0); an attenuated hard return below the detection floor is lost.
    ``alpha = 0`` returns ``scan`` itself. ``ground`` is unused (fog needs none).
    With ``return_info`` also returns ``{"lost", "changed", "weather"}`` masks.
    """
    del ground
    alpha, beta, jitter = _check_params(params)
    r0_step, quad_nodes = _check_fidelity(fidelity)
    n = len(scan)
    if alpha == 0.0 or n == 0:
        return unchanged(scan, return_info)
    scale = effect_scale(scan, sensor, "fog")
    pts = scan.points

    xyz = pts[:, :3].astype(np.float64)
    r2 = np.einsum("ij,ij->i", xyz, xyz)
    r = np.sqrt(r2)
    rho = pts[:, 3].astype(np.float64) / scale

    # Reporting quantum q and the detection floor F (power ~ rho / R^2), see module doc.
    positive = rho[rho > 0]
    q = min(float(positive.min()), MAX_QUANTUM) if len(positive) else MAX_QUANTUM
    rho_eff = np.where(rho > 0, rho, 0.5 * q)
    weakest = np.divide(rho_eff, r2, out=np.full(n, np.inf), where=r2 > 0).min()
    floor = min(0.5 * q / sensor.max_range**2, float(weakest))

    table = soft_return_table(alpha, r0_step=r0_step, quad_nodes=quad_nodes, cache_dir=cache_dir)
    transmission = np.exp(-2.0 * alpha * r)
    gain = np.interp(r, table.r0, table.i_fog) * (beta / BETA0)  # I_soft = gain * rho * R0^2
    # Compare echoes in power; multiply instead of dividing by R0^2 (R0 may be ~0).
    fog = gain * r2 > transmission
    lost = ~fog & (rho_eff * transmission < floor * r2)

    out = pts.copy()
    out[:, 3] = (pts[:, 3] * transmission).astype(np.float32)  # hard path: I exp(-2 alpha R0)
    idx = np.flatnonzero(fog)
    if len(idx):
        u = rng.uniform(-1.0, 1.0, size=len(idx))
        r_in = r[idx]
        centre, lo, hi, _ = table.lookup(r_in)
        hi = np.minimum(hi, r_in)
        rng_fog = centre + jitter * np.where(u < 0, u * (centre - lo), u * (hi - centre))
        rng_fog = np.clip(rng_fog, lo, hi)
        out[idx, :3] = (xyz[idx] * np.minimum(rng_fog / r_in, 1.0)[:, None]).astype(np.float32)
        # Power of the fog echo, reported at r_fog by a range-compensated sensor.
        rho_fog = gain[idx] * rho_eff[idx] * rng_fog * rng_fog
        out[idx, 3] = (np.clip(rho_fog, 0.0, 1.0) * scale).astype(np.float32)

    semantic, instance = scan.semantic, scan.instance
    if len(idx):
        if semantic is not None:
            semantic = semantic.copy()
            semantic[idx] = WEATHER_RETURN_LABEL
        if instance is not None:
            instance = instance.copy()
            instance[idx] = 0
    result = replace(scan, points=out, semantic=semantic, instance=instance)
    if lost.any():
        result = result.select(~lost)
    if not return_info:
        return result
    changed = np.any(out != pts, axis=1)
    if semantic is not None:
        changed |= semantic != scan.semantic
    if instance is not None:
        changed |= instance != scan.instance
    changed &= ~lost
    return result, {"lost": lost, "changed": changed, "weather": fog[~lost]}


# --------------------------------------------------------------------------- fidelity study


def accuracy_time_curve(scan: Scan, sensor: SensorSpec, severity: str, seeds) -> list[dict]:
    """Accuracy against time for every value in ``FIDELITY_LEVELS`` (other knob at its
    default), against the highest-fidelity setting, averaged over the nonzero ``ALPHAS``
    and ``seeds`` (which drive the range jitter).

    Each row: knob, value, is_default, table_s (cold build of all alphas' tables),
    apply_s (median warm time per scan), and the mean absolute errors of the fog
    fraction, lost fraction, mean output intensity (sensor scale) and mean fog range (m).
    """
    seeds = list(seeds)
    if severity not in SEVERITIES:
        raise InputError(None, f"unknown fog severity {severity!r}; known: {', '.join(SEVERITIES)}")
    beta = SEVERITIES[severity]["beta"]
    alphas = [a for a in ALPHAS if a > 0]

    def stats(fidelity: dict) -> tuple[np.ndarray, list[float]]:
        rows, times = [], []
        for alpha in alphas:
            for seed in seeds:
                t0 = time.perf_counter()
                out, info = apply(
                    scan, {"alpha": alpha, "beta": beta, "range_jitter": 1.0}, sensor,
                    np.random.default_rng(seed), fidelity=fidelity, return_info=True,
                )
                times.append(time.perf_counter() - t0)
                weather = info["weather"]
                fog_range = np.linalg.norm(out.points[weather, :3], axis=1)
                rows.append([
                    weather.sum() / len(scan),
                    info["lost"].mean(),
                    float(out.points[:, 3].mean()) if len(out) else 0.0,
                    float(fog_range.mean()) if len(fog_range) else 0.0,
                ])
        return np.asarray(rows), times

    def build_time(step: float, nodes: int) -> float:
        t0 = time.perf_counter()
        for alpha in alphas:
            _build_table(alpha, step, nodes)
        return time.perf_counter() - t0

    reference, _ = stats(_HIGHEST_FIDELITY)
    curve = []
    for knob, values in FIDELITY_LEVELS.items():
        for value in values:
            fidelity = {**DEFAULT_FIDELITY, knob: value}
            result, times = stats(fidelity)
            err = np.abs(result - reference).mean(axis=0)
            curve.append({
                "knob": knob,
                "value": value,
                "is_default": DEFAULT_FIDELITY[knob] == value,
                "table_s": build_time(fidelity["r0_step"], fidelity["quad_nodes"]),
                "apply_s": float(np.median(times)),
                "err_fog_fraction": float(err[0]),
                "err_lost_fraction": float(err[1]),
                "err_mean_intensity": float(err[2]),
                "err_fog_range_m": float(err[3]),
            })
    return curve
