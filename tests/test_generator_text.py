"""Prompt encoding with the packaged MiniLM, the cache round trip, presets, and the CLI."""

from __future__ import annotations

import json

import pytest
import torch

from omnilidar.cli import main
from omnilidar.config import section_defaults
from omnilidar.errors import InputError
from omnilidar.generator.presets import ablation_presets, apply_preset
from omnilidar.generator.text import load_prompt_cache, stack_prompts
from test_generator_fixtures import one_torch_thread, tiny_settings  # noqa: F401


@pytest.fixture(scope="module")
def cache_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("prompts") / "prompts.pt"
    assert main(["encode-prompts", "--settings", json.dumps(tiny_settings()), "--out", str(path)]) == 0
    return path


def test_prompt_cache_round_trip_weights_only(cache_path):
    raw = torch.load(cache_path, weights_only=True)  # plain tensors and dicts only
    cache = load_prompt_cache(cache_path)
    assert cache["encoder"] == "minilm" and cache["dim"] == 384
    assert set(cache["domains"]) == {"Vehicle", "Fog", "Beam32"}
    beam = cache["domains"]["Beam32"]
    assert beam["prompts"][0] == "a sparse 32-beam scan"
    assert beam["tokens"].shape == (3, cache["max_tokens"], 384) and beam["mask"].dtype == torch.bool
    assert torch.equal(raw["domains"]["Fog"]["tokens"], cache["domains"]["Fog"]["tokens"])
    # padding positions are zero; real tokens are not
    m = beam["mask"]
    assert beam["tokens"][~m].abs().sum() == 0 and beam["tokens"][m].abs().sum() > 0
    # different prompts, different embeddings; the encoder is deterministic
    v = cache["domains"]["Vehicle"]["tokens"]
    assert not torch.allclose(v[0], v[1])
    tok, mask, spans = stack_prompts(cache, ["Vehicle", "Fog", "Beam32"])
    assert tok.shape[0] == 6 and spans == {"Vehicle": (0, 2), "Fog": (2, 1), "Beam32": (3, 3)}
    with pytest.raises(InputError, match="Snow"):
        stack_prompts(cache, ["Snow"])


def test_bad_prompt_caches_are_rejected(tmp_path, cache_path):
    with pytest.raises(InputError, match="not found"):
        load_prompt_cache(tmp_path / "none.pt")
    (tmp_path / "junk.pt").write_bytes(b"junk")
    with pytest.raises(InputError, match="readable"):
        load_prompt_cache(tmp_path / "junk.pt")
    cache = torch.load(cache_path, weights_only=True)
    cache["domains"]["Fog"]["tokens"][0, 0, 0] = float("nan")
    torch.save(cache, tmp_path / "nan.pt")
    with pytest.raises(InputError, match="non-finite"):
        load_prompt_cache(tmp_path / "nan.pt")


def test_schema_defaults_and_presets():
    d = section_defaults("generator")
    assert len(d["prompts"]) == 8 and d["sampling"]["scans_per_domain"] >= 1
    presets = ablation_presets()
    assert list(presets) == ["single_domain", "batch_homogeneous", "cdts", "cdts_cdfm", "cdts_dafs", "full"]
    full = apply_preset(d, "full")
    assert full["model"]["cdfm"] and full["model"]["dafs"] and full["training"]["strategy"] == "cdts"
    hom = apply_preset(d, "batch_homogeneous")
    assert not hom["model"]["cdfm"] and hom["training"]["strategy"] == "batch_homogeneous"
    assert d["model"]["cdfm"]  # applying a preset does not modify its input
    with pytest.raises(InputError, match="unknown generator preset"):
        apply_preset(d, "half")


def test_unknown_config_key_is_an_input_error(tmp_path, capsys):
    bad = {"model": {"base_chanels": 8}}
    assert main(["encode-prompts", "--settings", json.dumps(bad), "--out", str(tmp_path / "p.pt")]) == 2
    assert "base_chanels" in capsys.readouterr().err
    assert not (tmp_path / "p.pt").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
def test_cuda_text_device_without_cuda_is_one_line(tmp_path, capsys):
    s = tiny_settings()
    s["text"]["device"] = "cuda"
    assert main(["encode-prompts", "--settings", json.dumps(s), "--out", str(tmp_path / "p.pt")]) == 2
    err = capsys.readouterr().err.strip()  # the echoed command line, then one error line
    assert "Traceback" not in err and len(err.splitlines()) == 2
    assert "generator.text.device cuda: CUDA is not available" in err.splitlines()[-1]
    assert not (tmp_path / "p.pt").exists()


def test_clip_missing_from_offline_cache_says_so(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("HF_HOME", str(tmp_path / "empty_hf_home"))  # nothing cached, and no network asked
    s = tiny_settings()
    s["text"].update(encoder="clip", clip_model="openai/clip-vit-large-patch14")
    assert main(["encode-prompts", "--settings", json.dumps(s), "--out", str(tmp_path / "p.pt")]) == 2
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 2
    assert "offline Hugging Face cache" in err.splitlines()[-1] and "clip-vit-large-patch14" in err
    assert not (tmp_path / "p.pt").exists()
