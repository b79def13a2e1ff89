"""RangeNet++ (DarkNet-53 / DarkNet-21) feature extractors for FRD and FRID.

Architecture (RangeNet++, Milioto et al. 2019; lidar-bonnetal layout):

* stem: 3x3 conv (C) - BN - LeakyReLU(0.1);
* five encoder stages, each a 3x3 conv with stride (1, 2) (width halves, height
  stays) to twice the channels, then ``blocks[i]`` residual blocks
  (1x1 conv to the stage's input width, 3x3 conv back, each conv-BN-LeakyReLU,
  plus identity); DarkNet-53 has blocks (1, 2, 8, 8, 4), DarkNet-21 (1, 1, 2, 2, 1);
* five decoder stages, each a (1, 4) transposed conv with stride (1, 2) (with
  bias) - BN - LeakyReLU and one residual block, whose output is added to the
  encoder feature of the same resolution;
* head: Dropout2d then a 3x3 conv to the classes.

Module names mirror the official files (``backbone``: ``conv1``, ``bn1``,
``encN.{conv,bn,residual_K.{conv1,bn1,conv2,bn2}}``; ``decoder``:
``decN.{upconv,bn,residual.{...}}``; ``head``: ``1``), so the official weights
load by prefixing each file's keys (see ``weights.py``).

Protocol (R2Flow ``evaluate.py``, after LiDARGen):

* input image [range, x, y, z, reflectance] (FRD, 5 channels) or
  [range, x, y, z] (FRID, DarkNet-21 without remission), pixels outside
  0.5 m < range < 63 m set to 0, then normalised by the sensor mean/std and
  multiplied by the mask (range > 0);
* features: the decoder output (C x H x W, C = 32 officially), i.e. the input
  of the head;
* FRD: the flattened (C, H, W) map at 4096 fixed indices, drawn as
  ``random.Random(0).sample(range(C*H*W), 4096)`` (what ``random.seed(0);
  random.sample(...)`` draws, without touching the global RNG);
* FRID: the map averaged over 16 horizontal bands of H/16 rows (and all
  columns), flattened channel-major: 16 C values (512 for C = 32).
"""

from __future__ import annotations

import random
from collections import OrderedDict

import numpy as np
import torch
from torch import nn

from omnilidar.errors import InputError

# Official sensor statistics (range, x, y, z, remission) of the SemanticKITTI models.
SENSOR_MEAN = (12.12, 10.88, 0.23, -1.04, 0.21)
SENSOR_STD = (12.32, 11.47, 6.91, 0.86, 0.16)
# LiDARGen / R2Flow masking of range-image pixels before feature extraction.
MIN_DEPTH = 0.5
MAX_DEPTH = 63.0
FRD_DIM = 4096
FRID_BANDS = 16
BLOCKS = {53: (1, 2, 8, 8, 4), 21: (1, 1, 2, 2, 1)}
BN_MOMENTUM = 0.01


def _cbl(cin: int, cout: int, kernel, stride, padding) -> list[tuple[str, nn.Module]]:
    return [
        ("conv", nn.Conv2d(cin, cout, kernel, stride, padding, bias=False)),
        ("bn", nn.BatchNorm2d(cout, momentum=BN_MOMENTUM)),
        ("relu", nn.LeakyReLU(0.1)),
    ]


