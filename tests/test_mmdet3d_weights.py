"""mmdetection3d MinkUNet / SPVCNN labeler checkpoints convert on load.

The mmdet3d state dicts are written here from mmdet3d's module structure
(``MinkUNetBackbone`` / ``SPVCNNBackbone``, ``MinkUNetHead``, mmdet's
``BasicBlock`` for spconv, torchsparse's kernel-offset order spelled out), not
with the converter's own key map; synthetic weights. That torchsparse's offset
order computes what our kernels compute is proven in test_lidm_weights.py.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from omnilidar.config import section_defaults
from omnilidar.downstream.seg.evaluate import load_segmentor
from omnilidar.downstream.seg.labeler import import_labeler
from omnilidar.interop.mmdet3d import convert_mmdet3d_state
from omnilidar.downstream.seg.models import build_segmentor
from omnilidar.segnets.voxelize import collate
from omnilidar.errors import InputError


def _torchsparse_kernel(w: torch.Tensor) -> torch.Tensor:
    """Our (C_out, k, k, k, C_in) weight as torchsparse's kernel."""
    c_out, k, _, _, c_in = w.shape
    if k == 1:
        return w.reshape(c_out, c_in).T.contiguous()  # (C_in, C_out)
    out = w.new_zeros((k**3, c_in, c_out))
    for x in range(k):
        for y in range(k):
            for z in range(k):
                # odd kernels: x fastest (offsets -1..1); even kernels: z fastest (0..1)
                t = z * 9 + y * 3 + x if k == 3 else x * 4 + y * 2 + z
                out[t] = w[:, x, y, z, :].T
    return out


def _mmdet3d_name(key: str, backend: str) -> str:
    ts = backend == "torchsparse"
    conv = (lambda n: f"net.{n}") if ts else (lambda n: f"{n}")
    block = {"0": "net.0", "1": "net.1", "3": "net.3", "4": "net.4"} if ts else \
        {"0": "conv1", "1": "bn1", "3": "conv2", "4": "bn2"}
    rules = [
        (r"trunk\.stem\.(\d)\.(\d)\.", lambda m: f"backbone.conv_input.{m[1]}.{conv(m[2])}."),
        (r"trunk\.encoder\.(\d)\.0\.(\d)\.", lambda m: f"backbone.encoder.{m[1]}.0.{conv(m[2])}."),
        (r"trunk\.encoder\.(\d)\.1\.(\d)\.body\.(\d)\.",
         lambda m: f"backbone.encoder.{m[1]}.{int(m[2]) + 1}.{block[m[3]]}."),
        (r"trunk\.encoder\.(\d)\.1\.(\d)\.shortcut\.(\d)\.",
         lambda m: f"backbone.encoder.{m[1]}.{int(m[2]) + 1}.downsample.{m[3]}."),
        (r"trunk\.up\.(\d)\.(\d)\.", lambda m: f"backbone.decoder.{m[1]}.0.{conv(m[2])}."),
        (r"trunk\.fuse\.(\d)\.(\d)\.body\.(\d)\.", lambda m: f"backbone.decoder.{m[1]}.1.{m[2]}.{block[m[3]]}."),
        (r"trunk\.fuse\.(\d)\.(\d)\.shortcut\.(\d)\.", lambda m: f"backbone.decoder.{m[1]}.1.{m[2]}.downsample.{m[3]}."),
        (r"point_mlps\.", lambda m: "backbone.point_transforms."),
        (r"classifier\.", lambda m: "decode_head.conv_seg."),
    ]
    for pattern, repl in rules:
        new, n = re.subn("^" + pattern, repl, key)
        if n:
            return new
    raise AssertionError(key)


def as_mmdet3d(model: torch.nn.Module, backend: str) -> dict[str, torch.Tensor]:
    out = {}
    for key, value in model.state_dict().items():
        name = _mmdet3d_name(key, backend)
        if value.dim() == 5:  # sparse conv weight; torchsparse calls it "kernel"
            name = name[:-len("weight")] + "kernel" if backend == "torchsparse" else name
            value = {"torchsparse": _torchsparse_kernel, "spconv": lambda w: w,
                     "spconv1": lambda w: w.permute(1, 2, 3, 4, 0).contiguous()}[backend](value)
        out[name] = value.clone()
    return out


