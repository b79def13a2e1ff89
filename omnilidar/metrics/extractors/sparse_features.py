"""Sparse-voxel feature extractors for FSVD (MinkowskiNet) and FPVD (SPVCNN).

Protocol (LiDM's perceptual metrics as run by R2Flow ``evaluate.py``):

* the points are the range image's valid pixels (0.5 m < range < 63 m; the
  protocol drops the masked pixels, which sit at the origin);
* voxels of 0.05 m, one point per voxel, input features [x, y, z, -1]
  (coordinates in metres and a constant -1 in place of the remission);
* features: the network's penultimate layer (the classifier's input): voxel
  features for MinkowskiNet, point features for SPVCNN;
* aggregation: positions (voxel units) are centred on their mean, the
  distance |p - centroid| x 0.05 m is binned into 16 bins with edges
  0, 7.25, 10.5, ..., 56 m (``linspace(4, 56, 17)`` with the first edge set to
  0), the features of each bin are averaged (0 for an empty bin), and the 16
  means are concatenated bin-major: 16 C values.

The networks are this package's MinkUNet / SPVCNN
(``omnilidar.downstream.seg``); voxelisation takes the first point of a voxel
(``floor`` binning) where LiDM's takes ``round`` -- a half-voxel shift of the
grid that the distance bins (metres wide) do not notice.
"""

from __future__ import annotations

import numpy as np
import torch

from omnilidar.segnets.voxelize import VOXEL_SIZE, collate
from omnilidar.errors import InputError

NUM_BINS = 16
BIN_EDGES = np.concatenate([[0.0], np.linspace(4.0, 56.0, NUM_BINS + 1)[1:]])
KINDS = ("fsvd", "fpvd")


def scan_inputs(points: np.ndarray) -> np.ndarray:
    """(N, >=3) points -> (N, 4) float32 [x, y, z, -1] without points at the origin."""
    xyz = np.asarray(points, dtype=np.float32)[:, :3]
    xyz = xyz[np.einsum("ij,ij->i", xyz, xyz) > 0]
    return np.concatenate([xyz, np.full((len(xyz), 1), -1.0, np.float32)], axis=1)


def distance_bin_means(feats: torch.Tensor, positions: torch.Tensor, scan: torch.Tensor, num_scans: int,
                       voxel_size: float = VOXEL_SIZE) -> torch.Tensor:
    """Per scan, the mean feature in each distance bin from the scan's centroid.

    ``feats`` (M, C), ``positions`` (M, 3) in voxel units, ``scan`` (M,) scan
    index. Returns (num_scans, NUM_BINS * C) float64, bin-major; empty bins are 0.
    Rows beyond the last edge (56 m) count in no bin.
    """
    feats, pos = feats.double(), positions.double()
    count = torch.bincount(scan, minlength=num_scans).clamp_min(1).double()
    centroid = torch.zeros(num_scans, 3, dtype=torch.float64).index_add_(0, scan, pos) / count[:, None]
    dist = torch.linalg.vector_norm(pos - centroid[scan], dim=1) * voxel_size
    edges = torch.as_tensor(BIN_EDGES, dtype=torch.float64)
    b = torch.bucketize(dist, edges, right=True) - 1  # bin i holds edges[i] <= d < edges[i + 1]
    keep = (b >= 0) & (b < NUM_BINS)
    slot = scan[keep] * NUM_BINS + b[keep]
    c = feats.shape[1]
    sums = torch.zeros(num_scans * NUM_BINS, c, dtype=torch.float64).index_add_(0, slot, feats[keep])
    n = torch.bincount(slot, minlength=num_scans * NUM_BINS).double()
    means = torch.where(n[:, None] > 0, sums / n.clamp_min(1)[:, None], torch.zeros_like(sums))
    return means.reshape(num_scans, NUM_BINS * c)


class SparseExtractor:
    """FSVD (``kind="fsvd"``, a MinkUNet) or FPVD (``kind="fpvd"``, an SPVCNN) features."""

    def __init__(self, kind: str, model: torch.nn.Module, voxel_size: float = VOXEL_SIZE):
        if kind not in KINDS:
            raise InputError(None, f"unknown sparse metric {kind!r}")
        self.kind, self.model, self.voxel_size = kind, model.eval(), voxel_size
        self._captured: list[torch.Tensor] = []
        # The classifier's input is the penultimate feature of both networks.
        model.classifier.register_forward_hook(lambda mod, args, out: self._captured.append(args[0]))

    @torch.no_grad()
    def __call__(self, views: dict) -> np.ndarray:
        scans = [scan_inputs(p) for p in views["points"]]
        out = np.zeros((len(scans), 0))
        present = [i for i, s in enumerate(scans) if len(s)]
        if not present:
            raise InputError(None, f"{self.kind.upper()}: every scan of the batch is empty")
        batch = collate([scans[i] for i in present], voxel_size=self.voxel_size)
        self._captured.clear()
        self.model(batch)
        feats = self._captured.pop()
        if self.kind == "fsvd":  # one row per voxel
            pos = batch.voxel_coords[:, 1:].double() + 0.5
            scan = batch.voxel_coords[:, 0].long()
        else:  # one row per point
            pos = batch.point_coords[:, 1:].double()
            scan = batch.point_coords[:, 0].long()
        agg = distance_bin_means(feats, pos, scan, len(present), self.voxel_size).numpy()
        # An empty scan has no feature anywhere: all bins 0 (the protocol's nan_to_num).
        out = np.zeros((len(scans), agg.shape[1]))
        out[present] = agg
        return out
