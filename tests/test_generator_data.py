"""Domains index, range-image loading errors, and batch composition of the three strategies."""

from __future__ import annotations

import collections
import json

import numpy as np
import pytest

from omnilidar.errors import InputError
from omnilidar.generator.data import RangeImageDataset, collate, load_range_image, make_batch_sampler, read_domains_index
from test_generator_fixtures import make_domains, one_torch_thread, tiny_settings  # noqa: F401


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    settings = tiny_settings()
    index = make_domains(root, settings, scans_per_domain=(12, 4, 8))
    domains = read_domains_index(index)
    spans = {"Vehicle": (0, 2), "Fog": (2, 1), "Beam32": (3, 3)}
    return RangeImageDataset(domains, (16, 64), spans)


def _take(sampler, n):
    it = iter(sampler)
    return [next(it) for _ in range(n)]


def test_cdts_mixes_domains_in_empirical_proportions(dataset):
    batches = _take(make_batch_sampler("cdts", dataset, 8, seed=0), 30)  # 240 draws = 10 passes of 24 scans
    scans = [s for b in batches for s, _ in b]
    counts = collections.Counter(dataset.domain_of_arr[scans].tolist())
    assert counts == {0: 120, 1: 40, 2: 80}  # exactly 12:4:8 over whole passes
    mixed = sum(len({dataset.domain_of[s] for s, _ in b}) > 1 for b in batches)
    assert mixed >= 25
    # each pass over the data visits every scan once
    assert sorted(scans[:24]) == list(range(24))


def test_batch_homogeneous_batches_are_single_domain_with_size_proportional_choice(dataset):
    batches = _take(make_batch_sampler("batch_homogeneous", dataset, 4, seed=1), 600)
    doms = [{dataset.domain_of[s] for s, _ in b} for b in batches]
    assert all(len(d) == 1 for d in doms)
    freq = collections.Counter(next(iter(d)) for d in doms)
    for d, p in ((0, 0.5), (1, 4 / 24), (2, 8 / 24)):
        assert abs(freq[d] / 600 - p) < 0.06


def test_single_domain_only_draws_that_domain(dataset):
    batches = _take(make_batch_sampler("single_domain", dataset, 4, seed=2, single_domain="Fog"), 10)
    assert {dataset.domain_of[s] for b in batches for s, _ in b} == {1}
    with pytest.raises(InputError, match="Snow"):
        make_batch_sampler("single_domain", dataset, 4, seed=2, single_domain="Snow")
    with pytest.raises(InputError):
        make_batch_sampler("round_robin", dataset, 4, seed=2)


def test_prompts_are_drawn_from_the_scans_own_pool(dataset):
    batches = _take(make_batch_sampler("cdts", dataset, 8, seed=3), 40)
    seen = collections.defaultdict(set)
    for b in batches:
        for s, p in b:
            seen[dataset.domain_of[s]].add(p)
    assert seen == {0: {0, 1}, 1: {0}, 2: {0, 1, 2}}
    item = dataset[(next(s for s in range(24) if dataset.domain_of[s] == 2), 2)]
    assert item["prompt"] == 3 + 2 and item["domain"] == 2 and item["image"].shape == (2, 16, 64)


def test_determinism_skip_and_rank_slices(dataset):
    a = _take(make_batch_sampler("cdts", dataset, 8, seed=4), 6)
    b = _take(make_batch_sampler("cdts", dataset, 8, seed=4, skip=4), 6)
    assert b[:4] == [[]] * 4 and b[4:] == a[4:]
    r0 = _take(make_batch_sampler("cdts", dataset, 8, seed=4, rank=0, world_size=2), 6)
    r1 = _take(make_batch_sampler("cdts", dataset, 8, seed=4, rank=1, world_size=2), 6)
    for full, x, y in zip(a, r0, r1):
        assert sorted(x + y) == sorted(full) and len(x) == len(y) == 4
    assert _take(make_batch_sampler("cdts", dataset, 8, seed=5), 6) != a
    assert collate([]) == {}
    batch = collate([dataset[k] for k in a[0]])
    assert batch["image"].shape == (8, 2, 16, 64) and batch["domain"].dtype.is_signed


def test_bad_inputs_name_the_file(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, image=np.full((2, 16, 64), np.nan, np.float32))
    with pytest.raises(InputError, match="NaN") as err:
        load_range_image(bad)
    assert str(bad) in str(err.value)
    np.savez(bad, image=np.zeros((3, 16, 64), np.float32))
    with pytest.raises(InputError, match=r"\(2, H, W\)"):
        load_range_image(bad)
    np.savez(bad, image=np.zeros((2, 16, 64), np.float32))
    with pytest.raises(InputError, match="expects 32x256"):
        load_range_image(bad, (32, 256))
    np.savez(bad, other=np.zeros(3))
    with pytest.raises(InputError, match="no 'image'"):
        load_range_image(bad)
    idx = tmp_path / "domains.json"
    idx.write_text(json.dumps({"domains": {"Fog": {"id": 0, "shards": [str(tmp_path / "missing")]}}}))
    with pytest.raises(InputError, match="not found"):
        read_domains_index(idx)
    idx.write_text(json.dumps({"domains": {"A": {"id": 0, "shards": []}, "B": {"id": 0, "shards": []}}}))
    with pytest.raises(InputError, match="share id"):
        read_domains_index(idx)
    idx.write_text("{not json")
    with pytest.raises(InputError, match="invalid JSON"):
        read_domains_index(idx)
