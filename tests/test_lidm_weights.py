"""LiDM / SPVNAS torchsparse MinkowskiNet and SPVCNN weights converted to our layout.

The synthetic checkpoints below follow SPVNAS ``core/models/semantic_kitti/
{minkunet,spvcnn}.py`` (the modules LiDM's ``lidm/eval/models`` copy via 2DPASS):
``nn.Sequential`` stems and stages of ``BasicConvolutionBlock`` (``net.0`` conv,
``net.1`` BN), ``ResidualBlock`` (``net.0/1/3/4``, ``downsample.0/1`` when the
widths differ), ``BasicDeconvolutionBlock`` and ``classifier = Sequential(Linear)``;
``torchsparse.nn.Conv3d.kernel`` is ``(K, C_in, C_out)``, ``(C_in, C_out)`` for K = 1.

The expected outputs of the offset tests are derived from torchsparse's
documented kernel enumeration (``get_kernel_offsets`` in 1.4.0 and 2.x): an odd
kernel is enumerated x fastest with offsets -1..1, an even kernel z fastest with
offsets 0..1, and output ``o`` receives ``x[o + offset_t] @ K[t]`` (strided:
``x[2 o + offset_t]``; transposed: the strided pairs reversed, same ``t``).
"""

from __future__ import annotations


import numpy as np
import pytest
import torch

from omnilidar.cli import main
from omnilidar.errors import InputError
from omnilidar.interop.lidm import convert_lidm_state, kernel_to_ours
from omnilidar.metrics.extractors.weights import build_model, file_sha, load_extractor
from omnilidar.sparse.conv import SparseConv3d, SparseInverseConv3d, SubMConv3d
from omnilidar.sparse.tensor import SparseTensor

SPVNAS_CS = [32, 32, 64, 128, 256, 256, 128, 96, 96]


# --------------------------------------------------------------------------- torchsparse-side offsets