class ResidualBlock(nn.Module):
    """x + CBL3x3(CBL1x1(x)): 1x1 conv to ``mid`` channels, 3x3 back to ``ch``."""

    def __init__(self, ch: int, mid: int):
        super().__init__()
        self.conv1 = nn.Conv2d(ch, mid, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(mid, momentum=BN_MOMENTUM)
        self.relu1 = nn.LeakyReLU(0.1)
        self.conv2 = nn.Conv2d(mid, ch, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(ch, momentum=BN_MOMENTUM)
        self.relu2 = nn.LeakyReLU(0.1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.relu1(self.bn1(self.conv1(x)))
        return x + self.relu2(self.bn2(self.conv2(h)))


def _encoder_stage(cin: int, cout: int, blocks: int) -> nn.Sequential:
    layers = _cbl(cin, cout, 3, (1, 2), 1)
    layers += [(f"residual_{i}", ResidualBlock(cout, cin)) for i in range(blocks)]
    return nn.Sequential(OrderedDict(layers))


def _decoder_stage(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(OrderedDict([
        ("upconv", nn.ConvTranspose2d(cin, cout, (1, 4), (1, 2), (0, 1))),
        ("bn", nn.BatchNorm2d(cout, momentum=BN_MOMENTUM)),
        ("relu", nn.LeakyReLU(0.1)),
        ("residual", ResidualBlock(cout, cin)),
    ]))


class Backbone(nn.Module):
    def __init__(self, in_channels: int, depth: int, width: int):
        super().__init__()
        ch = [width << i for i in range(6)]
        self.conv1 = nn.Conv2d(in_channels, width, 3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(width, momentum=BN_MOMENTUM)
        self.relu1 = nn.LeakyReLU(0.1)
        for i, blocks in enumerate(BLOCKS[depth]):
            setattr(self, f"enc{i + 1}", _encoder_stage(ch[i], ch[i + 1], blocks))

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        skips = [self.relu1(self.bn1(self.conv1(x)))]
        for i in range(5):
            skips.append(getattr(self, f"enc{i + 1}")(skips[-1]))
        return skips


class Decoder(nn.Module):
    def __init__(self, width: int):
        super().__init__()
        ch = [width << i for i in range(6)]
        for i in range(5, 0, -1):
            setattr(self, f"dec{i}", _decoder_stage(ch[i], ch[i - 1]))

    def forward(self, skips: list[torch.Tensor]) -> torch.Tensor:
        h = skips[5]
        for i in range(5, 0, -1):
            h = getattr(self, f"dec{i}")(h) + skips[i - 1]
        return h


class RangeNet(nn.Module):
    """RangeNet++ segmentation network; ``features`` gives the decoder output."""

    def __init__(self, in_channels: int = 5, num_classes: int = 20, depth: int = 53, width: int = 32,
                 dropout: float = 0.05):
        super().__init__()
        if depth not in BLOCKS:
            raise InputError(None, f"RangeNet depth must be one of {sorted(BLOCKS)}, got {depth}")
        self.in_channels, self.num_classes, self.depth, self.width = in_channels, num_classes, depth, width
        self.backbone = Backbone(in_channels, depth, width)
        self.decoder = Decoder(width)
        self.head = nn.Sequential(nn.Dropout2d(dropout), nn.Conv2d(width, num_classes, 3, padding=1))

    def features(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] % 32:
            raise InputError(None, f"RangeNet needs an image width divisible by 32, got {x.shape[-1]}")
        return self.decoder(self.backbone(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


def protocol_image(depth: np.ndarray, xyz: np.ndarray, reflectance: np.ndarray, with_remission: bool) -> np.ndarray:
    """The protocol's input (B, 5 or 4, H, W) float32 from depth (B, H, W) in metres,
    xyz (B, 3, H, W) and reflectance (B, H, W) in [0, 1]: pixels outside
    (MIN_DEPTH, MAX_DEPTH) are zeroed in every channel."""
    mask = ((depth > MIN_DEPTH) & (depth < MAX_DEPTH)).astype(np.float32)
    chans = [depth[:, None], xyz] + ([reflectance[:, None]] if with_remission else [])
    return (np.concatenate(chans, axis=1) * mask[:, None]).astype(np.float32)


def normalise(img: torch.Tensor, mean, std) -> torch.Tensor:
    """(img - mean) / std per channel, then zero where the range channel is 0."""
    c = img.shape[1]
    m = torch.as_tensor(mean[:c], dtype=img.dtype, device=img.device)[None, :, None, None]
    s = torch.as_tensor(std[:c], dtype=img.dtype, device=img.device)[None, :, None, None]
    return (img - m) / s * (img[:, :1] > 0).to(img.dtype)


def frd_indices(size: int, dim: int = FRD_DIM) -> np.ndarray:
    """The protocol's fixed feature indices: Python's ``random`` seeded with 0."""
    if size < dim:
        raise InputError(None, f"FRD needs at least {dim} feature values per scan, the map has {size}")
    return np.asarray(random.Random(0).sample(range(size), dim), dtype=np.int64)


def band_average(fmap: torch.Tensor, bands: int = FRID_BANDS) -> torch.Tensor:
    """(B, C, H, W) -> (B, C * bands): mean over each band of H / bands rows."""
    b, c, h, w = fmap.shape
    if h % bands:
        raise InputError(None, f"FRID needs an image height divisible by {bands}, got {h}")
    return fmap.reshape(b, c, bands, (h // bands) * w).mean(-1).reshape(b, c * bands)


class RangeNetExtractor:
    """FRD (``kind="frd"``: DarkNet-53, 5 channels, 4096 sub-sampled values) or FRID
    (``kind="frid"``: DarkNet-21, 4 channels, 16 band means per channel)."""

    def __init__(self, kind: str, model: RangeNet, mean=SENSOR_MEAN, std=SENSOR_STD):
        if kind not in ("frd", "frid"):
            raise InputError(None, f"unknown RangeNet metric {kind!r}")
        want = 5 if kind == "frd" else 4
        if model.in_channels != want:
            raise InputError(None, f"{kind.upper()} needs a {want}-channel RangeNet, got {model.in_channels}")
        self.kind, self.model = kind, model.eval()
        self.mean, self.std = tuple(mean), tuple(std)
        self._index: np.ndarray | None = None

    @torch.no_grad()
    def __call__(self, views: dict) -> np.ndarray:
        """Features (B, D) float64 of a batch of protocol views (``generation.protocol_views``)."""
        img = protocol_image(views["depth"], views["xyz"], views["reflectance"], self.kind == "frd")
        x = normalise(torch.from_numpy(img), self.mean, self.std)
        fmap = self.model.features(x)
        if self.kind == "frid":
            return band_average(fmap).double().numpy()
        flat = fmap.reshape(len(fmap), -1)
        if self._index is None:
            self._index = frd_indices(flat.shape[1])
        return flat[:, torch.from_numpy(self._index)].double().numpy()
