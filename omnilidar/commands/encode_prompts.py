"""omnilidar encode-prompts: encode every domain's prompt pool once with the frozen text encoder."""

from __future__ import annotations

from omnilidar.commands._common import settings_arg

HELP = "encode the generator's prompt pools with the frozen text encoder (MiniLM offline, or CLIP)"
DATA_FILES = ("workflow/schemas/generator.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    parser.add_argument("--out", required=True, help="prompt cache to write (torch .pt, weights-only loadable)")


def run(args) -> int:
    import torch

    from omnilidar.config import validate
    from omnilidar.generator.text import TextEncoder, build_prompt_cache
    from omnilidar.io.atomic import atomic_path

    settings = validate(dict(args.settings), "generator.schema.yaml", source="--settings")
    text = settings["text"]
    model = text["minilm_path"] or None if text["encoder"] == "minilm" else text["clip_model"]
    encoder = TextEncoder(text["encoder"], model, text["max_tokens"], text["device"])
    cache = build_prompt_cache(settings["prompts"], encoder)
    with atomic_path(args.out) as tmp:
        torch.save(cache, tmp)
    n = sum(len(v["prompts"]) for v in cache["domains"].values())
    print(f"encoded {n} prompts of {len(cache['domains'])} domains with {encoder.kind} "
          f"({cache['dim']}-d, {cache['max_tokens']} tokens) -> {args.out}")
    return 0
