"""Street layout: where buildings, vegetation, street furniture and road users go.

Placement works in each road's (s, d) frame so that every object lines up with
its road (frontages follow curves, parked cars follow the kerb, moving traffic
keeps right). An occupancy set of discs keeps objects apart and keeps the ego
platform's corridors (the vehicle's lane, the quadruped's walking line) free.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnilidar.data.synthetic import classes as C
from omnilidar.data.synthetic import objects
from omnilidar.data.synthetic.ground import Area, GroundMap
from omnilidar.data.synthetic.primitives import PrimitiveBuilder
from omnilidar.data.synthetic.roads import Road


class Occupancy:
    """Discs (x, y, r) already taken; a new disc is free if it overlaps none."""

    def __init__(self) -> None:
        self._xyr = np.zeros((256, 3))
        self._n = 0

    def free(self, x: float, y: float, r: float) -> bool:
        a = self._xyr[: self._n]
        return bool(np.all((a[:, 0] - x) ** 2 + (a[:, 1] - y) ** 2 >= (a[:, 2] + r) ** 2))

    def add(self, x: float, y: float, r: float) -> None:
        if self._n == len(self._xyr):
            self._xyr = np.concatenate([self._xyr, np.zeros_like(self._xyr)])
        self._xyr[self._n] = (x, y, r)
        self._n += 1


@dataclass(frozen=True)
class Building:
    x: float
    y: float
    yaw: float
    length: float
    depth: float
    height: float


def _vehicle_discs(x, y, yaw, length, width):
    """Three discs along a vehicle's axis approximating its footprint."""
    r = width / 2 + 0.25
    off = max(length / 2 - r, 0.0)
    c, s = np.cos(yaw), np.sin(yaw)
    return [(x + k * off * c, y + k * off * s, r) for k in (-1.0, 0.0, 1.0)]


