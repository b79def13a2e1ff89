"""The domains index: which shard directories hold each built domain.

Format (read by ``omnilidar.generator.data.read_domains_index``)::

    {"domains": {"<label>": {"id": int, "name": "<config key>", "num_scans": int,
                             "shards": ["<dir relative to the index>", ...],
                             "shard_digests": ["<sha256 of the shard's manifest>", ...]}}}

Keys are the domains' labels (the generator's prompt-pool names, e.g.
``WetGround``). Every shard's sidecar must belong to a configured domain with the
same id, and each domain's shards must be complete (0..N-1 of one N).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from omnilidar.domains.builder import range_image_spec, read_sidecar
from omnilidar.domains.spec import domains_from_settings
from omnilidar.errors import InputError
from omnilidar.manifest import digest


def domains_index(settings: dict, shard_dirs: list[str | Path], out: str | Path) -> dict:
    """Group shard directories by domain (from their sidecars) into the index dict;
    shard paths are written relative to ``out``'s directory."""
    specs = domains_from_settings(settings)
    base = Path(out).resolve().parent
    grouped: dict[str, list[tuple[int, int, Path, int]]] = {}
    for shard_dir in shard_dirs:
        side = read_sidecar(shard_dir)
        where = Path(shard_dir) / "sidecar.json"
        name = side.get("domain")
        if name not in specs:
            raise InputError(where, f"domain {name!r} is not configured (known: {', '.join(specs)})")
        if side.get("id") != specs[name].id:
            raise InputError(where, f"built with id {side.get('id')} but domains.{name}.id is {specs[name].id}")
        grouped.setdefault(name, []).append((side["shard"], side["num_shards"], Path(shard_dir), len(side["scans"])))
    domains = {}
    for name, shards in grouped.items():
        shards.sort()
        counts = {n for _, n, _, _ in shards}
        numbers = [k for k, _, _, _ in shards]
        if len(counts) != 1 or numbers != list(range(next(iter(counts)))):
            raise InputError(shards[0][2], f"domain {name}: shards {numbers} of {sorted(counts)} are not one complete set")
        spec = specs[name]
        domains[spec.label] = {
            "id": spec.id,
            "name": name,
            "num_scans": sum(c for _, _, _, c in shards),
            "shards": [os.path.relpath(Path(d).resolve(), base) for _, _, d, _ in shards],
            # Content digests (manifests) of the shards: the generator's resumable state is keyed by them.
            "shard_digests": [digest(d) for _, _, d, _ in shards],
            # Field of view, pitch and range limits of this domain's images: the
            # generator's samples of this domain are back-projected with them.
            "range_image": dataclasses.asdict(range_image_spec(spec, settings)),
        }
    return {"domains": dict(sorted(domains.items(), key=lambda kv: kv[1]["id"]))}
