"""Procedural street scenes: roads, ground, buildings, vegetation and road users.

A scene is generated from a seeded ``np.random.Generator`` and the ``world``
settings; it is sized around a ROUTE (a stretch of the main road) along which a
platform records a sequence, so consecutive scans of a sequence see the same,
correlated world. Everything is in a world frame with z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnilidar.data.synthetic.ground import GroundMap, build_ground
from omnilidar.data.synthetic.layout import Layout
from omnilidar.data.synthetic.primitives import PrimitiveBuilder, Primitives
from omnilidar.data.synthetic.roads import Road, arc_road, straight_road

LAYOUTS = ("straight", "curve", "intersection", "t_junction")


@dataclass(frozen=True)
class Route:
    """Where the ego platform travels: arc lengths on road ``road`` and lateral
    offsets of the vehicle lane (rightmost lane), the quadruped's walking line
    (middle of the right sidewalk) and the drone's line (road centre)."""

    road: int
    s_start: float
    s_end: float
    lane_d: float
    walk_d: float
    centre_d: float = 0.0


@dataclass(frozen=True)
class Scene:
    """A generated world: roads, ground rasters, primitives and object boxes."""

    layout: str
    roads: tuple[Road, ...]
    ground: GroundMap
    prims: Primitives
    boxes: np.ndarray  # (M, 7) world-frame boxes of things
    box_semantic: np.ndarray  # (M,) uint16
    box_instance: np.ndarray  # (M,) uint16
    route: Route

    def route_pose(self, s: float, d: float) -> tuple[float, float, float]:
        """(x, y, heading) on the route road at arc length s, lateral offset d."""
        road = self.roads[self.route.road]
        x, y = road.point(s, d)
        return float(x), float(y), float(road.heading(s))


def _cross_section(world: dict, rng: np.random.Generator) -> dict:
    lanes = int(rng.integers(world["lanes"][0], world["lanes"][1] + 1))
    park = [world["parking_strip_width_m"] if rng.uniform() < world["parking_strip_probability"] else 0.0
            for _ in range(2)]
    return dict(
        lanes=lanes,
        lane_width=float(rng.uniform(*world["lane_width_m"])),
        parking_width=(float(park[0]), float(park[1])),
        sidewalk_width=tuple(float(v) for v in rng.uniform(*world["sidewalk_width_m"], size=2)),
        curb_height=float(rng.uniform(*world["curb_height_m"])),
    )


def generate_scene(rng: np.random.Generator, world: dict, route_length_m: float) -> Scene:
    """A street scene around a route of ``route_length_m`` metres on its main road.

    ``world`` is the ``world`` block of the validated ``synthetic`` settings. The
    route starts at s = -L/2 and ends at +L/2 of road 0; the scene extends
    ``margin_m`` beyond it in every direction.
    """
    weights = np.array([world["layout_weights"][k] for k in LAYOUTS], dtype=np.float64)
    if weights.sum() <= 0:
        raise ValueError("synthetic.world.layout_weights must not all be zero")
    layout = LAYOUTS[int(rng.choice(len(LAYOUTS), p=weights / weights.sum()))]
    half = 0.5 * float(route_length_m)

    main_xs = _cross_section(world, rng)
    if layout == "curve":
        radius = float(rng.uniform(*world["curve_radius_m"]))
        main = arc_road(radius, int(rng.choice([-1, 1])), **main_xs)
    else:
        main = straight_road((0.0, 0.0), 0.0, **main_xs)
    roads = [main]
    if layout in ("intersection", "t_junction"):
        s_x = float(rng.uniform(-half - 10.0, half + 10.0))
        px, py = main.point(s_x, 0.0)
        angle = float(main.heading(s_x)) + float(rng.choice([-1, 1])) * float(rng.uniform(np.deg2rad(70), np.deg2rad(110)))
        cross_xs = _cross_section(world, rng)
        s_min = 0.0 if layout == "t_junction" else -np.inf
        roads.append(Road("line", origin=(float(px), float(py)), direction=(float(np.cos(angle)), float(np.sin(angle))),
                          s_min=s_min, **cross_xs))

    # Scene rectangle: route +- margin.
    s_samples = np.linspace(-half, half, max(int(route_length_m) + 2, 2))
    rx, ry = main.point(s_samples, np.zeros_like(s_samples))
    margin = float(world["margin_m"])
    extent = (float(rx.min() - margin), float(ry.min() - margin), float(rx.max() + margin), float(ry.max() + margin))

    lay = Layout(roads, extent, world, rng)
    route = Route(road=0, s_start=-half, s_end=half,
                  lane_d=-main.half_width + 0.5 * main.lane_width,
                  walk_d=-(main.kerb_offset(0) + 0.5 * main.sidewalk_width[0]))
    # Corridors kept free: the vehicle's lane and the quadruped's walking line.
    lay.reserve_corridor(main, route.s_start - 8.0, route.s_end + 8.0, route.lane_d, 2.2)
    lay.reserve_corridor(main, route.s_start - 3.0, route.s_end + 3.0, route.walk_d, 0.45)
    lay.plan_frontages()
    ground = build_ground(roads, lay.areas, extent, world, rng)
    builder = PrimitiveBuilder()
    lay.populate(builder, ground)

    if lay.boxes:
        boxes = np.array([b for b, _, _ in lay.boxes], dtype=np.float64)
        sem = np.array([s for _, s, _ in lay.boxes], dtype=np.uint16)
        inst = np.array([i for _, _, i in lay.boxes], dtype=np.uint16)
    else:
        boxes, sem, inst = np.zeros((0, 7)), np.zeros(0, np.uint16), np.zeros(0, np.uint16)
    return Scene(layout=layout, roads=tuple(roads), ground=ground, prims=builder.build(), boxes=boxes,
                 box_semantic=sem, box_instance=inst, route=route)


__all__ = ["Scene", "Route", "generate_scene", "LAYOUTS"]
