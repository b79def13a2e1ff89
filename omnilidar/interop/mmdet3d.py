"""mmdetection3d MinkUNet / SPVCNN segmentor weights in this package's layout.

mmdet3d's ``MinkUNet`` segmentor (``mmdet3d/models/segmentors/minkunet.py``)
holds ``backbone.`` (``MinkUNetBackbone`` or ``SPVCNNBackbone``) and
``decode_head.conv_seg`` (``MinkUNetHead``: ``Linear(channels, num_classes)``,
19 SemanticKITTI classes in the official learning-map order, so its column
``c`` is our train id ``c + 1`` as well). Its checkpoints are mmengine files
(``{"meta", "state_dict", "optimizer", "message_hub"}``); the state dict is
taken from ``state_dict`` and whatever else a weights-only load refuses
(mmengine's message hub) becomes inert data, nothing in the file runs.

Backbone names (``sparseconv_backend``), all mapped by :func:`key_map`:

* ``torchsparse`` (mmdet3d's default, every SPVCNN): ``conv_input.{0,1}.net.{0,1}``,
  ``encoder.{i}.0.net.{0,1}`` (stride-2 conv), ``encoder.{i}.{j}.net.{0,1,3,4}`` and
  ``.downsample.{0,1}`` (basic blocks), ``decoder.{i}.0.net.{0,1}`` (transposed
  conv), ``decoder.{i}.1.{j}...``, SPVCNN ``point_transforms.{0,1,2}.{0,1}``.
  Kernels ``(K, C_in, C_out)`` in torchsparse's offset order, converted as the
  LiDM extractor weights are (:func:`omnilidar.interop.lidm.kernel_to_ours`).
* ``spconv`` (spconv 2.x): ``conv_input.{0,1}.{0,1}``, ``encoder.{i}.0.{0,1}``,
  blocks ``conv1``, ``bn1``, ``conv2``, ``bn2``, ``downsample.{0,1}`` (mmdet's
  ``BasicBlock``), ``decoder.{i}.0.{0,1}`` (``SparseInverseConv3d``). Weights
  ``(C_out, kx, ky, kz, C_in)`` -- our layout already, copied as they are.
* ``spconv`` through mmcv's spconv 1.x ops (no spconv 2 installed): the same
  names with weights ``(kx, ky, kz, C_in, C_out)``, permuted.
* ``minkowski`` (MinkowskiEngine) is refused: its kernel-offset order for the
  2x2x2 and transposed kernels is not established here.

Widths, depth (encoder blocks ``[2, 2, 2, 2]`` = 18, ``[2, 3, 4, 6]`` = 34),
classes and input channels are read from the tensor shapes; the backbone is
SPVCNN when ``point_transforms`` are present.

The same weights in both networks: the voxel trunk and head compute what
mmdet3d's do for the same voxels and features (first point's x, y, z,
intensity). mmdet3d's SPVCNN runs its point branch on one point per voxel at
the voxel's corner; ours on every point at its position, so SPVCNN point
predictions can differ slightly near voxel borders.
"""

from __future__ import annotations

import torch

from omnilidar.errors import InputError
from omnilidar.interop.lidm import kernel_to_ours, ours_to_kernel_shape, remap_state
from omnilidar.segnets.build import IN_CHANNELS, build_segmentor
from omnilidar.segnets.minkunet import DECODER_BLOCKS, WIDTHS

PREFIX = "backbone."
HEAD = "decode_head.conv_seg."
LAYOUTS = ("torchsparse", "spconv", "spconv1")
_BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
_DEPTHS = {(2, 2, 2, 2): 18, (2, 3, 4, 6): 34}


def looks_like_mmdet3d(state: dict) -> bool:
    """True for an mmdet3d segmentor state dict (``backbone.`` + ``decode_head.``)."""
    return any(k.startswith(PREFIX) for k in state) and f"{HEAD}weight" in state


def detect_layout(state: dict, where=None) -> str:
    """``torchsparse``, ``spconv`` (2.x weights) or ``spconv1`` (mmcv ops)."""
    if "backbone.conv_input.0.net.0.kernel" in state:
        if any(k.startswith("backbone.encoder.0.1.conv1.") for k in state):
            raise InputError(where, "mmdet3d MinkUNet with sparseconv_backend='minkowski' is not supported "
                                    "(convert it with the torchsparse or spconv backend)")
        return "torchsparse"
    stem = state.get("backbone.conv_input.0.0.weight")
    if stem is not None and stem.dim() == 5:
        if tuple(stem.shape[1:4]) == (3, 3, 3):
            return "spconv"
        if tuple(stem.shape[:3]) == (3, 3, 3):
            return "spconv1"
    raise InputError(where, "mmdet3d state dict of an unknown backbone: no 'backbone.conv_input.0.net.0.kernel' "
                            "(torchsparse) or 'backbone.conv_input.0.0.weight' (spconv)")


