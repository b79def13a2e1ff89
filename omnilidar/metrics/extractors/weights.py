"""Extractor weights: official files supplied by the user, or self-trained checkpoints.

Every feature metric names the weights that produced it:

* ``official:<sha256 of the file, 16 hex>`` -- a published weight file (see the
  README, "Generation metrics", for where each comes from): RangeNet++
  DarkNet-53 (``darknet53-1024.tar.gz`` etc. of the semantic-kitti /
  lidar-bonnetal release; FRD), LiDM's DarkNet-21 without remission
  (``rangenet21_lidm.tar.gz``; FRID), PointNet ShapeNet classifier
  (``cls_model_39.pth``; FPD), and LiDM's MinkowskiNet / SPVCNN converted to
  this package's MinkUNet / SPVCNN state-dict layout (FSVD / FPVD);
* ``self-trained:<config hash>`` -- an extractor the workflow trained on the
  real training split (``omnilidar train-extractor``). Such numbers are
  internally consistent but **not comparable with published ones**; results
  carry ``comparable_with_paper: false`` for them.

Everything is read with ``torch.load(weights_only=True)`` as plain state dicts
(tensors in dicts); nothing a user hands in is unpickled as code. Accepted
official layouts:

* RangeNet: a ``.tar.gz`` or directory holding ``backbone``,
  ``segmentation_decoder``, ``segmentation_head`` (and optionally
  ``arch_cfg.yaml`` with the sensor mean/std), whose keys are prefixed with
  ``backbone.``, ``decoder.`` and ``head.``; or one state dict with those prefixes;
* PointNet, MinkUNet, SPVCNN: one state dict (optionally under ``state_dict``);
* MinkUNet, SPVCNN also: LiDM's / SPVNAS's torchsparse MinkowskiNet / SPVCNN
  checkpoints as published (``model.ckpt``), converted on load by
  :mod:`omnilidar.interop.lidm` (the tag hashes the file as given).
"""

from __future__ import annotations

import hashlib
import io
import tarfile
from dataclasses import dataclass
from pathlib import Path

import torch
import yaml

from omnilidar.errors import InputError
from omnilidar.interop import lidm
from omnilidar.io.atomic import atomic_path
from omnilidar.metrics.extractors import KINDS, METRIC_NAMES
from omnilidar.metrics.extractors.pointnet import PointNet, PointNetExtractor
from omnilidar.metrics.extractors.rangenet import SENSOR_MEAN, SENSOR_STD, RangeNet, RangeNetExtractor
from omnilidar.metrics.extractors.sparse_features import SparseExtractor
from omnilidar.segnets.minkunet import WIDTHS

FORMAT = "omnilidar-extractor/1"
# The architecture each published number was computed with.
PROTOCOL_ARCH = {
    "frd": {"depth": 53, "width": 32, "in_channels": 5},
    "frid": {"depth": 21, "width": 32, "in_channels": 4},
    "fpd": {"num_classes": 16},
}
_BONNETAL_PARTS = {"backbone": "backbone.", "segmentation_decoder": "decoder.", "segmentation_head": "head."}


@dataclass
class LoadedExtractor:
    """A ready feature extractor and the provenance of its weights."""

    kind: str
    extract: object  # callable: views dict -> (B, D) float64 features
    weights: str  # "official:<sha>" or "self-trained:<config hash>"
    comparable_with_paper: bool
    arch: dict


def file_sha(path: str | Path) -> str:
    h = hashlib.sha256()
    path = Path(path)
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()[:16]


