"""Analytic scene primitives: yaw-oriented boxes, vertical cylinders, ellipsoids.

All scene geometry except the ground is a flat table of primitives (structure of
arrays) so that the ray caster can run over it without Python objects. Each
primitive is posed by a centre and a yaw about the world z axis; ``half`` holds
its half extents in its own frame (box: half sizes; cylinder: radius, radius,
half height; ellipsoid: the three semi-axes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BOX, CYLINDER, ELLIPSOID = 0, 1, 2


@dataclass(frozen=True)
class Primitives:
    """A table of P primitives (see module docstring)."""

    kind: np.ndarray  # (P,) int8
    center: np.ndarray  # (P, 3) float64, world frame
    half: np.ndarray  # (P, 3) float64
    yaw: np.ndarray  # (P,) float64
    semantic: np.ndarray  # (P,) uint16 raw SemanticKITTI id
    instance: np.ndarray  # (P,) uint16, 0 for stuff
    reflectivity: np.ndarray  # (P,) float32 in (0, 1]

    def __len__(self) -> int:
        return len(self.kind)

    def aabb_corners(self) -> np.ndarray:
        """(P, 8, 3) corners of each primitive's oriented bounding box."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        half = self.half.copy()
        cyl = self.kind == CYLINDER
        half[cyl, 1] = half[cyl, 0]  # a cylinder's radius is half[0]
        local = signs[None] * half[:, None, :]
        c, s = np.cos(self.yaw)[:, None], np.sin(self.yaw)[:, None]
        x = c * local[..., 0] - s * local[..., 1]
        y = s * local[..., 0] + c * local[..., 1]
        return np.stack([x, y, local[..., 2]], axis=-1) + self.center[:, None, :]


class PrimitiveBuilder:
    """Accumulates primitives while a scene is laid out, then freezes them."""

    def __init__(self) -> None:
        self._rows: list[tuple] = []

    def add(self, kind: int, center, half, yaw: float, semantic: int, instance: int, reflectivity: float) -> None:
        half = (float(half[0]), float(half[0] if kind == CYLINDER else half[1]), float(half[2]))
        if min(half) <= 0.0:
            raise ValueError(f"primitive half extents must be positive, got {half}")
        self._rows.append((kind, float(center[0]), float(center[1]), float(center[2]), *half, float(yaw),
                           int(semantic), int(instance), float(reflectivity)))

    def __len__(self) -> int:
        return len(self._rows)

    def build(self) -> Primitives:
        if not self._rows:
            z = np.zeros((0, 3))
            return Primitives(np.zeros(0, np.int8), z, z.copy(), np.zeros(0), np.zeros(0, np.uint16),
                              np.zeros(0, np.uint16), np.zeros(0, np.float32))
        a = np.array(self._rows, dtype=np.float64)
        return Primitives(
            kind=a[:, 0].astype(np.int8),
            center=np.ascontiguousarray(a[:, 1:4]),
            half=np.ascontiguousarray(a[:, 4:7]),
            yaw=np.ascontiguousarray(a[:, 7]),
            semantic=a[:, 8].astype(np.uint16),
            instance=a[:, 9].astype(np.uint16),
            reflectivity=a[:, 10].astype(np.float32),
        )
