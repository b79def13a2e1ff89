"""Configuration: YAML validated against JSON schemas that hold every default.

The schemas live in ``workflow/schemas/``: ``config.schema.yaml`` for the whole
file, which refers to one ``<section>.schema.yaml`` per stage. The Snakefile
validates the user's config with them; library code and tests get a stage's
defaults from the same files through :func:`section_defaults`, so defaults live
in one place. Unknown keys are errors (``additionalProperties: false``).

A schema is read when a validation refers to it, so validating one section reads
that section's schema only. Which one is the caller's choice: every package
module that validates names its schema and declares it in ``DATA_FILES``, so that
the schema is part of its stage's code hash (``omnilidar.provenance``). The
whole-config schema is for the Snakefile and tests.
"""

from __future__ import annotations

import copy
import functools
from pathlib import Path

import jsonschema
import yaml
from referencing import Registry, Resource
from referencing.jsonschema import DRAFT202012

from omnilidar.errors import InputError
from omnilidar.yaml_load import load_yaml

WORKFLOW_ROOT = Path(__file__).resolve().parents[1]
SCHEMA_DIR = WORKFLOW_ROOT / "workflow" / "schemas"


def workflow_file(path: str | Path) -> Path:
    """A file the workflow ships (``config/detectors/voxel_rcnn.yaml``): as given when it exists
    there (absolute, or relative to the working directory: a user's own copy), else relative to
    the workflow, so a run from another working directory finds it."""
    path = Path(path)
    return path if path.is_absolute() or path.exists() else WORKFLOW_ROOT / path


@functools.cache
def _load_schema(name: str) -> dict:
    path = SCHEMA_DIR / name
    if not path.exists():
        raise InputError(path, "schema file not found (is the package installed from a checkout?)")
    return load_yaml(path.read_text())


def _without_dialect(schema: dict) -> dict:
    # A "$schema" key makes jsonschema switch to the stock validator class when it
    # follows a $ref, which would skip our default-filling; all files are 2020-12.
    return {k: v for k, v in schema.items() if k != "$schema"}


def _retrieve(name: str) -> Resource:
    return Resource(contents=_without_dialect(_load_schema(name)), specification=DRAFT202012)


def _registry() -> Registry:
    return Registry(retrieve=_retrieve)  # schemas are read when referred to


def _fill_defaults_validator():
    base = jsonschema.Draft202012Validator

    def set_defaults(validator, properties, instance, schema):
        if isinstance(instance, dict):
            for key, sub in properties.items():
                if "$ref" in sub:
                    sub = validator._resolver.lookup(sub["$ref"]).contents
                if "default" in sub and key not in instance:
                    instance[key] = copy.deepcopy(sub["default"])
                elif sub.get("type") == "object" and key not in instance and "properties" in sub:
                    instance[key] = {}
        yield from base.VALIDATORS["properties"](validator, properties, instance, schema)

    return jsonschema.validators.extend(base, {"properties": set_defaults})


def validate(config: dict, schema_name: str = "config.schema.yaml", source: str | Path | None = None) -> dict:
    """Validate ``config`` in place, filling defaults; raise InputError on the first problem."""
    validator = _fill_defaults_validator()(_without_dialect(_load_schema(schema_name)), registry=_registry())
    errors = sorted(validator.iter_errors(config), key=lambda e: list(e.absolute_path))
    if errors:
        err = errors[0]
        where = ".".join(str(p) for p in err.absolute_path) or "<top level>"
        raise InputError(source, f"config key {where}: {err.message}")
    return config


def section_defaults(section: str) -> dict:
    """The defaults of one stage's section, from ``workflow/schemas/<section>.schema.yaml``."""
    return validate({}, f"{section}.schema.yaml", source=f"<defaults of {section}>")


def load_config(path: str | Path) -> dict:
    """Read and validate a YAML config file (defaults filled in)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "config file not found")
    try:
        config = load_yaml(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise InputError(path, f"invalid YAML: {err}") from None
    return validate(config, source=path)
