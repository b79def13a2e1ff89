"""Nested-dict helpers shared by settings code."""

from __future__ import annotations

import copy


def deep_merge(base: dict, patch: dict) -> dict:
    """A copy of ``base`` with ``patch`` merged in: dicts recursively, anything else replaced."""
    out = copy.deepcopy(base)
    for key, value in patch.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out
