"""Spherical range-image projection (R2DM convention) and its inverse.

Convention (angles in radians, atan2 conventions of numpy):

* azimuth ``az = atan2(y, x)`` in [-pi, pi]; column coordinate
  ``u = 0.5 * (1 - az / pi) * W``. Column 0 starts at az = +pi (behind the sensor,
  left side) and azimuth decreases to the right; the forward direction (az = 0) is
  at u = W / 2.
* elevation ``el = atan2(z, hypot(x, y))`` (equal to asin(z / r) but needs no
  clipping of z / r and is accurate near +-90 deg); row coordinate
  ``v = (1 - (el - fov_down) / (fov_up - fov_down)) * H``. Row 0 is the top.
* pixel = (floor(v), floor(u)) clipped to [0, H-1] x [0, W-1]. Points above or below
  the vertical field of view land in the first or last row (as in R2DM). Both seam
  azimuths map to valid columns: az = +pi -> column 0, az = -pi -> column W-1 (the
  two columns are neighbours across the seam).
* a pixel's centre has ``el = fov_up - (row + 0.5) / H * (fov_up - fov_down)`` and
  ``az = pi * (1 - 2 * (col + 0.5) / W)``; :func:`unproject` and
  :func:`beam_angle_features` use these angles.

Validity: a point takes part iff all four of its values are finite and its range,
rounded to float32, satisfies ``min_range < r < max_range`` (strict, limits compared
in float32). The same test masks encoded and decoded images, so a valid pixel stays
valid through encode/decode except within float32 rounding of the limits.
Among the valid points that fall into a pixel, the nearest wins; equal ranges go to
the lower point index.

Encoding (two channels in [-1, 1]): channel 0 is log-range
``2 * clamp(log2(d + 1) / log2(max_range + 1), 0, 1) - 1``, channel 1 is ``2 i - 1``
with intensity ``i`` in [0, 1] (the sensor's intensity divided by its
``intensity_scale``). Pixels without a valid return are exactly -1 in both channels.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from omnilidar.errors import InputError
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec, levelled_to_sensor, sensor_to_levelled

_F32_MAX = float(np.finfo(np.float32).max)


@dataclass(frozen=True)
class RangeImageSpec:
    """Size, vertical field of view (degrees) and valid range (metres) of a range image."""

    height: int
    width: int
    fov_up_deg: float
    fov_down_deg: float
    min_range: float
    max_range: float
    # Nose-down tilt of the sensor in the (gravity-levelled) frame the points are
    # stored in: scans are projected in the sensor's own frame, so rows are beams.
    pitch_deg: float = 0.0

    def __post_init__(self):
        for name in ("height", "width"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise InputError(None, f"range image spec: {name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("fov_up_deg", "fov_down_deg", "min_range", "max_range", "pitch_deg"):
            value = float(getattr(self, name))
            if not np.isfinite(value):
                raise InputError(None, f"range image spec: {name} must be finite, got {value!r}")
            object.__setattr__(self, name, value)
        if not -90.0 <= self.fov_down_deg < self.fov_up_deg <= 90.0:
            raise InputError(
                None,
                f"range image spec: need -90 <= fov_down_deg < fov_up_deg <= 90, "
                f"got {self.fov_down_deg} / {self.fov_up_deg}",
            )
        if not 0.0 <= self.min_range < self.max_range:
            raise InputError(
                None,
                f"range image spec: need 0 <= min_range < max_range, got {self.min_range} / {self.max_range}",
            )

    @classmethod
    def from_sensor(cls, sensor: SensorSpec, height: int | None = None, width: int = 1024) -> "RangeImageSpec":
        """The sensor's field of view and valid range; ``height`` defaults to its beam count."""
        return cls(
            height=sensor.num_beams if height is None else height,
            width=width,
            fov_up_deg=sensor.fov_up_deg,
            fov_down_deg=sensor.fov_down_deg,
            min_range=sensor.min_range,
            max_range=sensor.max_range,
            pitch_deg=sensor.mount_pitch_deg,
        )

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def fov_up(self) -> float:
        return float(np.deg2rad(self.fov_up_deg))

    @property
    def fov_down(self) -> float:
        return float(np.deg2rad(self.fov_down_deg))

    @property
    def log_max(self) -> float:
        """log2(max_range + 1), the log-range normaliser (log2(81) for 80 m)."""
        return float(np.log2(self.max_range + 1.0))


