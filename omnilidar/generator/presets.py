"""The paper's six ablation configurations as patches of the ``generator`` section.

The patches live in ``workflow/schemas/generator.schema.yaml`` under ``presets``
(single_domain, batch_homogeneous, cdts, cdts_cdfm, cdts_dafs, full), next to the
keys they switch, so there is one source of truth.
"""

from __future__ import annotations

import copy

from omnilidar.config import _load_schema, validate
from omnilidar.dicts import deep_merge
from omnilidar.errors import InputError

DATA_FILES = ("workflow/schemas/generator.schema.yaml",)  # run time reads (omnilidar.provenance)


def ablation_presets() -> dict[str, dict]:
    """{preset name: patch} in the paper's table order."""
    return copy.deepcopy(_load_schema("generator.schema.yaml")["presets"])


def apply_preset(settings: dict, name: str) -> dict:
    """A validated copy of ``settings`` with preset ``name`` merged in."""
    presets = ablation_presets()
    if name not in presets:
        raise InputError(None, f"unknown generator preset {name!r} (known: {', '.join(presets)})")
    return validate(deep_merge(settings, presets[name]), "generator.schema.yaml", source=f"<generator preset {name}>")
