"""Self-training of the metric extractors when no official weights are supplied.

Pretext: semantic segmentation on the real training split (SemanticKITTI labels,
train ids 1..19), with each scan seen exactly as the metrics see it: projected
to a range image of the generator's geometry and decoded into the protocol views
(``views.range_views``). Per network:

* RangeNet (FRD, FRID): per-pixel cross-entropy over 20 ids (0 ignored);
* MinkUNet / SPVCNN (FSVD, FPVD): per-point cross-entropy over the 19
  classes on the masked pixels' points with features [x, y, z, -1];
* PointNet (FPD): a scan-level classifier, so its pretext is to predict the
  scan's class distribution (soft cross-entropy against the label histogram
  of the masked pixels); k = 19 outputs, i.e. 1811-d features.

AdamW, a fixed number of iterations, batches drawn from an explicit
``np.random.Generator``, weights initialised from a seeded ``torch.Generator``.
The schedule is CPU-sized by default (``evaluation.extractors`` in the schema).
"""

from __future__ import annotations

import time
import zlib
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from omnilidar.data.range_image import RangeImageSpec, encode, project
from omnilidar.devices import resolve_device
from omnilidar.errors import InputError
from omnilidar.io.semantickitti import read_label, read_points, to_train_ids
from omnilidar.metrics.extractors.pointnet import pixel_points
from omnilidar.metrics.extractors.rangenet import SENSOR_MEAN, SENSOR_STD, normalise, protocol_image
from omnilidar.metrics.extractors.sparse_features import scan_inputs
from omnilidar.metrics.extractors.views import range_views, select
from omnilidar.metrics.extractors.weights import build_model, save_self_trained
from omnilidar.provenance import config_hash
from omnilidar.segnets.voxelize import collate

NUM_IDS = 20  # train ids 0 (ignore) .. 19


def labelled_views(entries: list[dict], spec: RangeImageSpec) -> tuple[dict, np.ndarray]:
    """Protocol views of labelled scans and their per-pixel train ids (B, H, W)."""
    images, labels = [], []
    for entry in entries:
        if not entry.get("labels"):
            raise InputError(entry["points"], "training an extractor needs labelled scans (no label file)")
        pts = read_points(entry["points"])
        sem, _ = read_label(entry["labels"], len(pts))
        ids = to_train_ids(sem)
        proj = project(pts, spec)
        labels.append(proj.per_pixel(ids).astype(np.int64))
        images.append(encode(proj.range_img, proj.intensity_img, spec))
    return range_views(np.stack(images), spec), np.stack(labels)


def _loss(kind: str, model, views: dict, labels: np.ndarray, device=torch.device("cpu")) -> torch.Tensor:
    mask = views["mask"]
    lab = np.where(mask, labels, 0)
    if kind in ("frd", "frid"):
        img = protocol_image(views["depth"], views["xyz"], views["reflectance"], kind == "frd")
        logits = model(normalise(torch.from_numpy(img), SENSOR_MEAN, SENSOR_STD).to(device))
        return F.cross_entropy(logits, torch.from_numpy(lab).to(device), ignore_index=0)
    if kind == "fpd":
        hist = np.stack([np.bincount(x[x > 0], minlength=NUM_IDS)[1:] for x in lab.reshape(len(lab), -1)])
        has = hist.sum(1) > 0
        target = torch.from_numpy(hist[has] / hist[has].sum(1, keepdims=True)).float().to(device)
        logits = model(torch.from_numpy(pixel_points(views["xyz_masked"][has])).to(device))
        return -(target * F.log_softmax(logits, 1)).sum(1).mean()
    scans, ids = [], []
    for b, pts in enumerate(views["points"]):
        keep = np.einsum("ij,ij->i", pts, pts) > 0
        scans.append(scan_inputs(pts))
        ids.append(lab[b][mask[b]][keep])
    batch = collate(scans, ids, num_classes=NUM_IDS).to(device)
    return F.cross_entropy(model(batch), batch.point_targets, ignore_index=-1)


def _fit(kind, model, views, labels, schedule, rng, take, log, device) -> tuple[list[float], float]:
    """AdamW for the scheduled iterations on random batches; the losses and seconds."""
    opt = torch.optim.AdamW(model.parameters(), lr=schedule["lr"], weight_decay=schedule["weight_decay"])
    model.train()
    t0 = time.perf_counter()
    losses = []
    bs = min(int(schedule["batch_size"]), take)
    if kind == "fpd":  # PointNet's BatchNorm on scan-level vectors needs two scans per batch
        if take < 2:
            raise InputError(None, "the FPD extractor needs at least 2 training scans")
        bs = max(bs, 2)
    for it in range(int(schedule["iterations"])):
        idx = np.sort(rng.choice(take, bs, replace=False))
        loss = _loss(kind, model, select(views, idx), labels[idx], device)
        if not torch.isfinite(loss):
            raise RuntimeError(f"{kind} extractor: non-finite loss at iteration {it}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        losses.append(float(loss.detach()))
        if it % max(1, int(schedule["iterations"]) // 10) == 0:
            log(f"{kind} iter {it}: loss {losses[-1]:.4f} ({time.perf_counter() - t0:.1f} s)")
    return losses, time.perf_counter() - t0


def train_extractor(kind: str, arch: dict, schedule: dict, entries: list[dict], spec: RangeImageSpec, seed: int,
                    out: str | Path, log=print) -> dict:
    """Train one extractor on labelled scans (on ``schedule["device"]``, CPU by default) and write it
    to ``out``; return a summary."""
    if not entries:
        raise InputError(None, "no labelled training scans for the extractor")
    rng = np.random.default_rng([seed, 0xE7, zlib.crc32(kind.encode())])
    take = min(len(entries), int(schedule["max_scans"]))
    picked = [entries[i] for i in np.sort(rng.choice(len(entries), take, replace=False))]
    views, labels = labelled_views(picked, spec)
    gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
    # Dropout draws from torch's global RNG: seed it for the whole run, restore it after.
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(rng.integers(2**62)))
        model = build_model(kind, arch, generator=gen)
        device = resolve_device(schedule.get("device", "cpu"), "evaluation.extractors.training.device")
        losses, seconds = _fit(kind, model.to(device), views, labels, schedule, rng, take, log, device)
    model = model.cpu().eval()
    # Where it trained is not what it is: the tag leaves the device out.
    identity = {k: v for k, v in schedule.items() if k != "device"}
    chash = config_hash({"kind": kind, "arch": arch, "schedule": identity, "seed": seed,
                         "spec": repr(spec), "scans": [Path(e["points"]).name for e in picked]})
    meta = {"loss_first": losses[0], "loss_last": float(np.mean(losses[-max(1, len(losses) // 10):])),
            "iterations": len(losses), "scans": take, "seconds": seconds}
    save_self_trained(out, kind, arch, chash, model, meta)
    return {"config_hash": chash, **meta}