@dataclass(frozen=True)
class ProjectionResult:
    """Output of :func:`project`.

    range_img: (H, W) float32 metres, 0 where no valid point landed.
    intensity_img: (H, W) float32 in [0, 1], 0 where empty.
    point_row, point_col: (N,) int32 pixel of every point (also for finite points
        outside the range limits); -1 for points with a non-finite value.
    point_index_img: (H, W) int64 index of the winning point, -1 where empty.
    valid: (N,) bool, finite and inside the range limits.
    """

    range_img: np.ndarray
    intensity_img: np.ndarray
    point_row: np.ndarray
    point_col: np.ndarray
    point_index_img: np.ndarray
    valid: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: pixels holding a return."""
        return self.point_index_img >= 0

    def per_pixel(self, values: np.ndarray, empty=0) -> np.ndarray:
        """(H, W) each pixel's winning point's entry of ``values`` (N,), e.g. its label; ``empty``
        where no point landed."""
        return np.where(self.mask, np.asarray(values)[np.maximum(self.point_index_img, 0)], empty)

    @property
    def winner(self) -> np.ndarray:
        """(N,) bool: points that won their pixel (survive a round trip)."""
        won = np.zeros(len(self.valid), bool)
        won[self.point_index_img[self.point_index_img >= 0]] = True
        return won


def _check_scale(intensity_scale: float) -> float:
    scale = float(intensity_scale)
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(None, f"intensity_scale must be a positive finite number, got {intensity_scale!r}")
    return scale


def _valid_range(d: np.ndarray, spec: RangeImageSpec) -> np.ndarray:
    """float32 ranges strictly inside the limits (NaN compares false)."""
    d = np.asarray(d, np.float32)
    return (d > np.float32(spec.min_range)) & (d < np.float32(spec.max_range))


def pixel_angles(spec: RangeImageSpec) -> tuple[np.ndarray, np.ndarray]:
    """Elevation per row (H,) and azimuth per column (W,) at pixel centres, radians (float64)."""
    rows = np.arange(spec.height, dtype=np.float64)
    cols = np.arange(spec.width, dtype=np.float64)
    elev = spec.fov_up - (rows + 0.5) / spec.height * (spec.fov_up - spec.fov_down)
    azim = np.pi * (1.0 - 2.0 * (cols + 0.5) / spec.width)
    return elev, azim


def project(points: np.ndarray, spec: RangeImageSpec, intensity_scale: float = 1.0) -> ProjectionResult:
    """Project (N, 4) x, y, z, intensity points into a range image; nearest return wins.

    Intensities are divided by ``intensity_scale`` and clipped to [0, 1]. Invalid
    points (non-finite, at or beyond the range limits) never win a pixel. Runs in
    O(N) vectorised numpy (a scatter-min on ranges, then on indices for ties).
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 4:
        raise InputError(None, f"project: points must be an (N, 4) array, got shape {pts.shape}")
    scale = _check_scale(intensity_scale)
    n = len(pts)
    h, w = spec.height, spec.width

    finite = np.isfinite(pts).all(axis=1)
    xyz = pts[:, :3].astype(np.float64)
    if not finite.all():
        xyz[~finite] = 0.0  # keep trig quiet; these points are flagged invalid below
    xyz = levelled_to_sensor(xyz, spec.pitch_deg)
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rho = np.sqrt(x * x + y * y)  # squares of float32-range values cannot overflow float64
    rng = np.sqrt(rho * rho + z * z)
    rng32 = np.minimum(rng, _F32_MAX).astype(np.float32)
    valid = finite & _valid_range(rng32, spec)

    u = 0.5 * (1.0 - np.arctan2(y, x) / np.pi) * w
    v = (1.0 - (np.arctan2(z, rho) - spec.fov_down) / (spec.fov_up - spec.fov_down)) * h
    col = np.clip(np.floor(u), 0, w - 1).astype(np.int32)
    row = np.clip(np.floor(v), 0, h - 1).astype(np.int32)
    col[~finite] = -1
    row[~finite] = -1

    idx = np.flatnonzero(valid)
    pix = row[idx].astype(np.int64) * w + col[idx]
    r_valid = rng32[idx]
    best = np.full(h * w, np.inf, np.float32)
    np.minimum.at(best, pix, r_valid)
    tie = r_valid == best[pix]  # every point at its pixel's minimum range
    winner = np.full(h * w, n, np.int64)
    np.minimum.at(winner, pix[tie], idx[tie])
    filled = np.flatnonzero(winner < n)
    won = winner[filled]

    range_img = np.zeros(h * w, np.float32)
    range_img[filled] = rng32[won]
    inten = pts[won, 3].astype(np.float64) / scale
    intensity_img = np.zeros(h * w, np.float32)
    intensity_img[filled] = np.clip(inten, 0.0, 1.0)
    index_img = np.full(h * w, -1, np.int64)
    index_img[filled] = won
    return ProjectionResult(
        range_img=range_img.reshape(h, w),
        intensity_img=intensity_img.reshape(h, w),
        point_row=row,
        point_col=col,
        point_index_img=index_img.reshape(h, w),
        valid=valid,
    )