# --------------------------------------------------------------------------- key map


def _conv_module(layout: str, theirs: str, ours: str, k: int) -> list[tuple[str, str, str]]:
    """conv + BN (the ReLU holds no tensors)."""
    conv, bn = (f"{theirs}.net.0", f"{theirs}.net.1") if layout == "torchsparse" else (f"{theirs}.0", f"{theirs}.1")
    weight = "kernel" if layout == "torchsparse" else "weight"
    return [(f"{conv}.{weight}", f"{ours}.0.weight", f"conv{k}")] + \
        [(f"{bn}.{t}", f"{ours}.1.{t}", "bn") for t in _BN]


def _block(layout: str, theirs: str, ours: str, shortcut: bool) -> list[tuple[str, str, str]]:
    """Basic residual block: two 3x3x3 conv-BN, optional 1x1x1 conv-BN shortcut."""
    if layout == "torchsparse":
        parts = [("net.0.kernel", "body.0.weight", "conv3"), ("net.3.kernel", "body.3.weight", "conv3")]
        parts += [(f"net.1.{t}", f"body.1.{t}", "bn") for t in _BN] + [(f"net.4.{t}", f"body.4.{t}", "bn") for t in _BN]
        short = [("downsample.0.kernel", "shortcut.0.weight", "conv1")]
    else:
        parts = [("conv1.weight", "body.0.weight", "conv3"), ("conv2.weight", "body.3.weight", "conv3")]
        parts += [(f"bn1.{t}", f"body.1.{t}", "bn") for t in _BN] + [(f"bn2.{t}", f"body.4.{t}", "bn") for t in _BN]
        short = [("downsample.0.weight", "shortcut.0.weight", "conv1")]
    if shortcut:
        parts += short + [(f"downsample.1.{t}", f"shortcut.1.{t}", "bn") for t in _BN]
    return [(f"{theirs}.{a}", f"{ours}.{b}", typ) for a, b, typ in parts]


def key_map(layout: str, arch: dict) -> list[tuple[str, str, str]]:
    """Every ``(mmdet3d key, our key, tensor type)`` of the network ``arch``
    (``stem``, ``encoder``, ``decoder`` widths, ``encoder_blocks``, ``spvcnn``)."""
    b, m = "backbone", []
    stem, enc, dec = arch["stem"], arch["encoder"], arch["decoder"]
    for s in range(2):
        m += _conv_module(layout, f"{b}.conv_input.{s}", f"trunk.stem.{s}", 3)
    cin = stem
    for i, (cout, blocks) in enumerate(zip(enc, arch["encoder_blocks"])):
        m += _conv_module(layout, f"{b}.encoder.{i}.0", f"trunk.encoder.{i}.0", 2)
        for j in range(blocks):
            m += _block(layout, f"{b}.encoder.{i}.{j + 1}", f"trunk.encoder.{i}.1.{j}", j == 0 and cin != cout)
        cin = cout
    for i, cout in enumerate(dec):
        m += _conv_module(layout, f"{b}.decoder.{i}.0", f"trunk.up.{i}", 2)
        for j in range(DECODER_BLOCKS[i]):
            m += _block(layout, f"{b}.decoder.{i}.1.{j}", f"trunk.fuse.{i}.{j}", j == 0)
    if arch["spvcnn"]:
        for k in range(3):
            m += [(f"{b}.point_transforms.{k}.0.{t}", f"point_mlps.{k}.0.{t}", "linear") for t in ("weight", "bias")]
            m += [(f"{b}.point_transforms.{k}.1.{t}", f"point_mlps.{k}.1.{t}", "bn") for t in _BN]
    m += [(f"{HEAD}{t}", f"classifier.{t}", "linear") for t in ("weight", "bias")]
    return m


# --------------------------------------------------------------------------- shapes


def _out_channels(t: torch.Tensor, layout: str) -> int:
    return int(t.shape[-1] if layout in ("torchsparse", "spconv1") else t.shape[0])


