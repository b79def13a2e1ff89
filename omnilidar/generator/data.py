"""Range-image training data and the three training strategies' batch samplers.

Data contract (written by the domain builder): a domains index JSON
``{"domains": {name: {"id": int, "shards": [dir, ...]}}}``; every ``*.npz`` under a
shard directory (recursively, sorted) holds one scan as key ``"image"``, a (2, H, W)
float32 array in [-1, 1]. Relative shard paths are resolved against the index's
directory first, then the working directory.

Batch samplers (all infinite, deterministic for a seed, and yielding *global*
batches of ``(scan_index, prompt_index)`` pairs, of which each DDP rank takes
its ``rank::world_size`` slice):

- :class:`CDTSBatchSampler` (cross-domain training strategy): mixed batches drawn
  from the concatenated training set, one shuffled pass after another, so domains
  appear in their empirical proportions;
- :class:`BatchHomogeneousSampler`: every batch comes from one domain, chosen with
  probability proportional to its size, scans drawn without replacement per domain;
- :class:`SingleDomainSampler`: only one domain's scans.

The prompt index is drawn per scan uniformly from its domain's pool. Resuming at
iteration k: ``skip=k`` makes the first k batches empty lists (no data is read for
them), which is what mmengine's loop discards when it fast-forwards the loader.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from omnilidar.errors import InputError
from omnilidar.io.json_file import read_json


def rng_for(*keys: int) -> np.random.Generator:
    """An independent generator for a tuple of integer keys (seed, stream, ...)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(k) & 0xFFFFFFFF for k in keys])))


def read_domains_index(path: str | Path) -> dict[str, dict]:
    """Parse the domains index; return {name: {"id": int, "files": [Path, ...], "shard_dirs": [Path, ...]}}
    sorted by id."""
    path = Path(path)
    index = read_json(path, "domains index not found")
    domains = index.get("domains") if isinstance(index, dict) else None
    if not isinstance(domains, dict) or not domains:
        raise InputError(path, 'expected {"domains": {name: {"id": int, "shards": [...]}}} with at least one domain')
    ids = {}
    for name, entry in domains.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("id"), int) or not isinstance(entry.get("shards"), list):
            raise InputError(path, f"domain {name}: needs an integer 'id' and a list 'shards'")
        if entry["id"] < 0:
            raise InputError(path, f"domain {name}: negative id {entry['id']}")
        if entry["id"] in ids:
            raise InputError(path, f"domains {ids[entry['id']]} and {name} share id {entry['id']}")
        ids[entry["id"]] = name
    out = {}
    for name, entry in domains.items():
        files, shard_dirs = [], []
        for shard in entry["shards"]:
            shard_dir = Path(shard)
            if not shard_dir.is_absolute() and (path.parent / shard_dir).is_dir():
                shard_dir = path.parent / shard_dir
            if not shard_dir.is_dir():
                raise InputError(path, f"domain {name}: shard directory {shard} not found")
            files.extend(sorted(shard_dir.rglob("*.npz")))
            shard_dirs.append(shard_dir)
        if not files:
            raise InputError(path, f"domain {name}: no .npz range images under its shards")
        out[name] = {"id": entry["id"], "files": files, "shard_dirs": shard_dirs}
        if isinstance(entry.get("range_image"), dict):  # the geometry the builder used
            out[name]["range_image"] = entry["range_image"]
    return dict(sorted(out.items(), key=lambda kv: kv[1]["id"]))


