"""LiDM's torchsparse MinkowskiNet / SPVCNN weights in this package's MinkUNet / SPVCNN layout.

LiDM (hancyran/LiDAR-Diffusion, ``lidm/eval``) computes FSVD with a
MinkowskiNet and FPVD with an SPVCNN written for torchsparse 1.4 (the SPVNAS
model definitions, via 2DPASS). Their state dicts differ from ours in three ways,
all handled here:

* **names** -- ``stem.{0,1,3,4}``, ``stage{1..4}.{0,1,2}``, ``up{1..4}.{0,1}``,
  ``classifier.0``, ``point_transforms.{0,1,2}`` (SPVCNN) against our
  ``trunk.stem``, ``trunk.encoder``, ``trunk.up`` / ``trunk.fuse``,
  ``classifier``, ``point_mlps`` (:func:`key_map` lists every pair);
* **kernel layout** -- a torchsparse ``Conv3d`` holds ``kernel`` of shape
  ``(K, C_in, C_out)`` (``(C_in, C_out)`` when K = 1) where ours holds
  ``weight`` ``(C_out, kx, ky, kz, C_in)``. A transposed conv keeps the same
  shape, ``C_in`` being its own (coarse) input;
* **kernel-offset order** -- torchsparse's ``get_kernel_offsets`` (identical in
  1.4.0, 2.0.0 and 2.1) enumerates an odd kernel **x fastest**
  (``t = (dz+1)*9 + (dy+1)*3 + (dx+1)`` for 3x3x3, offsets -1..1) and an even
  kernel **z fastest** (``t = dx*4 + dy*2 + dz``, offsets 0..1). A layer adds
  ``x[o + offset_t] @ W[t]`` to output ``o`` (submanifold: same coordinates;
  stride 2: ``o`` on the coarse grid, input at ``2 o + offset_t``), and its
  transposed conv reuses that strided kernel map with inputs and outputs
  swapped and the same index ``t`` (torchsparse 2.x's ``transpose_kernel_map``
  keeps ``t`` too). Ours is the same cross-correlation with offsets flattened
  x-major (:func:`omnilidar.sparse.kernel_map.kernel_offsets`), so 3x3x3
  kernels are permuted and 2x2x2 kernels keep their order.

BatchNorm (``torchsparse.nn.BatchNorm`` is ``torch.nn.BatchNorm1d``) and the
Linear layers keep their tensors; a missing ``num_batches_tracked`` (older
PyTorch) becomes 0.

Checkpoint files. LiDM's ``build_model`` reads ``model.ckpt`` with
``torch.load`` and takes ``ckpt['state_dict']`` (loaded with ``strict=False``);
its ``config.yaml`` (``model_params``: ``cr``, ``layer_num``, ``num_class``,
``input_dims``, ``voxel_size``) is read separately. SPVNAS's model zoo stores
``{'model': state}``. Accepted here: the state dict itself or under
``state_dict`` / ``model``, with an optional ``module.`` (DistributedDataParallel)
prefix. A PyTorch Lightning checkpoint (2DPASS trains that way) may pickle
classes that a weights-only load refuses (its hyper-parameters); those are
replaced by inert stand-ins -- nothing in the file is imported or executed.
Keys of 2DPASS's Lightning module that are not part of the network
(``criterion.*``, ``train_acc.*``, ``val_acc.*``, ``val_iou.*``) and SPVNAS
MinkUNet's ``point_transforms.*`` (defined but never used by its forward) are
dropped; any other unknown key is refused.

Not established (the files are Google-Drive downloads, unreachable here):
LiDM's exact key names, ``cr`` and class count. Their published configs point
to 2DPASS's defaults (``cr: 1``, i.e. W32, ``num_class: 20``, ``input_dims: 4``);
this converter infers widths, classes and input channels from the tensor
shapes, so any ``cr`` whose widths match a MinkUNet preset (cr 0.5 = W16,
0.625 = W20, 1.0 = W32) converts; others (e.g. SPVNAS's cr 0.64) are refused
with the widths found.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import torch

from omnilidar.errors import InputError
from omnilidar.io.atomic import atomic_path
from omnilidar.segnets.build import build_segmentor
from omnilidar.segnets.minkunet import WIDTHS

KINDS = ("fsvd", "fpvd")
# Keys of a training wrapper, not of the network: dropped silently.
IGNORED_PREFIXES = ("criterion.", "train_acc.", "val_acc.", "val_iou.")
# SPVNAS's MinkUNet builds SPVCNN's point MLPs but never calls them.
UNUSED_IN_MINKUNET = "point_transforms."
_BN_TENSORS = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
_STATE_KEYS = ("state_dict", "model")


# --------------------------------------------------------------------------- kernels


def torchsparse_offsets(kernel_size: int) -> torch.Tensor:
    """``(K, 3)`` kernel positions (0..k-1 per axis, x y z) in torchsparse's weight order.

    Odd kernels run x fastest, even kernels z fastest (torchsparse keeps the
    odd order compatible with MinkowskiEngine).
    """
    r = torch.arange(kernel_size)
    gx, gy, gz = torch.meshgrid(r, r, r, indexing="ij")
    pos = torch.stack([gx, gy, gz], -1)  # pos[x, y, z] = (x, y, z)
    if kernel_size % 2 == 1:
        pos = pos.permute(2, 1, 0, 3)  # z major, x minor
    return pos.reshape(-1, 3)


def kernel_to_ours(kernel: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """A torchsparse ``kernel`` ``(K, C_in, C_out)`` (or ``(C_in, C_out)`` for K = 1)
    as our ``weight`` ``(C_out, k, k, k, C_in)``; the same for transposed convs."""
    if kernel_size == 1:
        return kernel.T.reshape(kernel.shape[1], 1, 1, 1, kernel.shape[0]).contiguous()
    k = kernel_size
    c_in, c_out = kernel.shape[1], kernel.shape[2]
    pos = torchsparse_offsets(k)
    out = kernel.new_zeros((c_out, k, k, k, c_in))
    out[:, pos[:, 0], pos[:, 1], pos[:, 2], :] = kernel.permute(2, 0, 1)
    return out


def ours_to_kernel_shape(weight_shape: torch.Size) -> tuple[int, ...]:
    """The torchsparse kernel shape of one of our conv weights."""
    c_out, kx, ky, kz, c_in = weight_shape
    volume = kx * ky * kz
    return (c_in, c_out) if volume == 1 else (volume, c_in, c_out)


# --------------------------------------------------------------------------- key map


def _bn(ts: str, ours: str) -> list[tuple[str, str, str]]:
    return [(f"{ts}.{t}", f"{ours}.{t}", "bn") for t in _BN_TENSORS]


def _conv(ts: str, ours: str, k: int) -> list[tuple[str, str, str]]:
    return [(f"{ts}.kernel", f"{ours}.weight", f"conv{k}")]


def _residual(ts: str, ours: str, shortcut: bool) -> list[tuple[str, str, str]]:
    out = _conv(f"{ts}.net.0", f"{ours}.body.0", 3) + _bn(f"{ts}.net.1", f"{ours}.body.1")
    out += _conv(f"{ts}.net.3", f"{ours}.body.3", 3) + _bn(f"{ts}.net.4", f"{ours}.body.4")
    if shortcut:
        out += _conv(f"{ts}.downsample.0", f"{ours}.shortcut.0", 1) + _bn(f"{ts}.downsample.1", f"{ours}.shortcut.1")
    return out


def key_map(kind: str, widths: list[int]) -> list[tuple[str, str, str]]:
    """Every ``(torchsparse key, our key, tensor type)`` of a network with channel
    list ``widths`` (torchsparse's ``cs``: stem, 4 encoder, 4 decoder widths).

    Types: ``conv3`` / ``conv2`` / ``conv1`` (kernel size), ``bn``, ``linear``.
    Residual blocks have a 1x1x1 ``downsample`` exactly when their widths differ.
    """
    cs = widths
    m = []
    m += _conv("stem.0", "trunk.stem.0.0", 3) + _bn("stem.1", "trunk.stem.0.1")
    m += _conv("stem.3", "trunk.stem.1.0", 3) + _bn("stem.4", "trunk.stem.1.1")
    for s in range(1, 5):
        ours = f"trunk.encoder.{s - 1}"
        m += _conv(f"stage{s}.0.net.0", f"{ours}.0.0", 2) + _bn(f"stage{s}.0.net.1", f"{ours}.0.1")
        m += _residual(f"stage{s}.1", f"{ours}.1.0", cs[s - 1] != cs[s])
        m += _residual(f"stage{s}.2", f"{ours}.1.1", False)
    skips = (cs[3], cs[2], cs[1], cs[0])
    for u in range(1, 5):
        d = u - 1
        m += _conv(f"up{u}.0.net.0", f"trunk.up.{d}.0", 2) + _bn(f"up{u}.0.net.1", f"trunk.up.{d}.1")
        m += _residual(f"up{u}.1.0", f"trunk.fuse.{d}.0", cs[4 + u] + skips[d] != cs[4 + u])
        m += _residual(f"up{u}.1.1", f"trunk.fuse.{d}.1", False)
    m += [("classifier.0.weight", "classifier.weight", "linear"), ("classifier.0.bias", "classifier.bias", "linear")]
    if kind == "fpvd":
        for i in range(3):
            m += [(f"point_transforms.{i}.0.{t}", f"point_mlps.{i}.0.{t}", "linear") for t in ("weight", "bias")]
            m += _bn(f"point_transforms.{i}.1", f"point_mlps.{i}.1")
    return m


# --------------------------------------------------------------------------- files


def looks_like_torchsparse(state: dict) -> bool:
    """True for an SPVNAS/LiDM torchsparse layout (``stem.0.kernel``), False for ours."""
    return "stem.0.kernel" in state


def unwrap_state(obj, where) -> dict[str, torch.Tensor]:
    """The state dict inside a loaded checkpoint: itself, or under ``state_dict`` /
    ``model``; a ``module.`` prefix on every key is removed."""
    if isinstance(obj, dict):
        for key in _STATE_KEYS:
            if isinstance(obj.get(key), dict):
                obj = obj[key]
                break
    if not isinstance(obj, dict) or not obj:
        raise InputError(where, "no state dict found (expected names -> tensors, or one under "
                                "'state_dict' or 'model')")
    bad = next((k for k, v in obj.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)), None)
    if bad is not None:
        raise InputError(where, f"state dict entry {bad!r} is not a tensor")
    state = dict(obj)
    if all(k.startswith("module.") for k in state):
        state = {k[len("module."):]: v for k, v in state.items()}
    return state


class _StandIn:
    """Inert placeholder for a class or function a weights-only load does not know.

    "Constructing" or "calling" it yields an empty ``OrderedDict`` (the one type
    the weights-only unpickler lets both fill with items and give attributes),
    so the object's data survive as plain data and no code named in the file runs.
    """

    def __new__(cls, *args, **kwargs):
        return OrderedDict()


def _stand_in(name: str) -> tuple[type, str]:
    return type(name.rsplit(".", 1)[-1], (_StandIn,), {"__module__": "omnilidar.standin"}), name


def load_checkpoint(path: str | Path):
    """``torch.load(weights_only=True)`` of ``path``; classes it refuses (the
    hyper-parameters of a Lightning checkpoint, say) become inert stand-ins."""
    path = Path(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # refused globals, or not a torch file at all
        first = err
    try:
        names = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:
        names = []
    if not names:
        raise InputError(path, f"not a weights-only loadable file: {str(first)[:300]}") from None
    try:
        with torch.serialization.safe_globals([_stand_in(n) for n in names]):
            return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise InputError(path, f"not a weights-only loadable file: {str(err)[:300]}") from None


# --------------------------------------------------------------------------- conversion


def _need(state: dict, key: str, where, dims: int) -> torch.Tensor:
    if key not in state:
        raise InputError(where, f"not a LiDM/SPVNAS torchsparse state dict: missing key {key!r}")
    t = state[key]
    if t.dim() != dims:
        raise InputError(where, f"key {key!r} has shape {tuple(t.shape)}, expected {dims} dimensions")
    return t


def infer_arch(state: dict, kind: str, where) -> tuple[dict, list[int]]:
    """Our architecture dict and torchsparse's channel list ``cs`` from the shapes."""
    stem = _need(state, "stem.0.kernel", where, 3)
    cs = [int(stem.shape[2])]
    cs += [int(_need(state, f"stage{s}.1.net.0.kernel", where, 3).shape[2]) for s in range(1, 5)]
    cs += [int(_need(state, f"up{u}.0.net.0.kernel", where, 3).shape[2]) for u in range(1, 5)]
    if int(stem.shape[1]) != 4:
        raise InputError(where, f"key 'stem.0.kernel' takes {int(stem.shape[1])} input channels; the FSVD/FPVD "
                                "protocol feeds 4 ([x, y, z, -1])")
    classes = int(_need(state, "classifier.0.weight", where, 2).shape[0])
    for name, (s, enc, dec) in WIDTHS.items():
        if cs == [s, *enc, *dec]:
            return {"width": name, "depth": 18, "num_classes": classes}, cs
    presets = ", ".join(f"{n}={[s, *e, *d]}" for n, (s, e, d) in WIDTHS.items())
    raise InputError(where, f"channel widths {cs} match no MinkUNet preset ({presets}); "
                            f"{'MinkowskiNet' if kind == 'fsvd' else 'SPVCNN'} widths of another cr are not supported")


def sparse_extractor(kind: str, arch: dict, generator: torch.Generator | None = None) -> torch.nn.Module:
    """Our FSVD (MinkUNet) or FPVD (SPVCNN) network for ``arch`` (width, depth, num_classes), on
    the protocol's 4 input channels [x, y, z, -1]."""
    return build_segmentor({"backbone": "minkunet" if kind == "fsvd" else "spvcnn", "in_channels": 4,
                            "num_classes": arch.get("num_classes", 19), "width": arch["width"],
                            "depth": arch.get("depth", 18)}, "torch", generator=generator)


def remap_state(state: dict, mapping, expected: dict, their_shape, to_ours, network: str,
                where) -> dict[str, torch.Tensor]:
    """Our state dict from another layout's ``state`` along ``mapping`` ((their key, our key, type));
    ``expected`` is our network's state dict, ``their_shape(our_shape, type)`` the shape a key must
    have there, ``to_ours(tensor, type)`` its conversion. A missing, misshapen or non-finite key
    raises InputError naming ``where`` (``network`` says what should have had it)."""
    out: dict[str, torch.Tensor] = {}
    for theirs, ours, typ in mapping:
        target = expected[ours]
        if theirs not in state:
            if theirs.endswith("num_batches_tracked"):
                out[ours] = torch.zeros((), dtype=torch.long)
                continue
            raise InputError(where, f"missing key {theirs!r} ({network} has it)")
        t = state[theirs]
        want = their_shape(target.shape, typ)
        if tuple(t.shape) != want:
            raise InputError(where, f"key {theirs!r} has shape {tuple(t.shape)}, expected {want}")
        if t.is_floating_point() and not torch.isfinite(t).all():
            raise InputError(where, f"key {theirs!r} contains NaN or Inf")
        out[ours] = to_ours(t.to(target.dtype), typ).clone()
    return out


def convert_lidm_state(state: dict, kind: str, where=None) -> tuple[dict[str, torch.Tensor], dict]:
    """Convert a torchsparse MinkowskiNet (``kind="fsvd"``) or SPVCNN (``"fpvd"``)
    state dict to ours.

    Returns ``(our_state_dict, arch)`` where ``arch`` (``width``, ``depth``,
    ``num_classes``) builds the matching network with
    :func:`sparse_extractor`. Raises
    InputError naming ``where`` and the first unknown, missing or misshapen key.
    """
    if kind not in KINDS:
        raise InputError(where, f"torchsparse weights are FSVD or FPVD extractors, not {kind!r}")

    state = {k: v for k, v in state.items() if not k.startswith(IGNORED_PREFIXES)}
    if kind == "fsvd":
        state = {k: v for k, v in state.items() if not k.startswith(UNUSED_IN_MINKUNET)}
    arch, cs = infer_arch(state, kind, where)
    mapping = key_map(kind, cs)
    known = {ts for ts, _, _ in mapping}
    unknown = sorted(set(state) - known)
    if unknown:
        hint = " (SPVCNN point MLPs in an FSVD file?)" if kind == "fsvd" else ""
        raise InputError(where, f"unexpected key {unknown[0]!r} for a {'MinkowskiNet' if kind == 'fsvd' else 'SPVCNN'}"
                                f" with widths {cs}{hint}")
    def their_shape(ours_shape, typ):
        return ours_to_kernel_shape(ours_shape) if typ.startswith("conv") else tuple(ours_shape)

    def to_ours(t, typ):
        return kernel_to_ours(t, int(typ[4:])) if typ.startswith("conv") else t

    network = f"a {'MinkowskiNet' if kind == 'fsvd' else 'SPVCNN'} with widths {cs}"
    out = remap_state(state, mapping, sparse_extractor(kind, arch).state_dict(), their_shape, to_ours, network, where)
    return out, arch


def read_lidm_file(kind: str, path: str | Path) -> tuple[dict[str, torch.Tensor], dict]:
    """Load a LiDM/SPVNAS torchsparse checkpoint file and convert it (see module doc)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "torchsparse weight file not found")
    state = unwrap_state(load_checkpoint(path), path)
    if not looks_like_torchsparse(state):
        raise InputError(path, "not a torchsparse MinkowskiNet/SPVCNN state dict (no 'stem.0.kernel')")
    return convert_lidm_state(state, kind, path)


def write_converted(kind: str, src: str | Path, dst: str | Path) -> dict:
    """Convert ``src`` and write our plain state dict to ``dst`` atomically; returns the arch.

    The output is checked by loading it strictly into the network first.
    """
    state, arch = read_lidm_file(kind, src)
    sparse_extractor(kind, arch).load_state_dict(state, strict=True)
    with atomic_path(dst) as tmp:
        torch.save(state, tmp)
    return arch
