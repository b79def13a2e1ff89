# Helpers shared by the workflow: validated config, per-stage settings, code hashes, shards.
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
# One software environment for every rule: the omnilidar package and its dependencies.
ENV = "../workflow/envs/omnilidar.yaml"


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


def synthetic_shards(name):
    """Shard names (sequences, platforms or splits) the synthetic world writes for one dataset."""
    spec = config["synthetic"]["datasets"][name]
    if name == "semantickitti":
        return [f"{int(s):02d}" for s in spec["sequences"]]
    if name == "kitti360":
        return [f"{int(s):04d}" for s in spec["sequences"]]
    if name == "pi3det":
        return list(spec["platforms"])
    if name == "nuscenes":
        return list(spec["splits"])
    raise ValueError(f"unknown dataset {name}")


def synthetic_shard_dirs(name):
    pattern = {
        "semantickitti": "{root}/sequences/{shard}",
        "kitti360": "{root}/data_3d_raw/2013_05_28_drive_{shard}_sync",
        "pi3det": "{root}/{shard}",
        "nuscenes": "{root}/{shard}",
    }[name]
    return [pattern.format(root=f"{DATA}/synthetic/{name}", shard=s) for s in synthetic_shards(name)]
