"""Voxelisation for the segmentation backbones, and batching of voxelised scans.

Each voxel (0.05 m by default) takes the features of its FIRST point in file
order (mmdet3d's MinkUNet convention). Every point keeps the index of its voxel
so that voxel predictions map back to every point. During training the number
of voxels may be capped (80k in the reference schedule); the voxels kept are an
azimuth crop around a direction drawn from an explicit generator, and points of
dropped voxels are marked -1.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from omnilidar.errors import InputError
from omnilidar.sparse.tensor import SparseTensor

VOXEL_SIZE = 0.05  # metres
IGNORE_INDEX = -1  # target value of points/voxels without a trainable label


@dataclass(frozen=True)
class Voxelization:
    """Voxels of one scan.

    coords: ``(M, 3)`` int32 voxel indices, all >= 0, sorted (x, y, z).
    first_point: ``(M,)`` int64 index of each voxel's first point.
    point_to_voxel: ``(N,)`` int64 voxel of every point, -1 if its voxel was dropped.
    origin: ``(3,)`` float64 metric position of the corner of voxel (0, 0, 0).
    voxel_size: edge length in metres.
    """

    coords: np.ndarray
    first_point: np.ndarray
    point_to_voxel: np.ndarray
    origin: np.ndarray
    voxel_size: float

    @property
    def num_voxels(self) -> int:
        return len(self.coords)

    def point_positions(self, xyz: np.ndarray, point_ids: np.ndarray) -> np.ndarray:
        """Continuous positions (voxel units, float32) of the points ``point_ids``
        (rows of ``xyz``, all in kept voxels) whose floor is exactly their voxel index.

        The fraction inside the voxel is clipped to [0, 0.99] so that float32
        rounding can never move a point into the neighbouring voxel.
        """
        pos = (np.asarray(xyz, np.float64)[point_ids, :3] - self.origin) / self.voxel_size
        cell = self.coords[self.point_to_voxel[point_ids]].astype(np.float64)
        return (cell + np.clip(pos - cell, 0.0, 0.99)).astype(np.float32)


def _check_points(points: np.ndarray, path) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise InputError(path, f"points must be an (N, >=3) array, got shape {points.shape}")
    if len(points) == 0:
        raise InputError(path, "scan has no points to voxelise")
    if not np.isfinite(points).all():
        raise InputError(path, "points contain NaN or infinite values")
    return points


def voxelize(
    points: np.ndarray,
    voxel_size: float = VOXEL_SIZE,
    max_voxels: int | None = None,
    rng: np.random.Generator | None = None,
    path: str | Path | None = None,
) -> Voxelization:
    """First-point-per-voxel voxelisation of one scan.

    ``points``: ``(N, >=3)`` with x, y, z first, in the sensor's frame. ``max_voxels``
    caps the voxel count with a random azimuth crop (needs ``rng``): the voxels
    nearest in azimuth to a random direction are kept, so the crop keeps the scan's
    density and neighbourhoods (thinning a random subset would teach a sparser sensor
    than the one evaluated). ``path`` names the scan in error messages.
    """
    points = _check_points(points, path)
    if not voxel_size > 0:
        raise InputError(path, f"voxel size must be positive, got {voxel_size}")
    xyz = points[:, :3].astype(np.float64)
    origin = np.floor(xyz.min(0) / voxel_size) * voxel_size
    grid = np.floor((xyz - origin) / voxel_size).astype(np.int64)
    grid = np.maximum(grid, 0)  # guards a -1 from rounding at the minimum
    if grid.max() >= 2**20:
        raise InputError(path, f"scan extent {np.ptp(xyz, 0).max():.1f} m too large for {voxel_size} m voxels")
    keys = (grid[:, 0] << 40) | (grid[:, 1] << 20) | grid[:, 2]
    uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    coords = grid[first].astype(np.int32)
    if max_voxels is not None and len(uniq) > max_voxels:
        if rng is None:
            raise ValueError("max_voxels needs an explicit np.random.Generator")
        keep = azimuth_crop(xyz[first, :2], int(max_voxels), rng)
        remap = np.full(len(uniq), -1, np.int64)
        remap[keep] = np.arange(len(keep))
        inverse = remap[inverse]
        coords, first = coords[keep], first[keep]
    return Voxelization(coords, first.astype(np.int64), inverse.astype(np.int64), origin, float(voxel_size))


def azimuth_crop(xy: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of the ``count`` rows of ``xy`` nearest in azimuth to a random direction."""
    centre = rng.uniform(-np.pi, np.pi)
    offset = np.arctan2(xy[:, 1], xy[:, 0]) - centre
    distance = np.abs(np.arctan2(np.sin(offset), np.cos(offset)))  # wrapped to [0, pi]
    return np.sort(np.argsort(distance, kind="stable")[:count])


def voxel_labels(point_labels: np.ndarray, vox: Voxelization, num_classes: int) -> np.ndarray:
    """Majority label of each voxel's points, ignoring label 0 (ignore).

    A voxel whose points are all 0 gets 0. Ties go to the smaller class id.
    """
    point_labels = np.asarray(point_labels).astype(np.int64)
    if len(point_labels) != len(vox.point_to_voxel):
        raise InputError(None, f"{len(point_labels)} labels for {len(vox.point_to_voxel)} points")
    ok = (vox.point_to_voxel >= 0) & (point_labels > 0)
    counts = np.bincount(
        vox.point_to_voxel[ok] * num_classes + point_labels[ok], minlength=vox.num_voxels * num_classes
    ).reshape(vox.num_voxels, num_classes)
    return counts.argmax(1).astype(np.int64)  # all-zero rows give 0