def _in_channels(t: torch.Tensor, layout: str) -> int:
    if layout == "torchsparse":
        return int(t.shape[-2])
    return int(t.shape[-1] if layout == "spconv" else t.shape[-2])


def infer_arch(state: dict, layout: str, where=None) -> tuple[dict, dict]:
    """``(arch, spec)``: the mmdet3d network's widths and our model spec."""
    conv = "net.0.kernel" if layout == "torchsparse" else "0.weight"
    first = "net.0.kernel" if layout == "torchsparse" else "conv1.weight"

    def need(key: str) -> torch.Tensor:
        if key not in state:
            raise InputError(where, f"mmdet3d {layout} state dict lacks key {key!r}")
        return state[key]

    stem_t = need(f"backbone.conv_input.0.{conv}")
    stem = _out_channels(stem_t, layout)
    enc = [_out_channels(need(f"backbone.encoder.{i}.1.{first}"), layout) for i in range(4)]
    dec = [_out_channels(need(f"backbone.decoder.{i}.0.{conv}"), layout) for i in range(4)]
    blocks = tuple(len({k.split(".")[3] for k in state if k.startswith(f"backbone.encoder.{i}.")}) - 1
                   for i in range(4))
    depth = _DEPTHS.get(blocks)
    if depth is None:
        raise InputError(where, f"encoder blocks {list(blocks)} match no MinkUNet depth "
                                f"(18: [2, 2, 2, 2], 34: [2, 3, 4, 6])")
    width = next((n for n, (s, e, d) in WIDTHS.items() if [s, *e, *d] == [stem, *enc, *dec]), None)
    if width is None:
        presets = ", ".join(f"{n}={[s, *e, *d]}" for n, (s, e, d) in WIDTHS.items())
        raise InputError(where, f"channel widths {[stem, *enc, *dec]} match no MinkUNet preset ({presets})")
    cin = _in_channels(stem_t, layout)
    if cin != IN_CHANNELS:
        raise InputError(where, f"the network takes {cin} input channels; ours take {IN_CHANNELS} (x, y, z, intensity)")
    spvcnn = any(k.startswith("backbone.point_transforms.") for k in state)
    classes = int(need(f"{HEAD}weight").shape[0])
    arch = {"stem": stem, "encoder": enc, "decoder": dec, "encoder_blocks": blocks, "spvcnn": spvcnn}
    spec = {"backbone": "spvcnn" if spvcnn else "minkunet", "width": width, "depth": depth,
            "in_channels": IN_CHANNELS, "num_classes": classes}
    return arch, spec


def _their_shape(ours: torch.Size, layout: str, typ: str) -> tuple[int, ...]:
    if not typ.startswith("conv"):
        return tuple(ours)
    if layout == "torchsparse":
        return ours_to_kernel_shape(ours)
    if layout == "spconv1":
        c_out, kx, ky, kz, c_in = ours
        return (kx, ky, kz, c_in, c_out)
    return tuple(ours)


def _to_ours(t: torch.Tensor, layout: str, typ: str) -> torch.Tensor:
    if not typ.startswith("conv") or layout == "spconv":
        return t
    if layout == "torchsparse":
        return kernel_to_ours(t, int(typ[4:]))
    return t.permute(4, 0, 1, 2, 3).contiguous()  # spconv 1.x: (k, k, k, C_in, C_out)


def convert_mmdet3d_state(state: dict, where=None) -> tuple[dict[str, torch.Tensor], dict]:
    """Convert an mmdet3d MinkUNet / SPVCNN segmentor state dict.

    Returns ``(our_state_dict, spec)``; ``spec`` builds the network with
    :func:`omnilidar.downstream.seg.models.build_segmentor`. Raises InputError
    naming ``where`` and the first unknown, missing or misshapen key.
    """
    layout = detect_layout(state, where)
    arch, spec = infer_arch(state, layout, where)
    mapping = key_map(layout, arch)
    unknown = sorted(set(state) - {theirs for theirs, _, _ in mapping})
    if unknown:
        raise InputError(where, f"unexpected key {unknown[0]!r} for an mmdet3d {spec['backbone']} "
                                f"{spec['width']} depth {spec['depth']} ({layout})")
    network = f"an mmdet3d {spec['backbone']} {spec['width']} depth {spec['depth']}"
    out = remap_state(state, mapping, build_segmentor(spec, "torch").state_dict(),
                      lambda ours, typ: _their_shape(ours, layout, typ), lambda t, typ: _to_ours(t, layout, typ),
                      network, where)
    return out, spec
