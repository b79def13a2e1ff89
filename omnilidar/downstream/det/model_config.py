"""The MODEL section a detector is built from: a published-style yaml plus overrides.

``downstream.det.detectors.<name>`` names an OpenPCDet-style yaml
(``config``: a file whose ``MODEL`` section, or whole content, is the model
config, e.g. ``config/detectors/voxel_rcnn.yaml``) and ``overrides`` merged
into it key by key (dicts recursively, everything else replaced), which is how
the CPU default shrinks the paper's widths: either a mapping or the name of a
top-level section of the same yaml (``CPU_SMALL``). The platform's anchors always
replace ``DENSE_HEAD.ANCHOR_GENERATOR_CONFIG``, so one file serves Drone
(Car) and Quadruped (Car, Pedestrian).
"""

from __future__ import annotations

from pathlib import Path

import yaml

from omnilidar.dicts import deep_merge
from omnilidar.downstream.det.data_config import PlatformConfig, anchor_generator_config
from omnilidar.config import workflow_file
from omnilidar.errors import InputError
from omnilidar.yaml_load import load_yaml

DETECTORS = ("voxel_rcnn", "pv_rcnn")


def read_model_yaml(path: str | Path, section: str = "MODEL") -> dict:
    """The ``MODEL`` section of an OpenPCDet-style yaml (or the whole file when it has none),
    or another top-level ``section`` of it (an overrides preset such as ``CPU_SMALL``)."""
    path = workflow_file(path)
    if not path.is_file():
        raise InputError(path, "detector config not found (downstream.det.detectors.<name>.config)")
    try:
        doc = load_yaml(path.read_text())
    except yaml.YAMLError as err:
        raise InputError(path, f"not valid YAML: {str(err).splitlines()[0]}") from None
    if not isinstance(doc, dict):
        raise InputError(path, "detector config must be a mapping (an OpenPCDet cfg or its MODEL section)")
    if section != "MODEL":
        if not isinstance(doc.get(section), dict):
            raise InputError(path, f"has no overrides section {section!r} (downstream.det.detectors.<name>.overrides)")
        return doc[section]
    model = doc.get("MODEL", doc)
    if not isinstance(model, dict) or "NAME" not in model:
        raise InputError(path, "detector config has no MODEL.NAME")
    return model


def model_config(settings: dict, detector: str, cfg: PlatformConfig, path: str | Path | None = None) -> dict:
    """The resolved MODEL section of ``detector`` for one platform (from ``path``, default its config)."""
    if detector not in DETECTORS:
        raise InputError(None, f"unknown detector {detector!r}; known: {', '.join(DETECTORS)}")
    spec = settings["detectors"][detector]
    path = path or spec["config"]
    overrides = spec.get("overrides") or {}
    if isinstance(overrides, str):
        overrides = read_model_yaml(path, overrides)
    model = deep_merge(read_model_yaml(path), overrides)
    model.setdefault("DENSE_HEAD", {})["ANCHOR_GENERATOR_CONFIG"] = anchor_generator_config(cfg)
    return model


def build(model: dict, cfg: PlatformConfig, seed: int = 0):
    """The detector module (``omnilidar.downstream.det.models.detector.build_detector``) for a resolved
    MODEL section; ``seed`` seeds the heads' sampling generator."""
    from omnilidar.downstream.det.models.detector import build_detector

    return build_detector(model, num_class=len(cfg.class_names), class_names=list(cfg.class_names),
                          point_cloud_range=list(cfg.point_cloud_range), voxel_size=list(cfg.voxel_size),
                          seed=int(seed))