def ts_offset_odd(t: int) -> tuple[int, int, int]:
    """3x3x3: ``t = (dz+1)*9 + (dy+1)*3 + (dx+1)`` (x fastest)."""
    return (t % 3 - 1, (t // 3) % 3 - 1, t // 9 - 1)


def ts_offset_even(t: int) -> tuple[int, int, int]:
    """2x2x2: ``t = dx*4 + dy*2 + dz`` (z fastest)."""
    return (t // 4, (t // 2) % 2, t % 2)


# --------------------------------------------------------------------------- synthetic SPVNAS state dicts


class _Builder:
    def __init__(self, seed: int):
        self.g = torch.Generator().manual_seed(seed)
        self.state: dict[str, torch.Tensor] = {}

    def rand(self, *shape):
        return torch.randn(*shape, generator=self.g)

    # Magnitudes of a trained network (fan-in scaled), so that activations stay finite.
    def conv(self, name, cin, cout, k):
        scale = (cin * k**3) ** -0.5
        self.state[f"{name}.kernel"] = scale * (self.rand(cin, cout) if k == 1 else self.rand(k**3, cin, cout))

    def bn(self, name, c):
        self.state.update({f"{name}.weight": 1 + 0.1 * self.rand(c), f"{name}.bias": 0.1 * self.rand(c),
                           f"{name}.running_mean": 0.1 * self.rand(c), f"{name}.running_var": 1 + self.rand(c).abs(),
                           f"{name}.num_batches_tracked": torch.tensor(1234)})

    def linear(self, name, cin, cout):
        self.state.update({f"{name}.weight": cin**-0.5 * self.rand(cout, cin), f"{name}.bias": 0.1 * self.rand(cout)})

    def basic(self, name, cin, cout, k):  # Basic(De)ConvolutionBlock
        self.conv(f"{name}.net.0", cin, cout, k)
        self.bn(f"{name}.net.1", cout)

    def residual(self, name, cin, cout):
        self.conv(f"{name}.net.0", cin, cout, 3)
        self.bn(f"{name}.net.1", cout)
        self.conv(f"{name}.net.3", cout, cout, 3)
        self.bn(f"{name}.net.4", cout)
        if cin != cout:
            self.conv(f"{name}.downsample.0", cin, cout, 1)
            self.bn(f"{name}.downsample.1", cout)


def spvnas_state(point_transforms: bool, cr: float = 0.5, num_classes: int = 20, seed: int = 0) -> dict:
    cs = [int(cr * x) for x in SPVNAS_CS]
    b = _Builder(seed)
    b.conv("stem.0", 4, cs[0], 3)
    b.bn("stem.1", cs[0])
    b.conv("stem.3", cs[0], cs[0], 3)
    b.bn("stem.4", cs[0])
    for s in range(1, 5):
        b.basic(f"stage{s}.0", cs[s - 1], cs[s - 1], 2)
        b.residual(f"stage{s}.1", cs[s - 1], cs[s])
        b.residual(f"stage{s}.2", cs[s], cs[s])
    for u, skip in zip(range(1, 5), (cs[3], cs[2], cs[1], cs[0])):
        b.basic(f"up{u}.0", cs[3 + u], cs[4 + u], 2)
        b.residual(f"up{u}.1.0", cs[4 + u] + skip, cs[4 + u])
        b.residual(f"up{u}.1.1", cs[4 + u], cs[4 + u])
    b.linear("classifier.0", cs[8], num_classes)
    if point_transforms:
        for i, (cin, cout) in enumerate(((cs[0], cs[4]), (cs[4], cs[6]), (cs[6], cs[8]))):
            b.linear(f"point_transforms.{i}.0", cin, cout)
            b.bn(f"point_transforms.{i}.1", cout)
    return b.state


@pytest.fixture(scope="module")
def spvcnn_state() -> dict:
    return spvnas_state(point_transforms=True)


@pytest.fixture(scope="module")
def minkunet_state() -> dict:
    return spvnas_state(point_transforms=False, seed=1)


# --------------------------------------------------------------------------- kernel order


def _tensor(coords, feats, shape=(8, 8, 8)) -> SparseTensor:
    c = torch.tensor([[0, *p] for p in coords], dtype=torch.int32)
    return SparseTensor(torch.as_tensor(feats, dtype=torch.float64), c, shape, 1)


@pytest.mark.parametrize("t", range(8))
def test_strided_kernel_with_one_offset_hits_the_torchsparse_voxel(t):
    """One input voxel, a 2x2x2 stride-2 kernel with only offset t non-zero: the
    coarse voxel o = p // 2 receives the input exactly when p == 2 o + offset_t."""
    kernel = torch.zeros(8, 1, 1, dtype=torch.float64)
    kernel[t] = 1.0
    conv = SparseConv3d(1, 1, 2, 2).double()
    with torch.no_grad():
        conv.weight.copy_(kernel_to_ours(kernel, 2))
    for parity in np.ndindex(2, 2, 2):
        p = (2 + parity[0], 4 + parity[1], 6 + parity[2])
        with torch.no_grad():
            out = conv(_tensor([p], [[5.0]]))
        assert out.coords.tolist() == [[0, 1, 2, 3]]
        expected = 5.0 if parity == ts_offset_even(t) else 0.0
        assert float(out.feats[0, 0]) == expected


@pytest.mark.parametrize("t", [0, 4, 13, 17, 26])
def test_submanifold_kernel_with_one_offset_reads_the_torchsparse_neighbour(t):
    """A full 3x3x3 block, only offset t non-zero: every voxel i reads x[i + offset_t]."""
    kernel = torch.zeros(27, 1, 1, dtype=torch.float64)
    kernel[t] = 1.0
    conv = SubMConv3d(1, 1, 3).double()
    with torch.no_grad():
        conv.weight.copy_(kernel_to_ours(kernel, 3))
    coords = [tuple(3 + np.array(d) - 1) for d in np.ndindex(3, 3, 3)]
    value = {p: float(i + 1) for i, p in enumerate(coords)}
    with torch.no_grad():
        out = conv(_tensor(coords, [[value[p]] for p in coords]))
    off = ts_offset_odd(t)
    for row, p in enumerate(coords):
        src = tuple(int(a + b) for a, b in zip(p, off))
        assert float(out.feats[row, 0]) == value.get(src, 0.0)


def test_random_kernels_match_torchsparse_sums_for_all_layer_types():
    """Random channels (C_in != C_out) through submanifold, strided and transposed convs."""
    g = torch.Generator().manual_seed(0)
    cin, cmid, cout = 3, 4, 2
    coords = [tuple(int(v) for v in c) for c in torch.randint(0, 6, (40, 3), generator=g).unique(dim=0)]
    x = torch.randn(len(coords), cin, generator=g, dtype=torch.float64)
    k3 = torch.randn(27, cin, cmid, generator=g, dtype=torch.float64)
    k2 = torch.randn(8, cmid, cmid, generator=g, dtype=torch.float64)
    k2t = torch.randn(8, cmid, cout, generator=g, dtype=torch.float64)
    subm, down = SubMConv3d(cin, cmid, 3).double(), SparseConv3d(cmid, cmid, 2, 2, indice_key="d").double()
    up = SparseInverseConv3d(cmid, cout, 2, indice_key="d").double()
    with torch.no_grad():
        subm.weight.copy_(kernel_to_ours(k3, 3))
        down.weight.copy_(kernel_to_ours(k2, 2))
        up.weight.copy_(kernel_to_ours(k2t, 2))
    with torch.no_grad():
        y1 = subm(_tensor(coords, x))
        y2 = down(y1)
        y3 = up(y2)

    index = {p: i for i, p in enumerate(coords)}
    ref1 = torch.zeros(len(coords), cmid, dtype=torch.float64)
    for i, p in enumerate(coords):
        for t in range(27):
            q = tuple(a + b for a, b in zip(p, ts_offset_odd(t)))
            if q in index:
                ref1[i] += x[index[q]] @ k3[t]
    torch.testing.assert_close(y1.feats, ref1)

    coarse = [tuple(c[1:]) for c in y2.coords.tolist()]
    assert sorted(coarse) == sorted({tuple(v // 2 for v in p) for p in coords})
    ref2 = torch.zeros(len(coarse), cmid, dtype=torch.float64)
    for j, o in enumerate(coarse):
        for t in range(8):
            q = tuple(2 * a + b for a, b in zip(o, ts_offset_even(t)))
            if q in index:
                ref2[j] += ref1[index[q]] @ k2[t]
    torch.testing.assert_close(y2.feats, ref2)

    ref3 = torch.zeros(len(coords), cout, dtype=torch.float64)
    for j, o in enumerate(coarse):
        for t in range(8):
            q = tuple(2 * a + b for a, b in zip(o, ts_offset_even(t)))
            if q in index:
                ref3[index[q]] += y2.feats[j] @ k2t[t]
    assert [tuple(c[1:]) for c in y3.coords.tolist()] == coords
    torch.testing.assert_close(y3.feats, ref3)


def test_one_by_one_kernel_is_transposed():
    k = torch.arange(6.0).reshape(2, 3)  # (C_in, C_out)
    w = kernel_to_ours(k, 1)
    assert w.shape == (3, 1, 1, 1, 2)
    x = torch.tensor([[1.0, -2.0]])
    torch.testing.assert_close(x @ w.reshape(3, 2).T, x @ k)


# --------------------------------------------------------------------------- whole networks


@pytest.mark.parametrize("kind", ["fsvd", "fpvd"])
def test_spvnas_layout_converts_and_loads_strictly(kind, spvcnn_state, minkunet_state):
    # SPVNAS's MinkUNet also defines (unused) point_transforms: an FSVD file may carry them.
    state = dict(spvcnn_state)
    state["criterion.ce_loss.weight"] = torch.ones(20)  # 2DPASS's Lightning module
    ours, arch = convert_lidm_state(state, kind, "x.ckpt")
    assert arch == {"width": "W16", "depth": 18, "num_classes": 20}
    model = build_model(kind, arch)
    model.load_state_dict(ours, strict=True)
    sd = model.state_dict()
    torch.testing.assert_close(sd["classifier.weight"], state["classifier.0.weight"])
    torch.testing.assert_close(sd["trunk.fuse.0.0.shortcut.1.running_var"], state["up1.1.0.downsample.1.running_var"])
    torch.testing.assert_close(sd["trunk.encoder.2.1.0.shortcut.0.weight"].reshape(64, 32).T,
                               state["stage3.1.downsample.0.kernel"])
    assert int(sd["trunk.stem.1.1.num_batches_tracked"]) == 1234
    if kind == "fpvd":
        torch.testing.assert_close(sd["point_mlps.2.1.weight"], state["point_transforms.2.1.weight"])
    # LiDM's own MinkowskiNet has no point_transforms at all.
    ours2, _ = convert_lidm_state(minkunet_state, "fsvd", "m.ckpt")
    build_model("fsvd", arch).load_state_dict(ours2, strict=True)


class _HParams(dict):
    """Stands for the config object a Lightning checkpoint pickles (EasyDict-like:
    items and attributes)."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.__dict__.update(kwargs)


CALLS: list = []


def _side_effect(*args):
    CALLS.append(args)


class _Evil:
    def __reduce__(self):
        return (_side_effect, ("executed",))


def test_lidm_checkpoint_file_loads_directly_with_official_tag(tmp_path, spvcnn_state, synthetic_sweep):
    path = tmp_path / "model.ckpt"
    torch.save({"state_dict": {f"module.{k}": v for k, v in spvcnn_state.items()}, "epoch": 63,
                "hyper_parameters": _HParams(cr=0.5), "callbacks": {"x": _Evil()}}, path)
    loaded = load_extractor("fpvd", path)
    assert not CALLS  # nothing in the file ran
    assert loaded.weights == f"official:{file_sha(path)}"
    assert loaded.arch["width"] == "W16" and loaded.comparable_with_paper
    pts = synthetic_sweep.points[::200]
    feats = loaded.extract({"points": [pts]})
    assert feats.shape == (1, 16 * 48) and np.isfinite(feats).all() and np.abs(feats).sum() > 0


def test_cli_writes_our_layout(tmp_path, minkunet_state, capsys):
    src, dst = tmp_path / "model.ckpt", tmp_path / "out" / "fsvd.pt"
    torch.save({"state_dict": minkunet_state}, src)
    assert main(["convert-extractor-weights", "--kind", "fsvd", "--in", str(src), "--out", str(dst)]) == 0
    state = torch.load(dst, weights_only=True)
    assert "trunk.stem.0.0.weight" in state and not any(k.endswith(".kernel") for k in state)
    loaded = load_extractor("fsvd", dst)  # our layout, loaded as is
    assert loaded.arch["width"] == "W16" and loaded.weights == f"official:{file_sha(dst)}"
    assert [p.name for p in dst.parent.iterdir()] == ["fsvd.pt"]  # no temporary left behind
    # An SPVCNN conversion of a MinkowskiNet file lacks the point MLPs.
    assert main(["convert-extractor-weights", "--kind", "fpvd", "--in", str(src), "--out", str(tmp_path / "b.pt")]) == 2
    assert "missing key 'point_transforms.0.0.weight'" in capsys.readouterr().err
    assert not (tmp_path / "b.pt").exists()


# --------------------------------------------------------------------------- bad input


def _without(state, key):
    return {k: v for k, v in state.items() if k != key}


@pytest.mark.parametrize("edit, message", [
    (lambda s: _without(s, "stage2.1.net.3.kernel"), "missing key 'stage2.1.net.3.kernel'"),
    (lambda s: _without(s, "stem.0.kernel"), "missing key 'stem.0.kernel'"),
    (lambda s: {**s, "stage3.2.net.3.kernel": torch.zeros(8, 64, 64)},
     r"'stage3.2.net.3.kernel' has shape \(8, 64, 64\)"),
    (lambda s: {**s, "up2.1.0.net.1.running_mean": torch.zeros(5)}, "'up2.1.0.net.1.running_mean' has shape"),
    (lambda s: {**s, "stage4.3.net.0.kernel": torch.zeros(27, 128, 128)}, "unexpected key 'stage4.3.net.0.kernel'"),
    (lambda s: {**s, "classifier.0.bias": torch.full((20,), float("nan"))}, "NaN"),
])
def test_bad_state_dicts_are_input_errors(minkunet_state, edit, message):
    with pytest.raises(InputError, match=message) as err:
        convert_lidm_state(edit(minkunet_state), "fsvd", "weights/model.ckpt")
    assert str(err.value).startswith("weights/model.ckpt: ")


def test_unsupported_width_and_input_channels_are_refused():
    with pytest.raises(InputError, match=r"channel widths \[20, 20, 40, 81, 163, 163, 81, 61, 61\]"):
        convert_lidm_state(spvnas_state(True, cr=0.64), "fpvd", "spvnas.pt")
    state = spvnas_state(False, seed=2)
    state["stem.0.kernel"] = torch.zeros(27, 3, 16)
    with pytest.raises(InputError, match="3 input channels"):
        convert_lidm_state(state, "fsvd", "x.pt")


def test_bad_files_are_input_errors(tmp_path):
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="weights-only"):
        load_extractor("fsvd", junk)
    empty = tmp_path / "empty.ckpt"
    torch.save({"epoch": 3, "state_dict": {}}, empty)
    with pytest.raises(InputError, match="no state dict"):
        load_extractor("fsvd", empty)
