"""PointNet feature extractor for FPD (Frechet point-cloud distance).

Architecture (PointNet classification network, Qi et al. 2017; the layout of the
ShapeNet classifier whose weights the protocol uses, ``cls_model_39.pth``):

* ``feat.stn``: input transform: shared MLP 3-64-128-1024 (1x1 conv-BN-ReLU),
  max over points, FC 1024-512-256-9 (BN-ReLU on the first two), plus identity;
* ``feat``: points times the 3x3 transform, shared MLP 3-64-128-1024 (BN, ReLU
  except after the last), max over points -> global feature (1024);
* classifier: FC 1024-512-256-k (BN-ReLU on the first two).

FPD features are the concatenation [global 1024, fc1 512, fc2 256, logits k]:
1808-d for the ShapeNet classifier (k = 16). The protocol feeds every pixel of
the range image as a point (masked pixels at the origin), scaled by 1/80
(KITTI's maximum range), with no other normalisation.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from omnilidar.errors import InputError

POINT_SCALE = 1.0 / 80.0
SHAPENET_CLASSES = 16


class STN3d(nn.Module):
    def __init__(self):
        super().__init__()
        self.conv1, self.conv2, self.conv3 = nn.Conv1d(3, 64, 1), nn.Conv1d(64, 128, 1), nn.Conv1d(128, 1024, 1)
        self.fc1, self.fc2, self.fc3 = nn.Linear(1024, 512), nn.Linear(512, 256), nn.Linear(256, 9)
        self.bn1, self.bn2, self.bn3 = nn.BatchNorm1d(64), nn.BatchNorm1d(128), nn.BatchNorm1d(1024)
        self.bn4, self.bn5 = nn.BatchNorm1d(512), nn.BatchNorm1d(256)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.bn1(self.conv1(x)))
        x = F.relu(self.bn2(self.conv2(x)))
        x = F.relu(self.bn3(self.conv3(x))).amax(dim=2)
        x = F.relu(self.bn4(self.fc1(x)))
        x = F.relu(self.bn5(self.fc2(x)))
        return self.fc3(x).view(-1, 3, 3) + torch.eye(3, dtype=x.dtype, device=x.device)


class PointNetFeat(nn.Module):
    def __init__(self):
        super().__init__()
        self.stn = STN3d()
        self.conv1, self.conv2, self.conv3 = nn.Conv1d(3, 64, 1), nn.Conv1d(64, 128, 1), nn.Conv1d(128, 1024, 1)
        self.bn1, self.bn2, self.bn3 = nn.BatchNorm1d(64), nn.BatchNorm1d(128), nn.BatchNorm1d(1024)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = torch.bmm(x.transpose(2, 1), self.stn(x)).transpose(2, 1)
        x = F.relu(self.bn1(self.conv1(x)))
        x = F.relu(self.bn2(self.conv2(x)))
        return self.bn3(self.conv3(x)).amax(dim=2)


class PointNet(nn.Module):
    """PointNet classifier over (B, 3, N) points; ``features`` is the FPD vector."""

    def __init__(self, num_classes: int = SHAPENET_CLASSES):
        super().__init__()
        self.num_classes = num_classes
        self.feat = PointNetFeat()
        self.fc1, self.fc2, self.fc3 = nn.Linear(1024, 512), nn.Linear(512, 256), nn.Linear(256, num_classes)
        self.bn1, self.bn2 = nn.BatchNorm1d(512), nn.BatchNorm1d(256)

    @property
    def feature_dim(self) -> int:
        return 1024 + 512 + 256 + self.num_classes

    def features(self, x: torch.Tensor) -> torch.Tensor:
        g = self.feat(x)
        h1 = F.relu(self.bn1(self.fc1(g)))
        h2 = F.relu(self.bn2(self.fc2(h1)))
        return torch.cat([g, h1, h2, self.fc3(h2)], dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)[:, -self.num_classes:]


def pixel_points(xyz: np.ndarray) -> np.ndarray:
    """(B, 3, H, W) per-pixel coordinates (0 where masked) -> (B, 3, H*W) scaled by 1/80."""
    if xyz.ndim != 4 or xyz.shape[1] != 3:
        raise InputError(None, f"expected (B, 3, H, W) coordinates, got {xyz.shape}")
    return (xyz.reshape(len(xyz), 3, -1) * POINT_SCALE).astype(np.float32)


class PointNetExtractor:
    """FPD features (B, 1024 + 512 + 256 + k) of every pixel of the protocol views."""

    kind = "fpd"

    def __init__(self, model: PointNet):
        self.model = model.eval()

    @torch.no_grad()
    def __call__(self, views: dict) -> np.ndarray:
        pts = torch.from_numpy(pixel_points(views["xyz_masked"]))
        return self.model.features(pts).double().numpy()
