"""The protocol's per-pixel views of range images, shared by every extractor.

Generated and real scans enter every metric the same way: as (2, H, W)
range images in the R2DM encoding, decoded with the generator's geometry. From
them ``range_views`` derives

* ``depth`` (B, H, W) metres, 0 where there is no return;
* ``reflectance`` (B, H, W) in [0, 1];
* ``xyz`` (B, 3, H, W) per-pixel coordinates (0 where there is no return);
* ``mask`` (B, H, W): the protocol mask 0.5 m < depth < 63 m;
* ``xyz_masked``: ``xyz`` zeroed outside ``mask`` (FPD's "all pixels as points");
* ``points``: per scan the (N_i, 3) coordinates of the masked pixels (FSVD,
  FPVD, BEV metrics).
"""

from __future__ import annotations

import numpy as np

from omnilidar.data.range_image import RangeImageSpec, decode, pixel_angles
from omnilidar.errors import InputError
from omnilidar.metrics.extractors.rangenet import MAX_DEPTH, MIN_DEPTH


def pixel_directions(spec: RangeImageSpec) -> np.ndarray:
    """(3, H, W) unit vectors at the pixel-centre angles (sensor frame, no pitch)."""
    elev, azim = pixel_angles(spec)
    ce = np.cos(elev)[:, None]
    return np.stack([
        ce * np.cos(azim)[None, :],
        ce * np.sin(azim)[None, :],
        np.broadcast_to(np.sin(elev)[:, None], spec.shape),
    ])


def check_images(images, spec: RangeImageSpec, source=None) -> np.ndarray:
    """(B, 2, H, W) finite float32 images of the spec's shape, clipped to [-1, 1]."""
    img = np.asarray(images, dtype=np.float32)
    if img.ndim == 3:
        img = img[None]
    if img.ndim != 4 or img.shape[1] != 2 or img.shape[2:] != spec.shape:
        raise InputError(source, f"range images must be (B, 2, {spec.height}, {spec.width}), got {img.shape}")
    if not np.isfinite(img).all():
        raise InputError(source, "range images contain NaN or Inf")
    return np.clip(img, -1.0, 1.0)


def range_views(images, spec: RangeImageSpec, source=None) -> dict:
    """The protocol views of a batch of range images (see module docstring)."""
    img = check_images(images, spec, source)
    depth = np.empty((len(img), *spec.shape), np.float32)
    refl = np.empty_like(depth)
    for b, one in enumerate(img):
        d, i, valid = decode(one, spec)
        depth[b] = np.where(valid, d, 0.0)
        refl[b] = np.where(valid, np.clip(np.nan_to_num(i), 0.0, 1.0), 0.0)
    xyz = (depth[:, None] * pixel_directions(spec)[None]).astype(np.float32)
    mask = (depth > MIN_DEPTH) & (depth < MAX_DEPTH)
    xyz_masked = xyz * mask[:, None]
    points = [xyz[b].reshape(3, -1).T[mask[b].ravel()] for b in range(len(img))]
    return {"depth": depth, "reflectance": refl, "xyz": xyz, "mask": mask, "xyz_masked": xyz_masked,
            "points": points}


def select(views: dict, index) -> dict:
    """The views of a subset of the batch (``index``: slice or index array)."""
    out = {}
    for key, value in views.items():
        if isinstance(value, list):
            idx = range(len(value))[index] if isinstance(index, slice) else index
            out[key] = [value[i] for i in idx]
        else:
            out[key] = value[index]
    return out