def _model(backbone: str, width: str = "W16", depth: int = 18, seed: int = 0) -> torch.nn.Module:
    g = torch.Generator().manual_seed(seed)
    model = build_segmentor({"backbone": backbone, "width": width, "depth": depth, "in_channels": 4,
                             "num_classes": 19}, "torch", generator=g)
    with torch.no_grad():  # non-trivial BatchNorm statistics
        for m in model.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.running_mean.uniform_(-0.2, 0.2, generator=g)
                m.running_var.uniform_(0.5, 1.5, generator=g)
                m.weight.uniform_(0.5, 1.5, generator=g)
                m.bias.uniform_(-0.2, 0.2, generator=g)
    return model.eval()


def _batch():
    rng = np.random.default_rng(1)
    xyz = rng.uniform([-6, -6, -1.5], [6, 6, 1.0], (1500, 3)).astype(np.float32)
    pts = np.concatenate([xyz, rng.uniform(0, 1, (1500, 1)).astype(np.float32)], 1)
    return collate([pts], voxel_size=0.25)


class HistoryBuffer:  # stands for mmengine's message-hub objects a weights-only load refuses
    def __init__(self):
        self.data = [1.0, 2.0]


def test_mmdet3d_names_follow_its_module_structure():
    names = set(as_mmdet3d(_model("minkunet", "W32"), "torchsparse"))
    # W32: stem 32 = encoder[0] 32, so mmdet3d's first encoder block has no downsample
    assert "backbone.encoder.0.1.downsample.0.kernel" not in names
    assert {"backbone.conv_input.1.net.0.kernel", "backbone.encoder.0.0.net.0.kernel",
            "backbone.encoder.1.1.downsample.0.kernel", "backbone.encoder.3.2.net.4.running_var",
            "backbone.decoder.3.0.net.1.weight", "backbone.decoder.0.1.0.downsample.0.kernel",
            "backbone.decoder.3.1.1.net.3.kernel", "decode_head.conv_seg.weight"} <= names


@pytest.mark.parametrize("backbone,backend,width,depth", [
    ("minkunet", "torchsparse", "W16", 18), ("spvcnn", "torchsparse", "W16", 18),
    ("minkunet", "spconv", "W16", 34), ("minkunet", "spconv1", "W20", 18)])
def test_mmdet3d_checkpoint_imports_and_predicts_identically(backbone, backend, width, depth, tmp_path):
    model = _model(backbone, width, depth)
    ckpt = tmp_path / "epoch_15.pth"
    torch.save({"meta": {"epoch": 15, "dataset_meta": {"classes": ["car"]}},
                "state_dict": as_mmdet3d(model, backend), "message_hub": {"log": HistoryBuffer()}}, ckpt)
    section = section_defaults("downstream")["labeler"]  # backbone, width, depth come from the file
    info = import_labeler(section, ckpt, tmp_path / "labeler.pt")
    assert info["layout"] == "mmdet3d"
    assert info["model"] == {"backbone": backbone, "width": width, "depth": depth, "in_channels": 4,
                             "num_classes": 19}
    imported, payload = load_segmentor(tmp_path / "labeler.pt", device="cpu")
    batch = _batch()
    with torch.no_grad():
        assert torch.equal(imported.eval()(batch), model(batch))


def test_wrong_mmdet3d_checkpoints_are_one_clear_error(tmp_path):
    state = as_mmdet3d(_model("minkunet"), "torchsparse")
    missing = {k: v for k, v in state.items() if k != "backbone.encoder.2.1.net.3.kernel"}
    with pytest.raises(InputError, match="missing key 'backbone.encoder.2.1.net.3.kernel'"):
        convert_mmdet3d_state(missing, "x.pth")
    extra = {**state, "backbone.point_extra.weight": torch.zeros(3)}
    with pytest.raises(InputError, match="unexpected key 'backbone.point_extra.weight'"):
        convert_mmdet3d_state(extra, "x.pth")
    bent = {**state, "backbone.encoder.1.0.net.0.kernel": torch.zeros(27, 16, 16)}
    with pytest.raises(InputError, match=r"has shape \(27, 16, 16\), expected \(8, 16, 16\)"):
        convert_mmdet3d_state(bent, "x.pth")
    mink = {k.replace("encoder.0.1.net.0.", "encoder.0.1.conv1."): v for k, v in state.items()}
    with pytest.raises(InputError, match="minkowski"):
        convert_mmdet3d_state(mink, "x.pth")
    ten = dict(state, **{"decode_head.conv_seg.weight": torch.zeros(10, 48), "decode_head.conv_seg.bias": torch.zeros(10)})
    torch.save({"state_dict": ten}, tmp_path / "ten.pth")
    with pytest.raises(InputError, match="10 classes"):
        import_labeler(section_defaults("downstream")["labeler"], tmp_path / "ten.pth", tmp_path / "out.pt")
    assert not (tmp_path / "out.pt").exists()