def load_range_image(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read one (2, H, W) float32 training image; check shape, finiteness and range."""
    path = Path(path)
    try:
        with np.load(path) as data:
            if "image" not in data:
                raise InputError(path, f"no 'image' array (keys: {sorted(data.files)})")
            img = np.asarray(data["image"], dtype=np.float32)
    except InputError:
        raise
    except Exception as err:  # zipfile / pickle errors from a corrupt file
        raise InputError(path, f"cannot read range image: {err}") from None
    if img.ndim != 3 or img.shape[0] != 2:
        raise InputError(path, f"image must be (2, H, W), got {img.shape}")
    if shape is not None and img.shape[1:] != tuple(shape):
        raise InputError(path, f"image is {img.shape[1]}x{img.shape[2]}, the generator expects {shape[0]}x{shape[1]}")
    if not np.isfinite(img).all():
        raise InputError(path, "image has NaN or infinite values")
    if img.min() < -1.0 - 1e-4 or img.max() > 1.0 + 1e-4:
        raise InputError(path, f"image values {img.min():.3f}..{img.max():.3f} outside [-1, 1]")
    return np.clip(img, -1.0, 1.0)


class RangeImageDataset(torch.utils.data.Dataset):
    """All scans of all domains, concatenated in domain-id order; items are read lazily.

    ``dataset[(scan_index, prompt_index)]`` -> {"image", "domain", "prompt"}, where
    ``domain`` is the *position* of the scan's domain in ``domain_names`` (the model's
    domain index) and ``prompt`` the global row of its prompt in the stacked table.
    """

    def __init__(self, domains: dict[str, dict], shape: tuple[int, int], prompt_spans: dict[str, tuple[int, int]]):
        self.domain_names = list(domains)
        self.shape = tuple(shape)
        self.files: list[Path] = []
        self.domain_of: list[int] = []
        for pos, name in enumerate(self.domain_names):
            self.files.extend(domains[name]["files"])
            self.domain_of.extend([pos] * len(domains[name]["files"]))
        self.domain_of_arr = np.asarray(self.domain_of, dtype=np.int64)
        self.prompt_offset = np.asarray([prompt_spans[n][0] for n in self.domain_names], dtype=np.int64)
        self.prompt_count = np.asarray([prompt_spans[n][1] for n in self.domain_names], dtype=np.int64)

    def __len__(self) -> int:
        return len(self.files)

    def indices_of(self, domain_pos: int) -> np.ndarray:
        return np.flatnonzero(self.domain_of_arr == domain_pos)

    def domain_means(self, max_scans: int = 512) -> torch.Tensor:
        """(num_domains, 2, H, W) per-pixel mean of each domain's training images (float64 sums),
        over at most ``max_scans`` evenly spaced scans per domain (a dataset-scale domain's mean
        is settled long before its 20k scans are read)."""
        means = []
        for pos in range(len(self.domain_names)):
            total = np.zeros((2, *self.shape), dtype=np.float64)
            scans = self.indices_of(pos)
            if len(scans) > max_scans:
                scans = scans[np.linspace(0, len(scans) - 1, max_scans).round().astype(np.int64)]
            for scan in scans:
                total += load_range_image(self.files[scan], self.shape)
            means.append(total / max(len(scans), 1))
        return torch.from_numpy(np.stack(means)).float()

    def __getitem__(self, key) -> dict:
        scan, prompt = key
        img = load_range_image(self.files[scan], self.shape)
        d = int(self.domain_of_arr[scan])
        return {
            "image": torch.from_numpy(img),
            "domain": d,
            "prompt": int(self.prompt_offset[d] + prompt),
        }


def collate(items: list[dict]) -> dict:
    """Stack items into {"image": (B,2,H,W), "domain": (B,), "prompt": (B,)}; {} for a skipped batch."""
    if not items:
        return {}
    return {
        "image": torch.stack([it["image"] for it in items]),
        "domain": torch.tensor([it["domain"] for it in items], dtype=torch.long),
        "prompt": torch.tensor([it["prompt"] for it in items], dtype=torch.long),
    }


class _BatchSampler(torch.utils.data.Sampler):
    def __init__(self, dataset: RangeImageDataset, batch_size: int, seed: int, rank: int = 0, world_size: int = 1, skip: int = 0):
        if batch_size < 1:
            raise ValueError("batch_size must be >= 1")
        if batch_size % world_size:
            raise ValueError(f"global batch {batch_size} does not split over {world_size} processes")
        self.dataset, self.batch_size, self.seed = dataset, batch_size, seed
        self.rank, self.world_size, self.skip = rank, world_size, skip

    def _global_batches(self, rng: np.random.Generator):  # pragma: no cover
        raise NotImplementedError

    def _with_prompts(self, scans: np.ndarray, rng: np.random.Generator) -> list[tuple[int, int]]:
        counts = self.dataset.prompt_count[self.dataset.domain_of_arr[scans]]
        prompts = rng.integers(0, counts)
        return [(int(s), int(p)) for s, p in zip(scans, prompts)]

    def __iter__(self):
        rng = rng_for(self.seed, 0x5A3D)
        for k, batch in enumerate(self._global_batches(rng)):
            items = self._with_prompts(batch, rng)
            yield [] if k < self.skip else items[self.rank :: self.world_size]

    def __len__(self) -> int:  # infinite; a large number keeps DataLoader's length queries happy
        return 2**62


class CDTSBatchSampler(_BatchSampler):
    """Mixed-domain batches from the concatenated set (empirical domain proportions)."""

    def _pool(self) -> np.ndarray:
        return np.arange(len(self.dataset))

    def _global_batches(self, rng):
        pool = self._pool()
        stream = np.empty(0, dtype=np.int64)
        while True:
            while len(stream) < self.batch_size:
                stream = np.concatenate([stream, rng.permutation(pool)])
            yield stream[: self.batch_size]
            stream = stream[self.batch_size :]


class SingleDomainSampler(CDTSBatchSampler):
    """Batches from one domain only (``domain`` is its position in ``dataset.domain_names``)."""

    def __init__(self, dataset, batch_size, seed, domain: int, **kw):
        super().__init__(dataset, batch_size, seed, **kw)
        self.domain = domain
        if len(dataset.indices_of(domain)) == 0:
            raise InputError(None, f"single-domain training: domain {dataset.domain_names[domain]} has no scans")

    def _pool(self) -> np.ndarray:
        return self.dataset.indices_of(self.domain)


class BatchHomogeneousSampler(_BatchSampler):
    """Each batch from one domain, chosen with probability proportional to its size."""

    def _global_batches(self, rng):
        n_dom = len(self.dataset.domain_names)
        pools = [self.dataset.indices_of(d) for d in range(n_dom)]
        sizes = np.asarray([len(p) for p in pools], dtype=np.float64)
        probs = sizes / sizes.sum()
        streams = [np.empty(0, dtype=np.int64) for _ in range(n_dom)]
        while True:
            d = int(rng.choice(n_dom, p=probs))
            while len(streams[d]) < self.batch_size:
                streams[d] = np.concatenate([streams[d], rng.permutation(pools[d])])
            yield streams[d][: self.batch_size]
            streams[d] = streams[d][self.batch_size :]


def make_batch_sampler(
    strategy: str,
    dataset: RangeImageDataset,
    batch_size: int,
    seed: int,
    single_domain: str | None = None,
    rank: int = 0,
    world_size: int = 1,
    skip: int = 0,
) -> _BatchSampler:
    """The batch sampler of a training strategy: ``cdts``, ``batch_homogeneous`` or ``single_domain``."""
    kw = dict(rank=rank, world_size=world_size, skip=skip)
    if strategy == "cdts":
        return CDTSBatchSampler(dataset, batch_size, seed, **kw)
    if strategy == "batch_homogeneous":
        return BatchHomogeneousSampler(dataset, batch_size, seed, **kw)
    if strategy == "single_domain":
        if single_domain not in dataset.domain_names:
            raise InputError(None, f"training.single_domain {single_domain!r} is not among {dataset.domain_names}")
        return SingleDomainSampler(dataset, batch_size, seed, dataset.domain_names.index(single_domain), **kw)
    raise InputError(None, f"unknown training strategy {strategy!r} (cdts, batch_homogeneous, single_domain)")
