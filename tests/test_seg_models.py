"""Voxelisation, MinkUNet and SPVCNN on a (cropped) full HDL-64E sweep."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from omnilidar.segnets.minkunet import MinkUNet, minkunet
from omnilidar.segnets.spvcnn import SPVCNN, devoxelize, spvcnn, trilinear_weights
from omnilidar.segnets.voxelize import IGNORE_INDEX, collate, voxel_labels, voxelize
from omnilidar.errors import InputError
from omnilidar.sparse.tensor import SparseTensor


@pytest.fixture(autouse=True)
def one_thread():
    """Small GEMMs on a shared 2-core machine run far faster single-threaded."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def crop(synthetic_sweep):
    """The sweep's points within 5 m of the sensor along x and y (about 35k, like KITTI's within 6 m)."""
    pts = synthetic_sweep.points
    keep = (np.abs(pts[:, 0]) < 5) & (np.abs(pts[:, 1]) < 5)
    return pts[keep]


def test_first_point_per_voxel_and_mapping_back():
    pts = np.array([[0.01, 0.01, 0.01, 0.1], [0.02, 0.03, 0.04, 0.2],  # same voxel
                    [0.26, 0.0, 0.0, 0.3], [0.04, 0.0, 0.0, 0.4]], np.float32)  # last joins voxel 0
    vox = voxelize(pts, 0.05)
    assert vox.num_voxels == 2
    assert vox.point_to_voxel.tolist() == [0, 0, 1, 0]
    assert vox.first_point.tolist() == [0, 2]  # features come from the first point
    assert vox.coords.tolist() == [[0, 0, 0], [5, 0, 0]]
    pos = vox.point_positions(pts, np.arange(4))
    assert np.array_equal(np.floor(pos).astype(np.int32), vox.coords[vox.point_to_voxel])


def test_voxel_cap_is_random_but_reproducible(crop):
    full = voxelize(crop)
    a = voxelize(crop, max_voxels=1000, rng=np.random.default_rng(3))
    b = voxelize(crop, max_voxels=1000, rng=np.random.default_rng(3))
    c = voxelize(crop, max_voxels=1000, rng=np.random.default_rng(4))
    assert full.num_voxels > 1000 and a.num_voxels == 1000
    assert np.array_equal(a.coords, b.coords) and np.array_equal(a.point_to_voxel, b.point_to_voxel)
    assert not np.array_equal(a.coords, c.coords)
    kept = a.point_to_voxel >= 0
    assert np.array_equal(a.coords[a.point_to_voxel[kept]], full.coords[full.point_to_voxel[kept]])
    assert (~kept).any()


