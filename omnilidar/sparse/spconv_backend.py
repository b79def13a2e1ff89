"""Optional spconv backend: the same layers, computed by spconv 2.x.

The layers subclass the pure-PyTorch ones, so parameters, their names and the
weight layout ``(out, kD, kH, kW, in)`` are identical and checkpoints move
between backends unchanged. Only ``forward`` differs: it wraps our
:class:`SparseTensor` as a ``spconv.SparseConvTensor`` (sharing the kernel-map
cache dict as spconv's ``indice_dict``), runs a spconv layer whose weight is our
parameter, and unwraps the result.

Two fixes make the CPU wheel (``spconv`` 2.3.8) usable for training:

- Every backward asks ``torch.cuda`` for the current stream and fails on a
  CPU-only torch; ``get_current_stream`` is replaced by a function that
  returns 0 (the null stream) when CUDA is unavailable.
- Its submanifold convolution races with more than one OpenMP thread (wrong
  results in a few % of calls). spconv bundles its own libgomp; it is loaded
  with ``OMP_NUM_THREADS=1`` in the environment (read once, when that library
  initialises) and additionally told ``omp_set_num_threads(1)``. PyTorch's own
  thread pool is not affected.

On CUDA (``spconv-cu120``) neither fix changes anything.
"""

from __future__ import annotations

import ctypes
import glob
import os
import sys
import warnings
from pathlib import Path

import torch

from omnilidar.sparse import conv as torch_conv
from omnilidar.sparse.tensor import SparseTensor


class SpconvUnavailable(ImportError):
    """spconv is not installed, cannot be loaded, or computes wrong results here."""


_SPCONV = None
_CHECKED: dict[str, str | None] = {}  # device type -> problem found by self_check (None: fine)


def _current_stream() -> int:
    if torch.cuda.is_available():
        return torch.cuda.current_stream().cuda_stream
    return 0


def _limit_bundled_openmp(package_dir: Path) -> bool:
    """Call omp_set_num_threads(1) in spconv's bundled libgomp; True if found."""
    libs = sorted(glob.glob(str(package_dir.parent / "spconv.libs" / "libgomp*.so*")))
    for lib in libs:
        try:
            ctypes.CDLL(lib).omp_set_num_threads(1)
            return True
        except OSError:
            continue
    return False


def load_spconv():
    """Import ``spconv.pytorch`` with the CPU fixes applied (once); return it.

    Raises :class:`SpconvUnavailable` when spconv cannot be imported.
    """
    global _SPCONV
    if _SPCONV is not None:
        return _SPCONV
    imported_before = "spconv.core_cc" in sys.modules
    previous = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"
    try:
        import spconv.pytorch as sp
        from spconv.pytorch import cppcore, hash as sp_hash, ops
    except Exception as exc:  # ImportError, or a broken binary wheel
        raise SpconvUnavailable(f"spconv is not usable: {exc}") from exc
    finally:
        if previous is None:
            del os.environ["OMP_NUM_THREADS"]
        else:
            os.environ["OMP_NUM_THREADS"] = previous
    for module in (ops, sp_hash, cppcore):
        module.get_current_stream = _current_stream
    import spconv

    limited = _limit_bundled_openmp(Path(spconv.__file__).parent)
    if imported_before and not torch.cuda.is_available():
        warnings.warn(
            "spconv was imported before omnilidar.sparse.spconv_backend; its OpenMP pool may use "
            "several threads (submanifold results can then be wrong on CPU). Set OMP_NUM_THREADS=1.",
            RuntimeWarning,
            stacklevel=2,
        )
    elif not limited and not torch.cuda.is_available():
        warnings.warn("could not find spconv's bundled libgomp to limit its threads", RuntimeWarning, stacklevel=2)
    _SPCONV = sp
    return sp


