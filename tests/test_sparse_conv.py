"""Sparse convolutions against dense torch references, forward and backward."""

from __future__ import annotations

import importlib.util

import pytest
import torch
import torch.nn.functional as F

from omnilidar.errors import InputError
from omnilidar.sparse.backend import resolve_backend
from omnilidar.sparse.conv import SparseConv3d, SparseInverseConv3d, SubMConv3d
from omnilidar.sparse.kernel_map import strided_map, submanifold_map
from omnilidar.sparse.tensor import SparseTensor

SHAPE = (6, 7, 5)


def random_input(seed=0, shape=SHAPE, batch=2, channels=3, density=0.3, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    mask = torch.rand((batch, *shape), generator=gen) < density
    coords = mask.nonzero().to(torch.int32)
    feats = torch.randn(coords.shape[0], channels, generator=gen, dtype=dtype)
    return SparseTensor(feats.requires_grad_(True), coords, shape, batch), mask


def at(dense: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Rows of a dense (B, C, X, Y, Z) tensor at coords."""
    c = coords.long()
    return dense.permute(0, 2, 3, 4, 1)[c[:, 0], c[:, 1], c[:, 2], c[:, 3]]


def torch_layout(weight):  # spconv (out, kD, kH, kW, in) -> conv3d (out, in, kD, kH, kW)
    return weight.permute(0, 4, 1, 2, 3)


def grads(outputs, reference, tensors, seed=5):
    """Gradients of a random projection of outputs and of the reference."""
    proj = torch.randn(outputs.shape, generator=torch.Generator().manual_seed(seed), dtype=outputs.dtype)
    g1 = torch.autograd.grad((outputs * proj).sum(), tensors, retain_graph=True)
    g2 = torch.autograd.grad((reference * proj).sum(), tensors, retain_graph=True)
    return g1, g2


def make(cls, *args, **kwargs):
    layer = cls(*args, **kwargs).double()
    layer.reset_parameters(torch.Generator().manual_seed(1))
    return layer


@pytest.mark.parametrize("kernel,dilation", [(3, 1), (1, 1), ((3, 1, 3), 1), (3, 2)])
def test_submanifold_matches_dense_conv3d(kernel, dilation):
    x, _ = random_input()
    conv = make(SubMConv3d, 3, 4, kernel, dilation=dilation)
    y = conv(x)
    ks = conv.kernel_size
    pad = tuple(dilation * (k // 2) for k in ks)
    ref = at(F.conv3d(x.dense(), torch_layout(conv.weight), padding=pad, dilation=dilation), x.coords)
    assert torch.equal(y.coords, x.coords)
    torch.testing.assert_close(y.feats, ref, rtol=1e-10, atol=1e-12)
    g, g_ref = grads(y.feats, ref, (x.feats, conv.weight))
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("kernel,stride,padding", [(2, 2, 0), (3, 2, 1), (3, 1, 0), (3, 2, 0)])
def test_strided_matches_dense_conv3d(kernel, stride, padding):
    x, mask = random_input(seed=1)
    conv = make(SparseConv3d, 3, 4, kernel, stride, padding)
    y = conv(x)
    dense = F.conv3d(x.dense(), torch_layout(conv.weight), stride=stride, padding=padding)
    assert y.spatial_shape == tuple(dense.shape[2:])
    # Active outputs: exactly the cells some active input reaches.
    reach = F.conv3d(mask[:, None].double(), torch.ones(1, 1, kernel, kernel, kernel, dtype=torch.float64),
                     stride=stride, padding=padding)[:, 0] > 0
    assert torch.equal(reach.nonzero().to(torch.int32), y.coords)  # sorted batch-major
    ref = at(dense, y.coords)
    torch.testing.assert_close(y.feats, ref, rtol=1e-10, atol=1e-12)
    g, g_ref = grads(y.feats, ref, (x.feats, conv.weight))
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("kernel,stride,padding", [(2, 2, 0), (3, 2, 1), (3, 2, 0)])
def test_inverse_matches_conv_transpose3d(kernel, stride, padding):
    x, _ = random_input(seed=2)
    down = make(SparseConv3d, 3, 5, kernel, stride, padding, indice_key="d")
    up = make(SparseInverseConv3d, 5, 2, kernel, indice_key="d")
    coarse = down(x)
    c = coarse.replace_feats(coarse.feats.detach().requires_grad_(True))
    y = up(c)
    assert torch.equal(y.coords, x.coords) and y.spatial_shape == x.spatial_shape
    # conv_transpose3d weight is (in, out, k...): ours (out, k..., in) -> (in, out, k...)
    w = up.weight.permute(4, 0, 1, 2, 3)
    base = [(s - 1) * stride - 2 * padding + kernel for s in coarse.spatial_shape]
    extra = [min(f - b, stride - 1) for f, b in zip(SHAPE, base)]
    dense = F.conv_transpose3d(c.dense(), w, stride=stride, padding=padding, output_padding=tuple(extra))
    dense = F.pad(dense, [0, SHAPE[2] - dense.shape[4], 0, SHAPE[1] - dense.shape[3], 0, SHAPE[0] - dense.shape[2]])
    ref = at(dense, x.coords)
    torch.testing.assert_close(y.feats, ref, rtol=1e-10, atol=1e-12)
    g, g_ref = grads(y.feats, ref, (c.feats, up.weight))
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_kernel_maps_never_write_a_row_twice_per_offset():
    x, _ = random_input(seed=3, density=0.6)
    maps = [submanifold_map(x.coords, SHAPE, 3), strided_map(x.coords, SHAPE, 3, 2, 1)[0]]
    for kmap in maps:
        for _, i_idx, o_idx in kmap.segments():
            assert i_idx.unique().numel() == i_idx.numel()
            assert o_idx.unique().numel() == o_idx.numel()
    sub = maps[0]
    centre = sub.in_idx[sub.bounds[sub.identity]:sub.bounds[sub.identity + 1]]
    assert torch.equal(centre, torch.arange(x.num_voxels))


def test_bitwise_deterministic_forward_and_backward():
    def run():
        x, _ = random_input(seed=4, shape=(12, 12, 8), channels=8, density=0.4, dtype=torch.float32)
        layers = [SubMConv3d(8, 16, 3, indice_key="s"), SparseConv3d(16, 16, 2, 2, indice_key="d"),
                  SparseInverseConv3d(16, 8, 2, indice_key="d")]
        y = x
        for i, layer in enumerate(layers):
            layer.reset_parameters(torch.Generator().manual_seed(i))
            y = layer(y)
        y.feats.square().sum().backward()
        return [y.feats.detach(), x.feats.grad] + [layer.weight.grad for layer in layers]

    for a, b in zip(run(), run()):
        assert torch.equal(a, b)


def test_kernel_map_cache_is_reused_and_checked():
    x, _ = random_input(seed=6)
    conv = make(SubMConv3d, 3, 3, 3, indice_key="k")
    conv(x)
    kmap = x.cache["k"].kmap
    conv(x)
    assert x.cache["k"].kmap is kmap
    with pytest.raises(ValueError, match="indice_key"):
        make(SubMConv3d, 3, 3, 3, dilation=2, indice_key="k")(x)
    with pytest.raises(ValueError, match="no strided convolution"):
        make(SparseInverseConv3d, 3, 3, 2, indice_key="nothing")(x)


def test_unknown_backend_is_an_input_error():
    with pytest.raises(InputError, match="sparse backend"):
        resolve_backend("cuda-magic")
    assert resolve_backend("torch") == "torch"


@pytest.mark.skipif(importlib.util.find_spec("spconv") is None, reason="spconv not installed")
def test_spconv_backend_agrees_or_is_refused():
    from omnilidar.sparse import conv as torch_conv
    from omnilidar.sparse import spconv_backend

    problem = spconv_backend.self_check("cpu")
    if problem is not None:
        # A broken build must never be picked silently.
        with pytest.raises(InputError, match="not usable"):
            resolve_backend("spconv")
        assert resolve_backend("auto") == "torch"
        pytest.skip(f"spconv installed but refused on this CPU: {problem}")
    x, _ = random_input(seed=7, shape=(10, 9, 8), channels=4, dtype=torch.float32)
    outs = []
    for module in (torch_conv, spconv_backend):
        f = x.feats.detach().clone().requires_grad_(True)
        y = SparseTensor(f, x.coords, x.spatial_shape, x.batch_size)
        layers = [module.SubMConv3d(4, 8, 3, indice_key="s"), module.SparseConv3d(8, 8, 2, 2, indice_key="d"),
                  module.SparseInverseConv3d(8, 4, 2, indice_key="d")]
        for i, layer in enumerate(layers):
            layer.reset_parameters(torch.Generator().manual_seed(i))
            y = layer(y)
        y.feats.square().sum().backward()
        outs.append([y.feats.detach(), f.grad] + [layer.weight.grad for layer in layers])
        assert list(layers[0].state_dict()) == ["weight"]
    for a, b in zip(*outs):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)


def test_autocast_runs_the_products_in_the_autocast_dtype_and_backpropagates():
    """AMP training (fp16 on CUDA; bf16 autocast here on CPU) must not mix dtypes inside the
    gather-GEMM-scatter: the output is in the autocast dtype, gradients reach fp32 weights."""
    x, _ = random_input(dtype=torch.float32)
    conv = SubMConv3d(3, 4, 3)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = conv(x)
    assert out.feats.dtype == torch.bfloat16
    out.feats.float().square().sum().backward()
    assert conv.weight.grad is not None and conv.weight.grad.dtype == torch.float32
    assert torch.isfinite(conv.weight.grad).all() and x.feats.grad.dtype == torch.float32
    reference = conv(SparseTensor(x.feats.detach(), x.coords, SHAPE, 2)).feats
    torch.testing.assert_close(out.feats.float(), reference, rtol=0.05, atol=0.05)