def _load_plain(stream, where) -> dict:
    try:
        obj = torch.load(stream, map_location="cpu", weights_only=True)
    except Exception as err:
        raise InputError(where, f"not a weights-only loadable state dict: {err}") from None
    if isinstance(obj, dict) and "state_dict" in obj and isinstance(obj["state_dict"], dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise InputError(where, "expected a plain state dict (names -> tensors)")
    return dict(obj)


def build_model(kind: str, arch: dict, generator: torch.Generator | None = None) -> torch.nn.Module:
    """The network of one metric for an architecture dict (see ``PROTOCOL_ARCH`` and the schema)."""
    if kind in ("frd", "frid"):
        return RangeNet(arch["in_channels"], arch.get("num_classes", 20), arch["depth"], arch["width"])
    if kind == "fpd":
        return PointNet(arch["num_classes"])
    return lidm.sparse_extractor(kind, arch, generator)


def wrap(kind: str, model: torch.nn.Module, mean=SENSOR_MEAN, std=SENSOR_STD):
    """The feature callable of a metric around its network."""
    if kind in ("frd", "frid"):
        return RangeNetExtractor(kind, model, mean, std)
    if kind == "fpd":
        return PointNetExtractor(model)
    return SparseExtractor(kind, model)


def _rangenet_arch(state: dict, where) -> dict:
    try:
        w = state["backbone.conv1.weight"]
        blocks = sum(1 for k in state if k.startswith("backbone.enc3.residual_") and k.endswith(".conv1.weight"))
        return {"in_channels": int(w.shape[1]), "width": int(w.shape[0]), "depth": {8: 53, 2: 21}[blocks],
                "num_classes": int(state["head.1.weight"].shape[0])}
    except (KeyError, IndexError) as err:
        raise InputError(where, f"not a RangeNet (DarkNet-21/53) state dict: missing or unexpected {err}") from None


def _read_rangenet_official(path: Path) -> tuple[dict, tuple, tuple]:
    """State dict with our prefixes, sensor mean and std, from a bonnetal tarball/dir or a file."""
    mean, std = SENSOR_MEAN, SENSOR_STD
    state: dict = {}
    if path.is_dir() or path.name.endswith((".tar.gz", ".tgz", ".tar")):
        members: dict[str, bytes] = {}
        if path.is_dir():
            for f in path.rglob("*"):
                if f.is_file():
                    members[f.name] = f.read_bytes()
        else:
            try:
                with tarfile.open(path) as tar:
                    for m in tar.getmembers():
                        if m.isfile():
                            members[Path(m.name).name] = tar.extractfile(m).read()
            except tarfile.TarError as err:
                raise InputError(path, f"cannot read the archive: {err}") from None
        for part, prefix in _BONNETAL_PARTS.items():
            if part not in members:
                raise InputError(path, f"RangeNet weights need a '{part}' file (lidar-bonnetal layout)")
            for k, v in _load_plain(io.BytesIO(members[part]), f"{path}:{part}").items():
                state[prefix + k] = v
        if "arch_cfg.yaml" in members:
            sensor = yaml.safe_load(members["arch_cfg.yaml"]).get("dataset", {}).get("sensor", {})
            mean = tuple(sensor.get("img_means", mean))
            std = tuple(sensor.get("img_stds", std))
    else:
        state = _load_plain(path, path)
    return state, mean, std


def load_extractor(kind: str, path: str | Path) -> LoadedExtractor:
    """Load the extractor of metric ``kind`` from a self-trained checkpoint or an official file."""
    if kind not in KINDS:
        raise InputError(None, f"unknown feature metric {kind!r}; known: {', '.join(KINDS)}")
    path = Path(path)
    if not path.exists():
        raise InputError(path, f"{METRIC_NAMES[kind]} extractor weights not found")
    payload = None
    if path.is_file() and not path.name.endswith((".tar.gz", ".tgz", ".tar")):
        if kind in ("fsvd", "fpvd"):  # LiDM's Lightning checkpoints need stand-ins for unknown classes
            payload = lidm.load_checkpoint(path)
        else:
            try:
                payload = torch.load(path, map_location="cpu", weights_only=True)
            except Exception as err:
                raise InputError(path, f"not a weights-only loadable file: {err}") from None
        if isinstance(payload, dict) and payload.get("format") == FORMAT:
            return _load_self_trained(kind, path, payload)
    tag = f"official:{file_sha(path)}"
    mean, std = SENSOR_MEAN, SENSOR_STD
    if kind in ("frd", "frid"):
        state, mean, std = _read_rangenet_official(path)
        arch = _rangenet_arch(state, path)
    elif kind in ("fsvd", "fpvd") and payload is not None:
        # LiDM's torchsparse MinkowskiNet / SPVCNN files convert on the fly; our layout loads as is.
        state = lidm.unwrap_state(payload, path)
        if lidm.looks_like_torchsparse(state):
            state, arch = lidm.convert_lidm_state(state, kind, path)
        else:
            arch = _infer_arch(kind, state, path)
    else:
        state = _load_plain(path, path)
        arch = _infer_arch(kind, state, path)
    model = build_model(kind, arch)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise InputError(path, f"weights do not fit the {METRIC_NAMES[kind]} network: {str(err)[:300]}") from None
    comparable = all(arch.get(k) == v for k, v in PROTOCOL_ARCH.get(kind, {}).items())
    return LoadedExtractor(kind, wrap(kind, model, mean, std), tag, comparable, arch)


def _infer_arch(kind: str, state: dict, where) -> dict:
    if kind == "fpd":
        if "fc3.weight" not in state:
            raise InputError(where, "not a PointNet classifier state dict (no fc3.weight)")
        return {"num_classes": int(state["fc3.weight"].shape[0])}
    classes = int(state["classifier.weight"].shape[0]) if "classifier.weight" in state else 19
    for width in WIDTHS:
        for depth in (18, 34):
            arch = {"width": width, "depth": depth, "num_classes": classes}
            try:
                build_model(kind, arch).load_state_dict(state, strict=True)
                return arch
            except RuntimeError:
                continue
    raise InputError(where, f"not a {'MinkUNet' if kind == 'fsvd' else 'SPVCNN'} state dict of a known width/depth "
                            "(convert LiDM's torchsparse weights to this package's layout first)")


def _load_self_trained(kind: str, path: Path, payload: dict) -> LoadedExtractor:
    if payload.get("kind") != kind:
        raise InputError(path, f"is a self-trained {payload.get('kind')} extractor, not {kind}")
    arch = dict(payload["arch"])
    model = build_model(kind, arch)
    try:
        model.load_state_dict(payload["state_dict"], strict=True)
    except RuntimeError as err:
        raise InputError(path, f"weights do not match the stored architecture: {str(err)[:300]}") from None
    return LoadedExtractor(kind, wrap(kind, model), f"self-trained:{payload['config_hash']}", False, arch)


def save_self_trained(path: str | Path, kind: str, arch: dict, config_hash: str, model: torch.nn.Module,
                      meta: dict) -> None:
    """Write a self-trained extractor (weights-only loadable) atomically."""
    payload = {
        "format": FORMAT,
        "kind": kind,
        "arch": arch,
        "config_hash": config_hash,
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
        "meta": meta,
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def parse_pairs(pairs: list[str] | None, what: str) -> dict[str, str]:
    """``["KEY=VALUE", ...]`` command-line pairs -> dict (InputError on a malformed one)."""
    out = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key or not value:
            raise InputError(None, f"{what}: expected KEY=PATH, got {pair!r}")
        out[key] = value
    return out


def load_extractors(weights: dict[str, str], metrics: list[str]) -> dict[str, LoadedExtractor]:
    """The extractors of the feature metrics among ``metrics`` (names such as "FRD"),
    from ``weights`` {kind: path}; a needed kind without weights is an error."""
    out = {}
    for kind in KINDS:
        if METRIC_NAMES[kind] not in metrics:
            continue
        if kind not in weights:
            raise InputError(None, f"{METRIC_NAMES[kind]} is requested but no --weights {kind}=PATH was given")
        out[kind] = load_extractor(kind, weights[kind])
    return out