def self_check(device: str | torch.device = "cpu") -> str | None:
    """Compare spconv with the pure-PyTorch layers on a small random input.

    Runs once per device type (cached). Returns None when submanifold, strided
    and inverse convolutions and their input gradients agree, otherwise a
    one-line description of the first disagreement. (The spconv 2.3.8 CPU wheel
    has been seen to build wrong submanifold kernel maps on some x86 CPUs even
    single-threaded; this check keeps such a build from training silently.)
    """
    device = torch.device(device)
    if device.type in _CHECKED:
        return _CHECKED[device.type]
    try:
        sp = load_spconv()
    except SpconvUnavailable as exc:
        return str(exc)
    gen = torch.Generator().manual_seed(0)
    shape = (6, 7, 5)
    coords = (torch.rand((2, *shape), generator=gen) < 0.35).nonzero().to(torch.int32)
    feats = torch.randn(coords.shape[0], 4, generator=gen)
    layers = [  # (ours, spconv) pairs with identical weights
        (torch_conv.SubMConv3d(4, 6, 3, indice_key="c_subm"), sp.SubMConv3d(4, 6, 3, bias=False, indice_key="c_subm")),
        (torch_conv.SparseConv3d(6, 5, 2, 2, indice_key="c_down"),
         sp.SparseConv3d(6, 5, 2, 2, bias=False, indice_key="c_down")),
        (torch_conv.SparseInverseConv3d(5, 3, 2, indice_key="c_down"),
         sp.SparseInverseConv3d(5, 3, 2, indice_key="c_down", bias=False)),
    ]
    problem = None
    outputs = []
    for backend in (0, 1):
        f = feats.to(device).requires_grad_(True)
        x = SparseTensor(f, coords.to(device), shape, 2)
        st = sp.SparseConvTensor(f, x.coords, list(shape), 2)
        for ours, theirs in layers:
            ours.reset_parameters(torch.Generator().manual_seed(1))
            theirs.to(device)
            theirs.weight.data.copy_(ours.weight.data.to(device))
            if backend == 0:
                x = ours.to(device)(x)
            else:
                st = theirs(st)
        out = x.feats if backend == 0 else st.features
        out.square().sum().backward()
        outputs.append((out.detach().cpu(), f.grad.cpu()))
    (a, ga), (b, gb) = outputs
    if a.shape != b.shape or not torch.allclose(a, b, atol=1e-4, rtol=1e-4):
        problem = "spconv forward disagrees with the reference sparse convolution"
    elif not torch.allclose(ga, gb, atol=1e-4, rtol=1e-4):
        problem = "spconv gradients disagree with the reference sparse convolution"
    _CHECKED[device.type] = problem
    return problem


def require_spconv(device: str | torch.device = "cpu"):
    """Return ``spconv.pytorch`` if it is installed and passes :func:`self_check`."""
    problem = self_check(device)
    if problem is not None:
        raise SpconvUnavailable(f"spconv backend unusable on {torch.device(device).type}: {problem}")
    return load_spconv()


def spconv_available(device: str | torch.device = "cpu") -> bool:
    """True if spconv imports (with the fixes) and passes :func:`self_check`."""
    return self_check(device) is None


class _SpconvMixin:
    """Runs ``self._impl`` (a spconv layer sharing our weight) on our tensors."""

    def _make_impl(self, factory):
        impl = factory()
        # Not registered as a submodule: the state dict holds only our own
        # `weight`/`bias`, and the spconv layer borrows them at call time.
        object.__setattr__(self, "_impl", impl)

    def _run(self, x: SparseTensor, keep_bias: bool = True) -> SparseTensor:
        sp = load_spconv()
        self._check_input(x)
        if x.feats.device.type == "cpu" and x.feats.dtype != torch.float32:
            raise TypeError(f"spconv on CPU supports float32 only, got {x.feats.dtype}")
        impl = self._impl
        impl._parameters["weight"] = self.weight
        impl._parameters["bias"] = self.bias
        st = sp.SparseConvTensor(x.feats, x.coords, list(x.spatial_shape), x.batch_size, indice_dict=x.cache)
        out = impl(st)
        return SparseTensor(out.features, out.indices, tuple(out.spatial_shape), x.batch_size, out.indice_dict)


class SubMConv3d(_SpconvMixin, torch_conv.SubMConv3d):
    """spconv ``SubMConv3d`` with the torch backend's parameters."""

    def __init__(self, in_channels, out_channels, kernel_size=3, stride=1, padding=0, dilation=1,
                 bias=False, indice_key=None):
        super().__init__(in_channels, out_channels, kernel_size, stride, padding, dilation, bias, indice_key)
        sp = load_spconv()
        self._make_impl(lambda: sp.SubMConv3d(
            self.in_channels, self.out_channels, self.kernel_size, 1, self.padding, self.dilation,
            bias=bias, indice_key=indice_key))

    def forward(self, x: SparseTensor) -> SparseTensor:
        return self._run(x)


class SparseConv3d(_SpconvMixin, torch_conv.SparseConv3d):
    """spconv ``SparseConv3d`` with the torch backend's parameters."""

    def __init__(self, in_channels, out_channels, kernel_size=3, stride=1, padding=0, dilation=1,
                 bias=False, indice_key=None):
        super().__init__(in_channels, out_channels, kernel_size, stride, padding, dilation, bias, indice_key)
        sp = load_spconv()
        self._make_impl(lambda: sp.SparseConv3d(
            self.in_channels, self.out_channels, self.kernel_size, self.stride, self.padding, self.dilation,
            bias=bias, indice_key=indice_key))

    def forward(self, x: SparseTensor) -> SparseTensor:
        return self._run(x)


class SparseInverseConv3d(_SpconvMixin, torch_conv.SparseInverseConv3d):
    """spconv ``SparseInverseConv3d`` with the torch backend's parameters."""

    def __init__(self, in_channels, out_channels, kernel_size, indice_key, bias=False):
        super().__init__(in_channels, out_channels, kernel_size, indice_key, bias)
        sp = load_spconv()
        self._make_impl(lambda: sp.SparseInverseConv3d(
            self.in_channels, self.out_channels, self.kernel_size, indice_key=indice_key, bias=bias))

    def forward(self, x: SparseTensor) -> SparseTensor:
        return self._run(x)