def _check_image(name: str, img: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(img)
    if arr.shape != shape:
        raise InputError(None, f"{name} must have shape {shape}, got {arr.shape}")
    return arr


def encode(range_img: np.ndarray, intensity_img: np.ndarray, spec: RangeImageSpec) -> np.ndarray:
    """(2, H, W) float32 network input in [-1, 1]: log-range and intensity; empty = -1."""
    d = _check_image("range_img", range_img, spec.shape).astype(np.float32)
    i = _check_image("intensity_img", intensity_img, spec.shape)
    mask = _valid_range(d, spec)  # NaN/Inf and out-of-range pixels are empty
    d64 = np.where(mask, d, 0.0).astype(np.float64)
    depth = np.clip(np.log2(d64 + 1.0) / spec.log_max, 0.0, 1.0)
    inten = np.clip(np.nan_to_num(np.asarray(i, np.float64), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    out = np.full((2, *spec.shape), -1.0, np.float32)
    out[0][mask] = 2.0 * depth[mask] - 1.0
    out[1][mask] = 2.0 * inten[mask] - 1.0
    return out


def encoded_min_range(spec: RangeImageSpec) -> float:
    """Channel-0 value of a return at min_range: decoded values at or below it are empty
    (about -0.592 for KITTI's 1.45 / 80 m)."""
    return float(2.0 * np.log2(spec.min_range + 1.0) / spec.log_max - 1.0)


def decode(image: np.ndarray, spec: RangeImageSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Invert :func:`encode`: (range_img metres, intensity_img 0..1, mask), all (H, W).

    Values are clipped to [-1, 1] first (NaN counts as -1); a pixel is a return iff
    its decoded float32 range lies strictly inside the valid range limits.
    """
    img = _check_image("image", image, (2, *spec.shape))
    x = np.clip(np.nan_to_num(np.asarray(img[0], np.float64), nan=-1.0), -1.0, 1.0)
    d = (np.exp2((x + 1.0) * 0.5 * spec.log_max) - 1.0).astype(np.float32)
    mask = _valid_range(d, spec)
    inten = np.clip(np.nan_to_num((np.asarray(img[1], np.float64) + 1.0) * 0.5, nan=0.0), 0.0, 1.0)
    range_img = np.where(mask, d, np.float32(0.0)).astype(np.float32)
    intensity_img = np.where(mask, inten, 0.0).astype(np.float32)
    return range_img, intensity_img, mask


def unproject(
    range_img: np.ndarray,
    intensity_img: np.ndarray,
    spec: RangeImageSpec,
    mask: np.ndarray | None = None,
    intensity_scale: float = 1.0,
) -> np.ndarray:
    """(M, 4) float32 points at the pixel-centre angles, in row-major pixel order.

    ``mask`` defaults to the pixels with a valid range; an explicit mask is still
    restricted to finite ranges. Intensities are multiplied by ``intensity_scale``.
    """
    d = _check_image("range_img", range_img, spec.shape).astype(np.float64)
    i = _check_image("intensity_img", intensity_img, spec.shape)
    scale = _check_scale(intensity_scale)
    if mask is None:
        keep = _valid_range(d.astype(np.float32), spec)
    else:
        keep = _check_image("mask", mask, spec.shape).astype(bool) & np.isfinite(d)
    rows, cols = np.nonzero(keep)  # row-major order
    elev, azim = pixel_angles(spec)
    el, az = elev[rows], azim[cols]
    dist = d[rows, cols]
    horiz = dist * np.cos(el)
    out = np.empty((len(rows), 4), np.float32)
    out[:, 0] = horiz * np.cos(az)
    out[:, 1] = horiz * np.sin(az)
    out[:, 2] = dist * np.sin(el)
    if spec.pitch_deg != 0.0:
        out[:, :3] = sensor_to_levelled(out[:, :3].astype(np.float64), spec.pitch_deg)
    inten = np.clip(np.nan_to_num(np.asarray(i, np.float64)[rows, cols], nan=0.0), 0.0, 1.0)
    out[:, 3] = inten * scale
    return out


def beam_angle_features(spec: RangeImageSpec, n_elev: int = 6, n_azim: int = 10) -> np.ndarray:
    """Fourier features of the pixel-centre angles, (2 * (n_elev + n_azim), H, W) float32.

    Channel order: sin(k el) for k = 0..n_elev-1, cos(k el), sin(k az) for
    k = 0..n_azim-1, cos(k az). Angles are the true ones in radians (not pixel indices);
    k = 0 gives the constant 0 / 1 channels, kept so the count matches R2DM's 32.
    """
    if n_elev < 1 or n_azim < 1:
        raise InputError(None, f"beam_angle_features: need n_elev, n_azim >= 1, got {n_elev}, {n_azim}")
    elev, azim = pixel_angles(spec)
    h, w = spec.shape
    ke = np.arange(n_elev)[:, None] * elev[None, :]  # (n_elev, H)
    ka = np.arange(n_azim)[:, None] * azim[None, :]  # (n_azim, W)
    out = np.empty((2 * (n_elev + n_azim), h, w), np.float32)
    out[:n_elev] = np.sin(ke)[:, :, None]
    out[n_elev : 2 * n_elev] = np.cos(ke)[:, :, None]
    out[2 * n_elev : 2 * n_elev + n_azim] = np.sin(ka)[:, None, :]
    out[2 * n_elev + n_azim :] = np.cos(ka)[:, None, :]
    return out


def to_range_image(scan: Scan, spec: RangeImageSpec) -> np.ndarray:
    """Encode a scan as a (2, H, W) float32 image (intensity normalised by its scale)."""
    proj = project(scan.points, spec, intensity_scale=scan.intensity_scale)
    return encode(proj.range_img, proj.intensity_img, spec)


def from_range_image(
    image: np.ndarray, spec: RangeImageSpec, intensity_scale: float = 1.0, ring_from_row: bool = False
) -> Scan:
    """Decode a (2, H, W) image into a scan (row-major point order).

    With ``ring_from_row`` the row index becomes the point's ring (meaningful when
    the image rows are the sensor's beams, e.g. 64 rows for the HDL-64E).
    """
    range_img, intensity_img, mask = decode(image, spec)
    points = unproject(range_img, intensity_img, spec, mask=mask, intensity_scale=intensity_scale)
    ring = None
    if ring_from_row:
        ring = np.nonzero(mask)[0].astype(np.int16)
    return Scan(points=points, ring=ring, intensity_scale=float(intensity_scale))


def round_trip(scan: Scan, spec: RangeImageSpec) -> Scan:
    """A scan as the generator would emit it if it were perfect: projected into ``spec``'s
    range image (nearest return per pixel), encoded and decoded as the network's input and
    output are, and back-projected; each kept point carries the labels (semantic, instance)
    of its pixel's winning point and that beam's row as its ring. Only the image's size and
    quantisation are lost: what a sensor of ``spec``'s resolution would have seen."""
    proj = project(scan.points, spec, intensity_scale=scan.intensity_scale)
    image = encode(proj.range_img, proj.intensity_img, spec)
    range_img, intensity_img, mask = decode(image, spec)
    mask &= proj.point_index_img >= 0  # decoding never invents a return, but never trust it to
    points = unproject(range_img, intensity_img, spec, mask=mask, intensity_scale=scan.intensity_scale)
    winners = proj.point_index_img[mask]  # row-major, as unproject orders its points
    return replace(scan.select(winners), points=points, ring=np.nonzero(mask)[0].astype(np.int16))
