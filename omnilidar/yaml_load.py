"""Reading YAML: PyYAML's safe loader, through libyaml where the wheel has it.

The Snakefile reads a dozen schema and config files at every start (and every cluster job
re-parses it); libyaml reads them about 6x faster than the pure-Python loader, to the same data.
"""

from __future__ import annotations

import yaml

_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def load_yaml(text: str | bytes):
    """The document in ``text``, as ``yaml.safe_load`` reads it (raises ``yaml.YAMLError``)."""
    return yaml.load(text, Loader=_LOADER)