@dataclass
class SegBatch:
    """A batch of voxelised scans, as the backbones consume it.

    Voxel rows and point rows are grouped by scan in batch order. Points of
    dropped voxels (training caps) are not in the batch; ``point_index`` gives
    each row's index within its own scan.
    """

    voxel_coords: torch.Tensor  # (M, 4) int32 batch, x, y, z
    voxel_feats: torch.Tensor  # (M, C) float32
    spatial_shape: tuple[int, int, int]
    batch_size: int
    point_coords: torch.Tensor  # (P, 4) float32 batch, then position in voxel units
    point_feats: torch.Tensor  # (P, C) float32
    point_to_voxel: torch.Tensor  # (P,) int64 row in the voxel arrays
    point_index: torch.Tensor  # (P,) int64 index within the point's scan
    points_per_scan: tuple[int, ...]
    voxel_targets: torch.Tensor | None = None  # (M,) int64 class 0..K-1 or IGNORE_INDEX
    point_targets: torch.Tensor | None = None  # (P,) int64 class 0..K-1 or IGNORE_INDEX

    def sparse_input(self) -> SparseTensor:
        """The voxel features as a fresh :class:`SparseTensor` (own kernel-map cache)."""
        return SparseTensor(self.voxel_feats, self.voxel_coords, self.spatial_shape, self.batch_size, {})

    def to(self, device) -> "SegBatch":
        move = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in self.__dict__.items()}
        return SegBatch(**move)

    def split_points(self, values: torch.Tensor) -> list[torch.Tensor]:
        """Split per-point rows (e.g. logits or predictions) by scan."""
        return list(torch.split(values, list(self.points_per_scan)))


def _targets(train_ids: np.ndarray) -> np.ndarray:
    """Train ids 0..19 (0 = ignore) -> class indices 0..18, ignore -> IGNORE_INDEX."""
    return np.asarray(train_ids, np.int64) - 1


def collate(
    scans: list[np.ndarray],
    labels: list[np.ndarray] | None = None,
    num_classes: int = 20,
    voxel_size: float = VOXEL_SIZE,
    max_voxels: int | None = None,
    rng: np.random.Generator | None = None,
    paths: list | None = None,
) -> SegBatch:
    """Voxelise and batch scans.

    ``scans``: list of ``(N_i, C)`` point arrays (x, y, z, intensity...), whose
    columns become the features. ``labels``: optional per-point TRAIN ids
    (0 = ignore, 1..19, see :func:`omnilidar.io.semantickitti.to_train_ids`);
    targets are ``train_id - 1`` with ignore as ``IGNORE_INDEX``, and
    ``num_classes`` counts the ignore id too (20 for SemanticKITTI).
    """
    if not scans:
        raise ValueError("collate needs at least one scan")
    paths = paths or [None] * len(scans)
    vcoords, vfeats, pcoords, pfeats, p2v, pidx, counts, vt, pt = [], [], [], [], [], [], [], [], []
    offset = 0
    for b, points in enumerate(scans):
        points = _check_points(points, paths[b]).astype(np.float32, copy=False)
        vox = voxelize(points, voxel_size, max_voxels, rng, paths[b])
        kept = np.flatnonzero(vox.point_to_voxel >= 0)
        vcoords.append(np.concatenate([np.full((vox.num_voxels, 1), b, np.int32), vox.coords], 1))
        vfeats.append(points[vox.first_point])
        pos = vox.point_positions(points, kept)
        pcoords.append(np.concatenate([np.full((len(kept), 1), b, np.float32), pos], 1))
        pfeats.append(points[kept])
        p2v.append(vox.point_to_voxel[kept] + offset)
        pidx.append(kept)
        counts.append(len(kept))
        offset += vox.num_voxels
        if labels is not None:
            lab = np.asarray(labels[b])
            if len(lab) != len(points):
                raise InputError(paths[b], f"has {len(lab)} labels but {len(points)} points")
            if lab.size and (lab.min() < 0 or lab.max() >= num_classes):
                raise InputError(paths[b], f"train ids must lie in 0..{num_classes - 1}")
            vt.append(_targets(voxel_labels(lab, vox, num_classes)))
            pt.append(_targets(lab[kept]))
    coords = np.concatenate(vcoords)
    shape = tuple(int(s) + 1 for s in coords[:, 1:].max(0))
    return SegBatch(
        voxel_coords=torch.from_numpy(coords),
        voxel_feats=torch.from_numpy(np.concatenate(vfeats)),
        spatial_shape=shape,
        batch_size=len(scans),
        point_coords=torch.from_numpy(np.concatenate(pcoords)),
        point_feats=torch.from_numpy(np.concatenate(pfeats)),
        point_to_voxel=torch.from_numpy(np.concatenate(p2v)),
        point_index=torch.from_numpy(np.concatenate(pidx)),
        points_per_scan=tuple(counts),
        voxel_targets=torch.from_numpy(np.concatenate(vt)) if labels is not None else None,
        point_targets=torch.from_numpy(np.concatenate(pt)) if labels is not None else None,
    )
