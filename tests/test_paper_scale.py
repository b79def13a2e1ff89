"""The networks of config/paper.yaml build and fit together at paper scale, in seconds.

Dense networks (generator, RangeNet, PointNet) run forward and backward on meta
tensors at the full 64x1024 geometry: every shape is checked, nothing is
computed. Sparse networks (MinkUNet, SPVCNN, their extractor variants) depend on
the coordinates, so they run for real at their paper widths and voxel size on a
small crop. Speed and memory at paper scale: benchmarks/bench_paper_scale.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from omnilidar.config import load_config
from omnilidar.data.range_image import encode
from omnilidar.downstream.seg.models import build_segmentor, model_spec
from omnilidar.downstream.seg.training import make_model
from omnilidar.segnets.voxelize import collate
from omnilidar.generator.unet import build_denoiser, range_image_spec
from omnilidar.metrics.extractors.rangenet import FRD_DIM, FRID_BANDS, band_average
from omnilidar.metrics.extractors.views import range_views
from omnilidar.metrics.extractors.weights import PROTOCOL_ARCH, build_model, wrap

PAPER = Path(__file__).resolve().parents[1] / "config" / "paper.yaml"
CLIP_L14_DIM = 768  # token width of clip-vit-large-patch14 (generator.text.clip_model in paper.yaml)
META = torch.device("meta")


@pytest.fixture(scope="module")
def paper() -> dict:
    return load_config(PAPER)


@pytest.fixture(autouse=True)
def one_thread():
    """Small sparse GEMMs on a shared 2-core machine run far faster single-threaded."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _backward_fills_every_grad(module: torch.nn.Module, out: torch.Tensor) -> None:
    out.float().sum().backward()
    for name, p in module.named_parameters():
        assert p.grad is not None and p.grad.shape == p.shape, name


def test_generator_forward_backward_at_paper_resolution(paper):
    g = paper["generator"]
    assert g["text"]["clip_model"] == "openai/clip-vit-large-patch14"
    spec = range_image_spec(g)
    assert spec.shape == (64, 1024)
    with META:
        den = build_denoiser(g, CLIP_L14_DIM, len(g["prompts"]))
    den = den.to(META)  # the beam-angle buffer is built on the CPU
    b, n_tok = 2, g["text"]["max_tokens"]
    x = torch.empty(b, 2, *spec.shape, device=META)
    eps = den(x, torch.empty(b, device=META), torch.zeros(b, dtype=torch.long, device=META),
              torch.empty(b, n_tok, CLIP_L14_DIM, device=META), torch.ones(b, n_tok, dtype=torch.bool, device=META))
    assert eps.shape == x.shape
    _backward_fills_every_grad(den, eps)


@pytest.mark.parametrize("kind", ["frd", "frid"])
def test_rangenet_extractors_at_paper_resolution(paper, kind):
    spec = range_image_spec(paper["generator"])
    for arch in (PROTOCOL_ARCH[kind], paper["evaluation"]["extractors"]["arch"][kind]):
        with META:
            net = build_model(kind, arch)
        x = torch.empty(1, arch["in_channels"], *spec.shape, device=META)
        fmap = net.features(x)
        assert fmap.shape == (1, arch["width"], *spec.shape)
        if kind == "frd":
            assert fmap[0].numel() >= FRD_DIM  # the protocol samples 4096 values of it
        else:
            assert band_average(fmap).shape == (1, FRID_BANDS * arch["width"])
        logits = net(x)
        assert logits.shape == (1, net.num_classes, *spec.shape)
        _backward_fills_every_grad(net, logits)


def test_pointnet_extractor_on_every_pixel(paper):
    spec = range_image_spec(paper["generator"])
    for arch in (PROTOCOL_ARCH["fpd"], paper["evaluation"]["extractors"]["arch"]["fpd"]):
        with META:
            net = build_model("fpd", arch)
        feats = net.features(torch.empty(2, 3, spec.height * spec.width, device=META))
        assert feats.shape == (2, 1024 + 512 + 256 + arch["num_classes"])  # 1808-d with the official head
        _backward_fills_every_grad(net, feats)


def _crop(rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    """A 3 m x 3 m patch of ground with a box on it, x, y, z, remission (a few thousand voxels at 5 cm)."""
    ground = np.c_[rng.uniform(5, 8, n), rng.uniform(-1.5, 1.5, n), rng.normal(-1.73, 0.01, n)]
    box = np.c_[rng.uniform(6, 7, n // 3), np.full(n // 3, 0.5), rng.uniform(-1.7, -0.2, n // 3)]
    xyz = np.concatenate([ground, box])
    return np.c_[xyz, rng.uniform(0, 1, len(xyz))].astype(np.float32)


@pytest.mark.parametrize("backbone", ["minkunet", "spvcnn"])
def test_segmentors_at_paper_width_and_voxel_size(paper, backbone):
    d = paper["downstream"]
    rng = np.random.default_rng(0)
    pts = _crop(rng)
    batch = collate([pts], [rng.integers(0, 20, len(pts))], voxel_size=d["voxel_size"], max_voxels=d["max_voxels"],
                    rng=rng)
    settings = d["models"][backbone]
    net = build_segmentor(model_spec(backbone, settings, 19), "torch", "cpu", torch.Generator().manual_seed(0))
    logits = net(batch)
    assert logits.shape == (len(pts), 19)
    loss = make_model(net, "voxel" if backbone == "minkunet" else "point")(batch)["loss"]
    loss.backward()
    assert all(p.grad is not None for p in net.parameters())
    lab = d["labeler"]
    if lab["backbone"] == backbone and lab["model"] != settings:
        assert build_segmentor(model_spec(backbone, lab["model"], 19), "torch", "cpu")(batch).shape == (len(pts), 19)


@pytest.mark.parametrize("kind", ["fsvd", "fpvd"])
def test_sparse_extractors_on_a_paper_range_image(paper, kind):
    spec = range_image_spec(paper["generator"])
    depth = np.zeros(spec.shape, np.float32)
    depth[:, :48] = np.linspace(6.0, 20.0, spec.height)[:, None]  # a 48-column wedge of returns
    views = range_views(encode(depth, np.full(spec.shape, 0.5, np.float32), spec)[None], spec)
    arch = paper["evaluation"]["extractors"]["arch"][kind]
    net = build_model(kind, arch, generator=torch.Generator().manual_seed(0))
    feats = wrap(kind, net)(views)
    assert feats.shape == (1, 16 * net.classifier.in_features)  # 16 distance bins (768-d at W16)
    assert np.isfinite(feats).all()