def test_voxel_cap_crops_an_azimuth_sector_and_keeps_its_density(crop):
    """Every voxel inside the kept sector stays (no thinning); none outside it is kept."""
    full = voxelize(crop)
    capped = voxelize(crop, max_voxels=full.num_voxels // 3, rng=np.random.default_rng(5))
    kept = np.zeros(full.num_voxels, bool)
    kept[np.unique(full.point_to_voxel[capped.point_to_voxel >= 0])] = True
    assert kept.sum() == capped.num_voxels
    xy = crop[full.first_point, :2].astype(np.float64)
    azimuth = np.arctan2(xy[:, 1], xy[:, 0])
    in_order = kept[np.argsort(azimuth, kind="stable")]
    # one contiguous run of kept voxels around the circle: exactly one kept -> dropped step
    assert np.count_nonzero(in_order & ~np.roll(in_order, -1)) == 1


def test_voxel_labels_majority_ignoring_zero():
    pts = np.zeros((5, 4), np.float32)
    pts[3:, 0] = 1.0
    vox = voxelize(pts, 0.05)
    assert voxel_labels(np.array([0, 0, 7, 0, 0]), vox, 20).tolist() == [7, 0]


def test_bad_points_raise_input_error():
    with pytest.raises(InputError, match="scan.bin.*NaN"):
        voxelize(np.array([[0.0, np.nan, 0.0, 0.0]]), path="scan.bin")
    with pytest.raises(InputError, match="no points"):
        voxelize(np.zeros((0, 4)), path="scan.bin")
    with pytest.raises(InputError, match="labels but"):
        collate([np.zeros((3, 4), np.float32)], [np.zeros(2, np.int64)], paths=["scan.bin"])


def test_trilinear_devoxelisation_reproduces_a_linear_field():
    # Fully occupied 6^3 grid; voxel features = centre x coordinate at the stride.
    stride = 2
    g = torch.stack(torch.meshgrid(*[torch.arange(3)] * 3, indexing="ij"), -1).reshape(-1, 3)
    coords = torch.cat([torch.zeros(len(g), 1, dtype=torch.long), g], 1).to(torch.int32)
    feats = ((g[:, :1].double() + 0.5) * stride)
    x = SparseTensor(feats, coords, (3, 3, 3), 1)
    p = torch.tensor([[0.0, 1.3, 2.2, 3.9], [0.0, 4.7, 1.1, 2.5]], dtype=torch.float32)  # interior
    rows, w = trilinear_weights(x, p, stride)
    torch.testing.assert_close(w.sum(1), torch.ones(2))
    torch.testing.assert_close(devoxelize(x, rows, w)[:, 0], p[:, 1].double(), rtol=1e-6, atol=1e-6)


def test_devoxelisation_and_its_gradient_equal_the_dense_interpolation_matrix():
    """The sparse product (CPU) reads the same features and sends back the same gradient as
    the dense (P, N) matrix of the neighbours' weights, absent neighbours included."""
    gen = torch.Generator().manual_seed(0)
    num_points, num_voxels = 200, 30
    rows = torch.randint(0, num_voxels, (num_points, 8), generator=gen)
    rows[torch.rand(num_points, 8, generator=gen) < 0.4] = -1
    rows[:, 0] = torch.randint(0, num_voxels, (num_points,), generator=gen)  # own voxel: always present
    w = torch.rand(num_points, 8, generator=gen) * (rows >= 0)
    w = w / w.sum(1, keepdim=True)
    dense = torch.zeros(num_points, num_voxels, dtype=torch.float64)
    for k in range(8):
        present = rows[:, k] >= 0
        dense[present.nonzero()[:, 0], rows[present, k]] += w[present, k].double()
    feats = torch.randn(num_voxels, 5, generator=gen, dtype=torch.float64, requires_grad=True)
    x = SparseTensor(feats, torch.zeros(num_voxels, 4, dtype=torch.int32), (1, 1, 1), 1)
    grad_out = torch.randn(num_points, 5, generator=gen, dtype=torch.float64)
    out = devoxelize(x, rows, w)
    (grad,) = torch.autograd.grad(out, feats, grad_out)
    torch.testing.assert_close(out, dense @ feats)
    torch.testing.assert_close(grad, dense.T @ grad_out)


def test_inference_reads_equal_training_reads_and_build_no_transposed_matrix(crop, monkeypatch):
    """Without a gradient SPVCNN skips the transposed matrices and builds each stride's matrix once
    (stride 1 is read twice); its logits equal those of a forward pass that keeps the graph."""
    from omnilidar.segnets import spvcnn as module

    built = []
    original = module.interpolation_matrices
    monkeypatch.setattr(module, "interpolation_matrices",
                        lambda rows, w, n, transposed=True: built.append(transposed) or original(rows, w, n, transposed))
    batch = collate([crop, crop[::2]], [np.ones(len(crop), np.int64), np.ones(len(crop[::2]), np.int64)])
    model = SPVCNN(width="W16", backend="torch", generator=torch.Generator().manual_seed(0)).eval()
    with torch.no_grad():
        fast = model(batch)
    assert built == [False, False, False]  # strides 1, 16, 4: no transposed matrix, stride 1 once
    built.clear()
    kept = model(batch)
    assert built == [True, True, True] and kept.requires_grad
    assert torch.equal(fast, kept.detach())


def test_trilinear_weights_are_the_products_of_the_axis_fractions():
    """Every corner's weight is the product over axes of f or 1 - f (corner order: first axis
    major), renormalised over the corners present."""
    gen = torch.Generator().manual_seed(3)
    g = torch.stack(torch.meshgrid(*[torch.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    keep = torch.rand(len(g), generator=gen) < 0.7
    coords = torch.cat([torch.zeros(int(keep.sum()), 1, dtype=torch.long), g[keep]], 1).to(torch.int32)
    x = SparseTensor(torch.zeros(len(coords), 1), coords, (4, 4, 4), 1)
    p = torch.cat([torch.zeros(50, 1), torch.rand(50, 3, generator=gen) * 6 + 0.5], 1)
    rows, w = trilinear_weights(x, p, 1)
    u = p[:, 1:].double() - 0.5
    f = (u - torch.floor(u)).float()
    expected = torch.ones(50, 8)
    for k, corner in enumerate([(i, j, l) for i in (0, 1) for j in (0, 1) for l in (0, 1)]):
        for axis, side in enumerate(corner):
            expected[:, k] *= f[:, axis] if side else 1 - f[:, axis]
    expected = expected * (rows >= 0)
    torch.testing.assert_close(w, expected / expected.sum(1, keepdim=True).clamp_min(1e-12))


def test_widths_and_depths():
    m = minkunet("W32", backend="torch")
    assert m.trunk.encoder_channels == (32, 64, 128, 256) and m.classifier.in_features == 96
    assert minkunet("W16", backend="torch").classifier.in_features == 48
    deep = minkunet("MinkUNet34", backend="torch")
    assert [len(stage[1]) for stage in deep.trunk.encoder] == [2, 3, 4, 6]
    s = spvcnn("W32", backend="torch")
    assert [(m[0].in_features, m[0].out_features) for m in s.point_mlps] == [(32, 256), (256, 128), (128, 96)]
    assert s.dropout.p == 0.3
    # spconv weight layout in the state dict
    w = m.state_dict()["trunk.stem.0.0.weight"]
    assert tuple(w.shape) == (32, 3, 3, 3, 4)


@pytest.mark.parametrize("cls", [MinkUNet, SPVCNN])
def test_forward_backward_every_point_deterministic(crop, cls):
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 20, len(crop))
    batch = collate([crop, crop[::2]], [labels, labels[::2]], max_voxels=None)

    def run():
        model = cls(width="W16", backend="torch", generator=torch.Generator().manual_seed(0))
        logits = model(batch)
        loss = torch.nn.functional.cross_entropy(logits, batch.point_targets, ignore_index=IGNORE_INDEX)
        loss.backward()
        return logits.detach(), [p.grad.clone() for p in model.parameters()]

    logits, g = run()
    assert logits.shape == (len(crop) + len(crop[::2]), 19)  # every point gets a prediction
    assert [len(t) for t in batch.split_points(logits)] == [len(crop), len(crop[::2])]
    assert torch.isfinite(logits).all() and all(torch.isfinite(x).all() for x in g)
    assert sum(float(x.abs().sum()) for x in g) > 0
    logits2, g2 = run()
    assert torch.equal(logits, logits2) and all(torch.equal(a, b) for a, b in zip(g, g2))


@pytest.mark.parametrize("cls", [MinkUNet, SPVCNN])
def test_bf16_autocast_trains_every_layer_finitely(crop, cls):
    """schedule.amp on CUDA autocasts in bf16 (fp16 overflowed SPVCNN on an H200); CPU autocast runs the
    same dtype through every layer: logits within a few percent of fp32's (same weights, same dropout
    masks), a finite loss and finite gradients on fp32 weights."""
    labels = np.random.default_rng(0).integers(0, 20, len(crop))
    batch = collate([crop, crop[::2]], [labels, labels[::2]], max_voxels=None)

    def model():
        return cls(width="W16", backend="torch", generator=torch.Generator().manual_seed(0))

    with torch.no_grad():
        reference = model()(batch)
    net = model()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        logits = net(batch)
    loss = torch.nn.functional.cross_entropy(logits.float(), batch.point_targets, ignore_index=IGNORE_INDEX)
    loss.backward()
    assert logits.dtype == torch.bfloat16 and torch.isfinite(loss)
    assert all(p.dtype == torch.float32 and torch.isfinite(p.grad).all() for p in net.parameters())
    assert float((logits.float() - reference).norm() / reference.norm()) < 0.05


def test_spvcnn_reads_corners_from_the_trunks_kernel_maps_exactly_as_by_search(crop, monkeypatch):
    """Corner and own-voxel rows taken from the cached kernel maps give the logits and gradients of
    the binary search bit for bit, points whose float position rounds across a cell included."""
    from omnilidar.segnets import spvcnn as module

    rng = np.random.default_rng(1)
    labels = rng.integers(0, 20, len(crop))
    batch = collate([crop, crop[::3]], [labels, labels[::3]], max_voxels=None)
    # Move some points most of a cell off their voxel (as if rounded across its face): their corners
    # leave the voxel's neighbourhood and must be searched.
    batch.point_coords[::50, 1] = torch.floor(batch.point_coords[::50, 1]) - 0.7
    calls = []
    lookup = module._lookup
    monkeypatch.setattr(module, "_lookup", lambda x, b, cells: calls.append(len(cells)) or lookup(x, b, cells))

    def run():
        model = SPVCNN(width="W16", backend="torch", generator=torch.Generator().manual_seed(0))
        logits = model(batch)
        logits.square().sum().backward()
        return logits.detach(), [p.grad.clone() for p in model.parameters()]

    fast = run()
    assert 0 < sum(calls) <= 3 * len(batch.point_coords[::50])  # only moved points were searched
    monkeypatch.setattr(module, "_neighbours", lambda x, stride: None)
    monkeypatch.setattr(module, "_own_rows", lambda x, batch, stride: None)
    searched = run()
    assert torch.equal(fast[0], searched[0]) and all(torch.equal(a, b) for a, b in zip(fast[1], searched[1]))


def test_checkpoint_moves_between_backends(crop):
    from omnilidar.sparse import spconv_backend

    torch_model = MinkUNet(width="W16", backend="torch", generator=torch.Generator().manual_seed(0))
    if not spconv_backend.spconv_available("cpu"):
        pytest.skip("spconv missing or refused by its self-check on this CPU")
    other = MinkUNet(width="W16", backend="spconv")
    other.load_state_dict(torch_model.state_dict())
    batch = collate([crop])
    torch_model.eval(), other.eval()
    with torch.no_grad():
        torch.testing.assert_close(torch_model(batch), other(batch), rtol=1e-3, atol=1e-3)