class Layout:
    """Places everything of one scene into a primitive builder (see module docstring)."""

    def __init__(self, roads: list[Road], extent, world: dict, rng: np.random.Generator):
        self.roads = roads
        self.extent = extent
        self.world = world
        self.rng = rng
        self.occupancy = Occupancy()
        self.buildings: list[Building] = []
        self.areas: list[Area] = []
        self.green_gaps: list[tuple[int, int, float, float]] = []  # (road, side, s0, s1)
        self.boxes: list[tuple] = []  # (box7, semantic, instance)
        self.next_instance = 1
        xmin, ymin, xmax, ymax = extent
        gx, gy = np.meshgrid(np.linspace(xmin, xmax, 41), np.linspace(ymin, ymax, 41))
        self.s_range = []
        for r in roads:
            s, _ = r.to_frame(gx.ravel(), gy.ravel())
            lo = max(float(s.min()), r.s_min) if np.isfinite(r.s_min) else float(s.min())
            self.s_range.append((lo, float(s.max())))

    # -- geometry helpers ----------------------------------------------------
    def _u(self, key: str) -> float:
        lo, hi = self.world[key]
        return float(self.rng.uniform(lo, hi))

    def clear_of_roads(self, x, y, margin: float, to: str = "sidewalk") -> np.ndarray:
        """True where points are at least ``margin`` beyond every road's kerb
        (``to="kerb"``) or sidewalk back edge (``to="sidewalk"``)."""
        x = np.atleast_1d(np.asarray(x, dtype=np.float64))
        y = np.atleast_1d(np.asarray(y, dtype=np.float64))
        ok = np.ones(x.shape, bool)
        for r in self.roads:
            _, d = r.to_frame(x, y)
            right, left = (r.kerb_offset(0), r.kerb_offset(1)) if to == "kerb" else (r.sidewalk_outer(0), r.sidewalk_outer(1))
            edge = np.where(d > 0, left, right)
            ok &= np.abs(d) >= edge + margin
        return ok

    def inside_building(self, x, y, margin: float = 0.0) -> np.ndarray:
        x = np.atleast_1d(np.asarray(x, dtype=np.float64))
        y = np.atleast_1d(np.asarray(y, dtype=np.float64))
        inside = np.zeros(x.shape, bool)
        for bld in self.buildings:
            c, s = np.cos(bld.yaw), np.sin(bld.yaw)
            lx = c * (x - bld.x) + s * (y - bld.y)
            ly = -s * (x - bld.x) + c * (y - bld.y)
            inside |= (np.abs(lx) < bld.length / 2 + margin) & (np.abs(ly) < bld.depth / 2 + margin)
        return inside

    def new_instance(self) -> int:
        inst = self.next_instance
        self.next_instance += 1
        return inst

    # -- stage 1: frontages (before the ground raster) -----------------------
    def plan_frontages(self) -> None:
        """Buildings along each side of each road, with gaps that become parking
        lots, paved yards or green space."""
        w = self.world
        for k, road in enumerate(self.roads):
            s_lo, s_hi = self.s_range[k]
            for side in (0, 1):
                sign = 1.0 if side == 1 else -1.0
                back = road.sidewalk_outer(side)
                s = s_lo - self.rng.uniform(0.0, 20.0)
                while s < s_hi:
                    if self.rng.uniform() < w["building_probability"]:
                        length = self._u("building_length_m")
                        depth = self._u("building_depth_m")
                        setback = self._u("building_setback_m")
                        height = self._u("building_height_m")
                        sc = s + length / 2
                        d = sign * (back + setback + depth / 2)
                        x, y = road.point(sc, d)
                        yaw = float(road.heading(sc))
                        c, sn = np.cos(yaw), np.sin(yaw)
                        lx, ly = np.meshgrid([-length / 2, 0, length / 2], [-depth / 2, 0, depth / 2])
                        px = float(x) + c * lx.ravel() - sn * ly.ravel()
                        py = float(y) + sn * lx.ravel() + c * ly.ravel()
                        if self.clear_of_roads(px, py, 0.5).all():
                            self.buildings.append(Building(float(x), float(y), yaw, length, depth, height))
                        s += length + self.rng.uniform(0.0, 2.0)
                    else:
                        gap = self._u("gap_length_m")
                        u = self.rng.uniform()
                        if u < w["parking_lot_probability"]:
                            gap = max(gap, 14.0)
                            self.areas.append(Area(k, side, s, s + gap, back, back + self.rng.uniform(12.0, 22.0),
                                                   C.PARKING))
                        elif u < w["parking_lot_probability"] + w["paved_yard_probability"]:
                            self.areas.append(Area(k, side, s, s + gap, back, back + self.rng.uniform(5.0, 15.0),
                                                   C.OTHER_GROUND))
                        else:
                            self.green_gaps.append((k, side, s, s + gap))
                        s += gap

    # -- stage 2: everything that stands on the ground -----------------------
    def populate(self, b: PrimitiveBuilder, ground: GroundMap) -> None:
        self._buildings(b, ground)
        self._street_furniture(b, ground)
        self._parked_vehicles(b, ground)
        self._moving_traffic(b, ground)
        self._people(b, ground)
        self._vegetation(b, ground)

    def _z0(self, ground: GroundMap, x, y) -> float:
        return float(ground.height(np.atleast_1d(x), np.atleast_1d(y)).min())

    def _buildings(self, b: PrimitiveBuilder, ground: GroundMap) -> None:
        w = self.world
        for bld in self.buildings:
            c, s = np.cos(bld.yaw), np.sin(bld.yaw)
            lx = np.array([-1, 1, 1, -1]) * bld.length / 2
            ly = np.array([-1, -1, 1, 1]) * bld.depth / 2
            z0 = self._z0(ground, bld.x + c * lx - s * ly, bld.y + s * lx + c * ly)
            objects.wall(b, self.rng, bld.x, bld.y, z0, bld.yaw, bld.length, bld.depth, bld.height, C.BUILDING)
            if self.rng.uniform() < 0.35:  # a set-back upper storey or roof structure
                h2 = self.rng.uniform(1.5, 4.0)
                objects.wall(b, self.rng, bld.x, bld.y, z0 + bld.height, bld.yaw, bld.length * self.rng.uniform(0.4, 0.9),
                             bld.depth * self.rng.uniform(0.4, 0.9), h2, C.BUILDING)
            # Front boundary: hedge or fence along the street side of the plot.
            for sign in (-1.0, 1.0):
                fx, fy = bld.x - s * sign * (bld.depth / 2 + 0.9), bld.y + c * sign * (bld.depth / 2 + 0.9)
                if not self.clear_of_roads(fx, fy, 0.3)[0] or self.inside_building(fx, fy)[0]:
                    continue
                if self.clear_of_roads(fx, fy, 3.0)[0]:
                    continue  # this is the back of the plot, not the street side
                u = self.rng.uniform()
                length = bld.length * self.rng.uniform(0.6, 1.0)
                if u < w["hedge_probability"]:
                    objects.wall(b, self.rng, fx, fy, self._z0(ground, fx, fy), bld.yaw, length,
                                 self.rng.uniform(0.6, 1.2), self.rng.uniform(0.8, 2.2), C.VEGETATION)
                elif u < w["hedge_probability"] + w["fence_probability"]:
                    objects.wall(b, self.rng, fx, fy, self._z0(ground, fx, fy), bld.yaw, length,
                                 self.rng.uniform(0.04, 0.12), self.rng.uniform(0.9, 2.0), C.FENCE)

    def _street_furniture(self, b: PrimitiveBuilder, ground: GroundMap) -> None:
        w = self.world
        # Green gaps are often screened from the sidewalk by a hedge.
        for k, side, s0, s1 in self.green_gaps:
            if self.rng.uniform() >= w["hedge_probability"]:
                continue
            road = self.roads[k]
            sign = 1.0 if side == 1 else -1.0
            for a in np.arange(s0, s1 - 1.0, 6.0):  # short straight pieces follow curves
                piece = min(6.0, s1 - a)
                x, y = road.point(a + piece / 2, sign * (road.sidewalk_outer(side) + 0.7))
                x, y = float(x), float(y)
                if not self.clear_of_roads(x, y, 0.3)[0] or self.inside_building(x, y, 0.5)[0]:
                    continue
                objects.wall(b, self.rng, x, y, self._z0(ground, x, y), float(road.heading(a + piece / 2)), piece,
                             self.rng.uniform(0.7, 1.3), self.rng.uniform(1.0, 2.4), C.VEGETATION)
        for k, road in enumerate(self.roads):
            s_lo, s_hi = self.s_range[k]
            for side in (0, 1):
                sign = 1.0 if side == 1 else -1.0
                # Street lights and signs at the kerb edge of the sidewalk.
                for spacing, is_sign in ((w["pole_spacing_m"], False), (w["sign_spacing_m"], True)):
                    s = s_lo + self.rng.uniform(0.0, spacing)
                    while s < s_hi:
                        d = sign * (road.kerb_offset(side) + 0.35)
                        x, y = road.point(s, d)
                        x, y = float(x), float(y)
                        if self.clear_of_roads(x, y, 0.2, to="kerb")[0] and self.occupancy.free(x, y, 0.25):
                            yaw_in = float(road.heading(s)) - sign * 0.5 * np.pi
                            objects.pole(b, self.rng, x, y, self._z0(ground, x, y), yaw_in, is_sign)
                            self.occupancy.add(x, y, 0.25)
                        s += spacing * self.rng.uniform(0.7, 1.3)
                # Street trees: in the sidewalk's back half when wide, else just behind it.
                s = s_lo + self.rng.uniform(0.0, w["street_tree_spacing_m"])
                while s < s_hi:
                    if self.rng.uniform() < w["street_tree_probability"]:
                        sw = road.sidewalk_width[side]
                        off = road.sidewalk_outer(side) - 0.6 if sw >= 2.5 else road.sidewalk_outer(side) + self.rng.uniform(0.8, 2.5)
                        x, y = road.point(s, sign * off)
                        x, y = float(x), float(y)
                        if (self.clear_of_roads(x, y, 0.3, to="kerb")[0] and not self.inside_building(x, y, 0.5)[0]
                                and self.occupancy.free(x, y, 0.5)):
                            objects.tree(b, self.rng, x, y, self._z0(ground, x, y))
                            self.occupancy.add(x, y, 0.5)
                    s += w["street_tree_spacing_m"] * self.rng.uniform(0.7, 1.3)

    def _vehicle(self, b, ground, x, y, yaw, semantic=None) -> bool:
        """Try to place one vehicle (class drawn from the fleet mix unless given)."""
        w = self.world
        if semantic is None:
            u = self.rng.uniform()
            semantic = C.TRUCK if u < w["truck_fraction"] else (
                C.OTHER_VEHICLE if u < w["truck_fraction"] + w["other_vehicle_fraction"] else C.CAR)
        if semantic == C.CAR:
            dims = (self.rng.uniform(3.7, 4.9), self.rng.uniform(1.62, 1.9), self.rng.uniform(1.4, 1.75))
        elif semantic == C.TRUCK:
            dims = (self.rng.uniform(6.0, 9.5), self.rng.uniform(2.3, 2.5), self.rng.uniform(2.8, 3.6))
        else:
            dims = (self.rng.uniform(4.8, 6.5), self.rng.uniform(1.9, 2.1), self.rng.uniform(1.9, 2.6))
        discs = _vehicle_discs(x, y, yaw, dims[0], dims[1])
        if not all(self.occupancy.free(*d) for d in discs):
            return False
        for d in discs:
            self.occupancy.add(*d)
        inst = self.new_instance()
        box = objects.vehicle(b, self.rng, x, y, self._z0(ground, x, y), yaw, semantic, inst, *dims)
        self.boxes.append((box, semantic, inst))
        return True

    def _parked_vehicles(self, b: PrimitiveBuilder, ground: GroundMap) -> None:
        w = self.world
        for k, road in enumerate(self.roads):
            s_lo, s_hi = self.s_range[k]
            for side in (0, 1):
                sign = 1.0 if side == 1 else -1.0
                if road.parking_width[side] > 0:
                    d = sign * (road.half_width + road.parking_width[side] / 2)
                elif self.rng.uniform() < w["kerbside_parking_probability"]:
                    d = sign * (road.half_width - 1.1)
                else:
                    continue
                s = s_lo + self.rng.uniform(0.0, 6.0)
                while s < s_hi:
                    slot = self.rng.uniform(5.0, 7.5)
                    if self.rng.uniform() < w["parked_car_occupancy"]:
                        x, y = road.point(s, d + self.rng.uniform(-0.15, 0.15))
                        yaw = float(road.heading(s)) + (np.pi if side == 1 else 0.0) + self.rng.normal(0, 0.03)
                        self._vehicle(b, ground, float(x), float(y), yaw)
                    s += slot
        # Parking lots: rows of cars at (roughly) right angles to the road, random nose direction.
        for area in self.areas:
            if area.semantic != C.PARKING:
                continue
            road = self.roads[area.road]
            sign = 1.0 if area.side == 1 else -1.0
            for row_d in np.arange(area.d0 + 3.0, area.d1 - 2.0, 6.0):
                for s in np.arange(area.s0 + 1.5, area.s1 - 1.2, 2.7):
                    if self.rng.uniform() > w["parked_car_occupancy"]:
                        continue
                    x, y = road.point(s, sign * row_d)
                    yaw = float(road.heading(s)) + 0.5 * np.pi + (np.pi if self.rng.uniform() < 0.5 else 0.0)
                    yaw += self.rng.normal(0, 0.15)
                    self._vehicle(b, ground, float(x), float(y), yaw, semantic=C.CAR)

    def _moving_traffic(self, b: PrimitiveBuilder, ground: GroundMap) -> None:
        w = self.world
        for k, road in enumerate(self.roads):
            s_lo, s_hi = self.s_range[k]
            n = self.rng.poisson(w["moving_vehicles_per_100m"] * (s_hi - s_lo) / 100.0 * road.lanes / 2)
            for _ in range(n):
                lane = int(self.rng.integers(road.lanes))
                d = -road.half_width + (lane + 0.5) * road.lane_width + self.rng.uniform(-0.3, 0.3)
                s = self.rng.uniform(s_lo, s_hi)
                yaw = float(road.heading(s)) + (np.pi if d > 0 else 0.0) + self.rng.normal(0, 0.03)
                if self.rng.uniform() < 0.05:  # turning / manoeuvring
                    yaw += self.rng.uniform(-0.6, 0.6)
                x, y = road.point(s, d)
                self._vehicle(b, ground, float(x), float(y), yaw)

    def _people(self, b: PrimitiveBuilder, ground: GroundMap) -> None:
        w = self.world
        for k, road in enumerate(self.roads):
            s_lo, s_hi = self.s_range[k]
            length = s_hi - s_lo
            for _ in range(self.rng.poisson(w["pedestrians_per_100m"] * length / 100.0)):
                side = int(self.rng.integers(2))
                sign = 1.0 if side == 1 else -1.0
                s = self.rng.uniform(s_lo, s_hi)
                on_road = self.rng.uniform() < 0.1  # crossing the street
                d = self.rng.uniform(-road.half_width, road.half_width) if on_road else sign * (
                    road.kerb_offset(side) + self.rng.uniform(0.3, max(road.sidewalk_width[side] - 0.3, 0.4)))
                x, y = road.point(s, d)
                x, y = float(x), float(y)
                if self.inside_building(x, y, 0.3)[0] or not self.occupancy.free(x, y, 0.4):
                    continue
                self.occupancy.add(x, y, 0.4)
                inst = self.new_instance()
                box = objects.person(b, self.rng, x, y, self._z0(ground, x, y), self.rng.uniform(-np.pi, np.pi),
                                     C.PERSON, inst, self.rng.uniform(1.5, 1.95))
                self.boxes.append((box, C.PERSON, inst))
            for count_key, riding in (("bicyclists_per_100m", True), ("parked_bicycles_per_100m", False)):
                for _ in range(self.rng.poisson(w[count_key] * length / 100.0)):
                    side = int(self.rng.integers(2))
                    sign = 1.0 if side == 1 else -1.0
                    s = self.rng.uniform(s_lo, s_hi)
                    if riding:
                        d = sign * (road.half_width - 0.7)
                        yaw = float(road.heading(s)) + (np.pi if side == 1 else 0.0)
                    else:
                        d = sign * (road.sidewalk_outer(side) - 0.4)
                        yaw = float(road.heading(s)) + self.rng.normal(0, 0.2)
                    x, y = road.point(s, d)
                    x, y = float(x), float(y)
                    discs = _vehicle_discs(x, y, yaw, 1.8, 0.5)
                    if self.inside_building(x, y, 0.3)[0] or not all(self.occupancy.free(*dd) for dd in discs):
                        continue
                    for dd in discs:
                        self.occupancy.add(*dd)
                    inst = self.new_instance()
                    sem = C.BICYCLIST if riding else C.BICYCLE
                    box = objects.bicycle(b, self.rng, x, y, self._z0(ground, x, y), yaw, sem, inst,
                                          self.rng.uniform(1.6, 1.9) if riding else None)
                    self.boxes.append((box, sem, inst))

    def _vegetation(self, b: PrimitiveBuilder, ground: GroundMap) -> None:
        """Parks, gardens and verges: trees and bushes scattered on terrain cells."""
        w = self.world
        xmin, ymin, xmax, ymax = self.extent
        area_ha = (xmax - xmin) * (ymax - ymin) / 1e4
        n = self.rng.poisson((w["trees_per_hectare"] + w["bushes_per_hectare"]) * area_ha)
        xs = self.rng.uniform(xmin, xmax, n)
        ys = self.rng.uniform(ymin, ymax, n)
        is_tree = self.rng.uniform(size=n) < w["trees_per_hectare"] / max(w["trees_per_hectare"] + w["bushes_per_hectare"], 1e-9)
        i, j, inside = ground.cell(xs, ys)
        ok = inside & (ground.semantic[i, j] == C.TERRAIN) & self.clear_of_roads(xs, ys, 0.8)
        ok &= ~self.inside_building(xs, ys, 1.0)
        for x, y, tree in zip(xs[ok], ys[ok], is_tree[ok]):
            r = 0.5 if tree else 0.8
            if not self.occupancy.free(x, y, r):
                continue
            self.occupancy.add(x, y, r)
            z0 = self._z0(ground, x, y)
            if tree:
                objects.tree(b, self.rng, float(x), float(y), z0, scale=self.rng.uniform(0.9, 1.4))
            else:
                objects.bush(b, self.rng, float(x), float(y), z0)

    def reserve_corridor(self, road: Road, s0: float, s1: float, d: float, radius: float) -> None:
        """Keep a strip along the route free (the ego platform moves along it)."""
        for s in np.arange(s0, s1 + 1e-9, max(radius, 0.5)):
            x, y = road.point(s, d)
            self.occupancy.add(float(x), float(y), radius)
