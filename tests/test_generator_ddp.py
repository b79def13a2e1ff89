"""Generator DDP on CPU: two gloo processes (as torchrun starts them) draw disjoint batches,
end with the same weights, and resume an interrupted run together."""

from __future__ import annotations

import json
import os
import socket

import torch
import torch.multiprocessing as mp

from omnilidar.generator.text import build_prompt_cache
from test_generator_fixtures import make_domains, tiny_settings
from test_generator_training import FakeEncoder

WORLD = 2


def _worker(rank: int, root: str, port: int) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), LOCAL_RANK=str(rank),
                      WORLD_SIZE=str(WORLD), OMP_NUM_THREADS="1")
    torch.set_num_threads(1)
    from omnilidar.generator import data, training

    drawn: list = []
    read = data.RangeImageDataset.__getitem__

    def recording(self, key):
        drawn.append([int(key[0]), int(key[1])])
        return read(self, key)

    data.RangeImageDataset.__getitem__ = recording  # records which scans this rank reads
    settings = json.loads(open(f"{root}/settings.json").read())
    longer = json.loads(json.dumps(settings))
    longer["training"]["iterations"] = 4
    runs = {}
    args = (f"{root}/domains.json", f"{root}/prompts.pt")
    # Uninterrupted: 4 iterations. Interrupted: 2 iterations, then raised to 4 in the same work dir.
    runs["full"] = training.train_generator(longer, *args, f"{root}/work_full", f"{root}/full.pt", seed=5)
    runs["full"]["drawn"], drawn[:] = list(drawn), []
    runs["first"] = training.train_generator(settings, *args, f"{root}/work_cut", f"{root}/cut.pt", seed=5)
    runs["first"]["drawn"], drawn[:] = list(drawn), []
    runs["resumed"] = training.train_generator(longer, *args, f"{root}/work_cut", f"{root}/resumed.pt", seed=5)
    runs["resumed"]["drawn"] = list(drawn)
    with open(f"{root}/rank{rank}.json", "w") as fh:
        json.dump(runs, fh)
    torch.distributed.destroy_process_group()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_gloo_ranks_draw_disjoint_batches_agree_and_resume(tmp_path):
    settings = tiny_settings()
    settings["training"].update(iterations=2, checkpoint_interval=2, batch_size=4)
    make_domains(tmp_path, settings)
    torch.save(build_prompt_cache(settings["prompts"], FakeEncoder()), tmp_path / "prompts.pt")
    (tmp_path / "settings.json").write_text(json.dumps(settings))
    mp.spawn(_worker, args=(str(tmp_path), _free_port()), nprocs=WORLD, join=True)
    ranks = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(WORLD)]

    full = [r["full"] for r in ranks]
    # The global batch of 4 is split: each rank reads 2 scans per iteration, none of the other
    # rank's, and together they read the batch one process would have read.
    from omnilidar.generator.data import RangeImageDataset, make_batch_sampler, read_domains_index
    from omnilidar.generator.text import load_prompt_cache, stack_prompts

    domains = read_domains_index(tmp_path / "domains.json")
    spans = stack_prompts(load_prompt_cache(tmp_path / "prompts.pt"), list(domains))[2]
    single = iter(make_batch_sampler("cdts", RangeImageDataset(domains, (16, 64), spans), 4, 5))
    assert [len(r["drawn"]) for r in full] == [4 * 2, 4 * 2]
    for step in range(4):
        a, b = ({tuple(x) for x in r["drawn"][2 * step : 2 * step + 2]} for r in full)
        assert not a & b, f"ranks share a scan at step {step}"
        assert sorted(a | b) == sorted(next(single))
    # Gradients are averaged: every rank ends with the same weights, and rank 0 wrote them.
    assert full[0]["weights_digest"] == full[1]["weights_digest"]
    from omnilidar.generator.training import state_digest

    written = torch.load(tmp_path / "full.pt", weights_only=True)["state_dict"]
    assert state_digest(written) == full[0]["weights_digest"]
    # Interrupted at iteration 2, raised to 4: both ranks resume at 2, read only the last two
    # steps' scans (the same ones as uninterrupted) and end with the uninterrupted weights.
    for r in ranks:
        assert r["first"]["iterations"] == 2 and r["resumed"]["resumed_from"] == 2
        assert r["resumed"]["iterations"] == 4
        assert r["first"]["drawn"] + r["resumed"]["drawn"] == r["full"]["drawn"]
        assert r["resumed"]["weights_digest"] == full[0]["weights_digest"]
    assert not (tmp_path / "resumed.pt").exists() or state_digest(
        torch.load(tmp_path / "resumed.pt", weights_only=True)["state_dict"]) == full[0]["weights_digest"]
