"""OpenPCDet's ResidualCoder: box residuals relative to anchors (or RoIs)."""

from __future__ import annotations

import torch


class ResidualCoder:
    """Encodes (x, y, z, dx, dy, dz, r) against anchors: centre offsets over the
    anchor's BEV diagonal (x, y) and height (z), log size ratios, heading difference."""

    def __init__(self, code_size: int = 7, encode_angle_by_sincos: bool = False, **_):
        if encode_angle_by_sincos:
            raise ValueError("ResidualCoder with encode_angle_by_sincos is not supported")
        self.code_size = int(code_size)

    def encode_torch(self, boxes: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
        anchors = torch.cat([anchors[..., :3], anchors[..., 3:6].clamp(min=1e-5), anchors[..., 6:]], -1)
        boxes = torch.cat([boxes[..., :3], boxes[..., 3:6].clamp(min=1e-5), boxes[..., 6:]], -1)
        xa, ya, za, dxa, dya, dza, ra = torch.split(anchors[..., :7], 1, dim=-1)
        xg, yg, zg, dxg, dyg, dzg, rg = torch.split(boxes[..., :7], 1, dim=-1)
        diagonal = torch.sqrt(dxa ** 2 + dya ** 2)
        extra = [g - a for g, a in zip(torch.split(boxes[..., 7:], 1, -1), torch.split(anchors[..., 7:], 1, -1))]
        return torch.cat([(xg - xa) / diagonal, (yg - ya) / diagonal, (zg - za) / dza,
                          torch.log(dxg / dxa), torch.log(dyg / dya), torch.log(dzg / dza), rg - ra, *extra], -1)

    def decode_torch(self, codes: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
        xa, ya, za, dxa, dya, dza, ra = torch.split(anchors[..., :7], 1, dim=-1)
        xt, yt, zt, dxt, dyt, dzt, rt = torch.split(codes[..., :7], 1, dim=-1)
        diagonal = torch.sqrt(dxa ** 2 + dya ** 2)
        extra = [t + a for t, a in zip(torch.split(codes[..., 7:], 1, -1), torch.split(anchors[..., 7:], 1, -1))]
        return torch.cat([xt * diagonal + xa, yt * diagonal + ya, zt * dza + za,
                          torch.exp(dxt) * dxa, torch.exp(dyt) * dya, torch.exp(dzt) * dza, rt + ra, *extra], -1)


BOX_CODERS = {"ResidualCoder": ResidualCoder}


def build_box_coder(name: str, **kwargs) -> ResidualCoder:
    if name not in BOX_CODERS:
        raise ValueError(f"BOX_CODER {name!r} is not one of {sorted(BOX_CODERS)}")
    return BOX_CODERS[name](**kwargs)
