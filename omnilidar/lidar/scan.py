"""In-memory scan: points with their labels, instance ids, rings and boxes.

Every stage passes ``Scan`` objects around; readers build them, effects return
new ones (never mutate), writers store them in the datasets' own formats.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np


@dataclass(frozen=True)
class Boxes:
    """3D boxes in the lidar frame: x, y, z_center, dx, dy, dz, heading (rad)."""

    boxes: np.ndarray  # (M, 7) float32
    names: np.ndarray  # (M,) str, e.g. "Car", "Pedestrian"
    instance: np.ndarray | None = None  # (M,) uint16: instance id of the box's points, if known

    def __post_init__(self):
        b = np.asarray(self.boxes, dtype=np.float32).reshape(-1, 7)
        object.__setattr__(self, "boxes", b)
        object.__setattr__(self, "names", np.asarray(self.names, dtype=str).reshape(-1))
        if len(self.names) != len(b):
            raise ValueError(f"{len(b)} boxes but {len(self.names)} names")
        if self.instance is not None:
            inst = np.asarray(self.instance, dtype=np.uint16).reshape(-1)
            if len(inst) != len(b):
                raise ValueError(f"{len(b)} boxes but {len(inst)} instance ids")
            object.__setattr__(self, "instance", inst)

    def __len__(self) -> int:
        return len(self.boxes)

    @classmethod
    def empty(cls) -> "Boxes":
        return cls(np.zeros((0, 7), np.float32), np.zeros((0,), str))

    def select(self, keep: np.ndarray) -> "Boxes":
        inst = None if self.instance is None else self.instance[keep]
        return Boxes(self.boxes[keep], self.names[keep], inst)


@dataclass(frozen=True)
class Scan:
    """One LiDAR sweep.

    points: (N, 4) float32 x, y, z (metres, sensor frame) and intensity in the
        sensor's native scale (``intensity_scale``: 1.0 for KITTI 0..1, 255.0 for
        nuScenes 0..255).
    semantic: (N,) uint16 raw SemanticKITTI ids (label & 0xFFFF), or None.
    instance: (N,) uint16 instance ids (label >> 16), or None.
    ring: (N,) int16 beam index, 0 = the top (highest elevation) beam, or None.
    boxes: lidar-frame boxes, possibly empty.
    """

    points: np.ndarray
    semantic: np.ndarray | None = None
    instance: np.ndarray | None = None
    ring: np.ndarray | None = None
    boxes: Boxes = field(default_factory=Boxes.empty)
    intensity_scale: float = 1.0

    def __post_init__(self):
        pts = np.asarray(self.points, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 4:
            raise ValueError(f"points must be (N, 4), got {pts.shape}")
        object.__setattr__(self, "points", pts)
        n = len(pts)
        for name, dtype in (("semantic", np.uint16), ("instance", np.uint16), ("ring", np.int16)):
            value = getattr(self, name)
            if value is None:
                continue
            value = np.asarray(value, dtype=dtype).reshape(-1)
            if len(value) != n:
                raise ValueError(f"{name} has {len(value)} entries for {n} points")
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def xyz(self) -> np.ndarray:
        return self.points[:, :3]

    @property
    def intensity(self) -> np.ndarray:
        return self.points[:, 3]

    @property
    def label(self) -> np.ndarray | None:
        """Packed SemanticKITTI label: semantic | instance << 16 (uint32)."""
        if self.semantic is None:
            return None
        inst = np.zeros(len(self), np.uint32) if self.instance is None else self.instance.astype(np.uint32)
        return self.semantic.astype(np.uint32) | (inst << 16)

    def select(self, keep: np.ndarray) -> "Scan":
        """A new scan with the points selected by a boolean mask or index array
        (labels, instances and rings follow their points; boxes are kept)."""
        pick = lambda a: None if a is None else a[keep]  # noqa: E731
        return replace(
            self,
            points=self.points[keep],
            semantic=pick(self.semantic),
            instance=pick(self.instance),
            ring=pick(self.ring),
        )

    def with_points(self, points: np.ndarray) -> "Scan":
        """Same labels and rings, new point values (same N)."""
        return replace(self, points=points)
