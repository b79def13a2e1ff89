"""Road centre-lines: straight lines and circular arcs with a road frame.

Every road has a frame (s, d): ``s`` is the arc length along the centre-line and
``d`` the signed lateral offset, positive to the LEFT of the travel direction.
Both conversions are closed-form and vectorised, so the ground rasteriser and the
object placer share one exact geometry (no polyline approximation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Road:
    """One road: centre-line geometry plus its cross-section.

    kind: "line" or "arc". A line passes through ``origin`` with unit
    ``direction``. An arc has centre ``center``, radius ``radius`` and turns left
    (``turn`` = +1, centre on the left) or right (-1); s = 0 at angle ``phi0``.
    s_min: the road starts at this arc length (a T-junction's side road starts at
    the main road); -inf for roads that cross the whole scene.
    The cross-section is symmetric in the carriageway and per side (index 0 =
    right side d < 0, 1 = left side d > 0) for parking strips and sidewalks.
    """

    kind: str
    origin: tuple[float, float] = (0.0, 0.0)
    direction: tuple[float, float] = (1.0, 0.0)
    center: tuple[float, float] = (0.0, 0.0)
    radius: float = np.inf
    turn: int = 1
    phi0: float = 0.0
    s_min: float = -np.inf
    lanes: int = 2
    lane_width: float = 3.3
    parking_width: tuple[float, float] = (0.0, 0.0)
    sidewalk_width: tuple[float, float] = (2.0, 2.0)
    curb_height: float = 0.12

    @property
    def half_width(self) -> float:
        """Half the carriageway width (kerb to kerb, without parking strips)."""
        return 0.5 * self.lanes * self.lane_width

    def kerb_offset(self, side: int) -> float:
        """|d| of the kerb line on ``side`` (0 right, 1 left): carriageway + parking strip."""
        return self.half_width + self.parking_width[side]

    def sidewalk_outer(self, side: int) -> float:
        """|d| of the back edge of the sidewalk on ``side``."""
        return self.kerb_offset(side) + self.sidewalk_width[side]

    # -- frame conversions ---------------------------------------------------
    def to_frame(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y) -> (s, d). Points before ``s_min`` get |d| = their distance
        to the road's start point (so they are never 'on' the road)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if self.kind == "line":
            ux, uy = self.direction
            px, py = x - self.origin[0], y - self.origin[1]
            s = px * ux + py * uy
            d = -px * uy + py * ux
        else:
            px, py = x - self.center[0], y - self.center[1]
            rho = np.hypot(px, py)
            dphi = np.angle(np.exp(1j * (np.arctan2(py, px) - self.phi0)))
            s = self.turn * self.radius * dphi
            d = self.turn * (self.radius - rho)
        if np.isfinite(self.s_min):
            before = s < self.s_min
            if np.any(before):
                sx, sy = self.point(self.s_min, 0.0)
                far = np.hypot(x - sx, y - sy)
                d = np.where(before, np.copysign(np.maximum(far, np.abs(d)), d + 1e-12), d)
        return s, d

    def point(self, s, d) -> tuple[np.ndarray, np.ndarray]:
        """(s, d) -> world (x, y)."""
        s = np.asarray(s, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        if self.kind == "line":
            ux, uy = self.direction
            return self.origin[0] + s * ux - d * uy, self.origin[1] + s * uy + d * ux
        phi = self.phi0 + self.turn * s / self.radius
        rho = self.radius - self.turn * d
        return self.center[0] + rho * np.cos(phi), self.center[1] + rho * np.sin(phi)

    def heading(self, s) -> np.ndarray:
        """Travel direction (rad, world frame) at arc length ``s``."""
        s = np.asarray(s, dtype=np.float64)
        if self.kind == "line":
            return np.full(s.shape, np.arctan2(self.direction[1], self.direction[0]))
        return self.phi0 + self.turn * s / self.radius + self.turn * 0.5 * np.pi


def straight_road(origin, heading: float, **cross_section) -> Road:
    """A straight road through ``origin`` heading ``heading`` (rad)."""
    return Road("line", origin=(float(origin[0]), float(origin[1])),
                direction=(float(np.cos(heading)), float(np.sin(heading))), **cross_section)


def arc_road(radius: float, turn: int, **cross_section) -> Road:
    """A circular road through the world origin heading +x at s = 0, turning left
    (``turn`` = +1) or right (-1) with the given radius."""
    center = (0.0, turn * radius)
    phi0 = float(np.arctan2(-center[1], -center[0]))
    return Road("arc", center=center, radius=float(radius), turn=int(turn), phi0=phi0, **cross_section)
