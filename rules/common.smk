# Helpers shared by all rule files: validated config, per-stage settings and code hashes.
import json
import sys

from omnilidar.config import validate
from omnilidar.errors import InputError
from omnilidar.provenance import command_code_hash

try:
    # Fills every default from workflow/schemas/ and rejects unknown keys.
    validate(config, source="config (config/config.yaml and --config/--configfile overrides)")
except InputError as err:
    sys.exit(f"Invalid configuration: {err}")

DATA = config["data_dir"]


def settings(*keys):
    """A config section as one JSON string: Snakemake compares params by value
    repr, so the whole section travels as one value and any change reruns."""
    node = config
    for key in keys:
        node = node[key]
    return json.dumps(node, sort_keys=True)


def code(command):
    """Content hash of the package code an ``omnilidar <command>`` runs."""
    return command_code_hash(command)


def dataset_root(name):
    """The dataset's root: the configured real root, or where the synthetic world writes it."""
    root = config["datasets"][name]["root"]
    return root if root is not None else f"{DATA}/synthetic/{name}"


def is_synthetic(name):
    return config["datasets"][name]["root"] is None
