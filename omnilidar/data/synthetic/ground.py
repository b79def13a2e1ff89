"""The ground: a tilted plane plus a rasterised residual height and class map.

Ground height is ``plane(x, y) + residual[cell]``: the plane carries the gentle
slope of the whole scene, the residual raster carries road crowns, raised
sidewalks (the kerb is a step between neighbouring cells), flush parking lots and
terrain relief. A second raster gives each cell its SemanticKITTI class and a
third its reflectivity (with painted lane markings), so the ray caster needs only
a height-field march and two look-ups.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from omnilidar.data.synthetic import classes as C
from omnilidar.data.synthetic.roads import Road


@dataclass(frozen=True)
class Area:
    """A paved or parking patch behind a sidewalk: road-frame rectangle of one road."""

    road: int
    side: int  # 0 right (d < 0), 1 left (d > 0)
    s0: float
    s1: float
    d0: float  # |d| range
    d1: float
    semantic: int  # PARKING or OTHER_GROUND


@dataclass(frozen=True)
class GroundMap:
    """Height, class and reflectivity rasters over the scene rectangle.

    Cell (i, j) covers x in [x0 + j res, x0 + (j+1) res), y in [y0 + i res, ...).
    Outside the raster the ground is the bare plane with class terrain.
    """

    x0: float
    y0: float
    res: float
    plane: tuple[float, float, float]  # z = a x + b y + c
    residual: np.ndarray  # (ny, nx) float32
    semantic: np.ndarray  # (ny, nx) uint16
    reflectivity: np.ndarray  # (ny, nx) float32

    TILE = 8  # cells per side of a ray-marching skip tile

    @functools.cached_property
    def tile_max(self) -> np.ndarray:
        """Max residual over each TILE x TILE tile and its 8 neighbours (float64),
        so a ray above it can skip one tile-width of travel at once."""
        ny, nx = self.residual.shape
        t = self.TILE
        py, px = (-ny) % t, (-nx) % t
        padded = np.pad(self.residual.astype(np.float64), ((0, py), (0, px)), constant_values=-np.inf)
        tiles = padded.reshape(padded.shape[0] // t, t, padded.shape[1] // t, t).max(axis=(1, 3))
        # Outside the raster the ground is the bare plane (residual 0).
        grown = np.pad(tiles, 1, constant_values=0.0)
        out = np.full_like(tiles, -np.inf)
        for di in (0, 1, 2):
            for dj in (0, 1, 2):
                out = np.maximum(out, grown[di:di + tiles.shape[0], dj:dj + tiles.shape[1]])
        return out

    @property
    def residual_range(self) -> tuple[float, float]:
        return float(self.residual.min()), float(self.residual.max())

    def cell(self, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside) of the cells holding world points (x, y)."""
        ny, nx = self.residual.shape
        j = np.floor((np.asarray(x) - self.x0) / self.res).astype(np.int64)
        i = np.floor((np.asarray(y) - self.y0) / self.res).astype(np.int64)
        inside = (i >= 0) & (i < ny) & (j >= 0) & (j < nx)
        return np.clip(i, 0, ny - 1), np.clip(j, 0, nx - 1), inside

    def height(self, x, y) -> np.ndarray:
        """Ground height at world points (x, y)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        i, j, inside = self.cell(x, y)
        a, b, c = self.plane
        return a * x + b * y + c + np.where(inside, self.residual[i, j], 0.0)


def _smooth_noise(xs: np.ndarray, ys: np.ndarray, rng: np.random.Generator,
                  wavelengths=(12.0, 25.0, 50.0)) -> np.ndarray:
    """Band-limited noise in [-1, 1] on the grid ``ys x xs`` from a few random plane
    waves. sin(a x + b y + p) = sin(a x + p) cos(b y) + cos(a x + p) sin(b y), so
    each wave is two outer products of 1-D arrays (no trig over the raster)."""
    out = np.zeros((len(ys), len(xs)), dtype=np.float64)
    total = 0.0
    for lam in wavelengths:
        for _ in range(2):
            theta = rng.uniform(0.0, 2.0 * np.pi)
            amp = lam / wavelengths[-1]
            k = 2.0 * np.pi / (lam * rng.uniform(0.8, 1.25))
            ax = k * np.cos(theta) * xs + rng.uniform(0.0, 2.0 * np.pi)
            by = k * np.sin(theta) * ys
            out += amp * (np.outer(np.cos(by), np.sin(ax)) + np.outer(np.sin(by), np.cos(ax)))
            total += amp
    return out / total


def build_ground(roads: list[Road], areas: list[Area], extent: tuple[float, float, float, float],
                 world: dict, rng: np.random.Generator) -> GroundMap:
    """Rasterise roads, parking strips, sidewalks, lots and terrain over ``extent``
    (xmin, ymin, xmax, ymax)."""
    res = float(world["grid_m"])
    xmin, ymin, xmax, ymax = extent
    nx = int(np.ceil((xmax - xmin) / res))
    ny = int(np.ceil((ymax - ymin) / res))
    xs = xmin + (np.arange(nx) + 0.5) * res
    ys = ymin + (np.arange(ny) + 0.5) * res
    X, Y = np.meshgrid(xs, ys)

    frames = [r.to_frame(X, Y) for r in roads]
    # Distance beyond each road's kerb; the nearest road (smallest) owns the cell's cross-section.
    beyond = np.stack([np.abs(d) - r.half_width for r, (_, d) in zip(roads, frames)])
    owner = np.argmin(beyond, axis=0)
    on_road = (beyond < 0).any(axis=0)

    residual = np.zeros((ny, nx), np.float64)
    semantic = np.full((ny, nx), C.TERRAIN, np.uint16)
    side = np.zeros((ny, nx), np.int8)
    e = np.take_along_axis(beyond, owner[None], axis=0)[0]
    d_own = np.choose(owner, [d for _, d in frames]) if len(roads) > 1 else frames[0][1]
    side[:] = (d_own > 0).astype(np.int8)
    parking_w = np.zeros((ny, nx))
    sidewalk_w = np.zeros((ny, nx))
    curb = np.zeros((ny, nx))
    for k, r in enumerate(roads):
        mine = owner == k
        for sd in (0, 1):
            m = mine & (side == sd)
            parking_w[m] = r.parking_width[sd]
            sidewalk_w[m] = r.sidewalk_width[sd]
        curb[mine] = r.curb_height

    parking = ~on_road & (e < parking_w)
    sidewalk = ~on_road & ~parking & (e < parking_w + sidewalk_w)
    behind = ~on_road & ~parking & ~sidewalk
    semantic[parking] = C.PARKING
    semantic[sidewalk] = C.SIDEWALK
    # Road crown: a few cm at the centre-line falling to 0 at the kerb, max over crossing roads.
    crown = np.zeros((ny, nx))
    for r, (_, d) in zip(roads, frames):
        crown = np.maximum(crown, 0.06 * np.clip(1.0 - np.abs(d) / r.half_width, 0.0, 1.0))
    residual[on_road] = crown[on_road]
    semantic[on_road] = C.ROAD
    # Sidewalks drain towards the road (1 % cross-fall).
    residual[sidewalk] = curb[sidewalk] + 0.01 * (e - parking_w)[sidewalk]
    base = curb + 0.01 * sidewalk_w
    # Terrain: relief fades in over 4 m behind the sidewalk.
    relief = float(world["terrain_relief_m"]) * np.clip(_smooth_noise(xs, ys, rng) * 1.2 + 0.3, -0.4, 1.0)
    fade = np.clip((e - parking_w - sidewalk_w) / 4.0, 0.0, 1.0)
    residual[behind] = (base + fade * relief)[behind]

    for area in areas:
        s, d = frames[area.road]
        sign = 1.0 if area.side == 1 else -1.0
        m = ~on_road & (s >= area.s0) & (s < area.s1) & (sign * d >= area.d0) & (sign * d < area.d1)
        semantic[m] = area.semantic
        residual[m] = base[m]

    # Reflectivity: per-class ranges, patchy (low-frequency) and per-cell variation.
    refl = np.empty((ny, nx), np.float64)
    patch = 0.5 + 0.5 * _smooth_noise(xs, ys, rng, wavelengths=(6.0, 15.0))
    grain = rng.uniform(0.0, 1.0, size=(ny, nx))
    for cls in C.GROUND_CLASSES:
        lo, hi = C.REFLECTIVITY[cls]
        m = semantic == cls
        refl[m] = lo + (hi - lo) * (0.6 * patch[m] + 0.4 * grain[m])

    # Lane markings: edge lines (solid) and lane dividers (dashed 3 m on / 6 m off).
    lo, hi = C.LANE_MARKING_REFLECTIVITY
    for k, r in enumerate(roads):
        s, d = frames[k]
        alone = on_road & np.all(np.delete(beyond, k, axis=0) >= 0, axis=0) if len(roads) > 1 else on_road
        paint = np.zeros((ny, nx), bool)
        for off in (r.half_width - 0.3, -(r.half_width - 0.3)):
            paint |= np.abs(d - off) < 0.1
        for lane in range(1, r.lanes):
            off = -r.half_width + lane * r.lane_width
            dashed = (np.mod(s, 9.0) < 3.0) if 2 * lane != r.lanes else True
            paint |= (np.abs(d - off) < 0.1) & dashed
        m = paint & alone
        refl[m] = rng.uniform(lo, hi, size=int(m.sum()))

    # Gentle slope of the whole scene.
    slope = float(world["max_slope"])
    a, b = rng.uniform(-slope, slope, size=2) / np.sqrt(2.0)
    return GroundMap(
        x0=float(xmin), y0=float(ymin), res=res, plane=(float(a), float(b), 0.0),
        residual=residual.astype(np.float32), semantic=semantic, reflectivity=refl.astype(np.float32),
    )
