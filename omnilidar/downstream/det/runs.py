"""What the detection commands share: settings validation, the platform's frames, one training call."""

from __future__ import annotations

from pathlib import Path

from omnilidar.errors import InputError

DATA_FILES = ("workflow/schemas/downstream.schema.yaml", "workflow/schemas/detection.schema.yaml")  # run time reads


def det_settings(settings: dict) -> dict:
    """The ``downstream.det`` section from ``--settings`` (validated, defaults filled)."""
    from omnilidar.config import validate

    return validate({"det": dict(settings)}, "downstream.schema.yaml", source="--settings (downstream.det)")["det"]


def platform_records(index_path: str | Path, platform: str, split: str) -> list[dict]:
    """Every frame of ``<platform>_<split>`` of a Pi3DET index."""
    from omnilidar.data.index import read_index
    from omnilidar.downstream.det.dataset import records_from_entries

    index = read_index(index_path)
    entries = index.get("splits", {}).get(f"{platform}_{split}")
    if not entries:
        raise InputError(index_path, f"has no frames in split {platform}_{split!s}")
    return records_from_entries(entries)


def run_training(det: dict, schedule: dict, detector: str, platform: str, model_yaml: str | None, real: list[dict],
                 generated: list[dict], out, work_dir, seed: int, info: dict, inputs: dict, command: str,
                 with_mixing: bool, segment: tuple[int, int] | None = None) -> dict:
    """Train ``detector`` on one platform's frames with the section's data keys and ``schedule``."""
    from omnilidar.downstream.det.data_config import platform_config
    from omnilidar.downstream.det.model_config import model_config
    from omnilidar.downstream.det.training import train_detector

    cfg = platform_config(det, platform)
    model = model_config(det, detector, cfg, model_yaml)
    training = {"device": det["device"], "voxels": det["voxels"], "schedule": schedule,
                "augmentation": det["augmentation"], "data": cfg.as_dict()}
    if with_mixing:
        training["mixing"] = det["mixing"]
    return train_detector(training, detector, model, cfg, real, generated, out, work_dir, seed, info=info,
                          inputs=inputs, command=command, segment=segment)


def load_detector(path: str | Path, device):
    """``(net in eval mode, PlatformConfig, payload)`` of a detector payload."""
    from omnilidar.downstream.det.checkpoints import load_payload
    from omnilidar.downstream.det.data_config import PlatformConfig
    from omnilidar.downstream.det.model_config import build

    payload = load_payload(path)
    data = payload["data"]
    cfg = PlatformConfig(platform=data["platform"], name=data["name"], class_names=tuple(data["class_names"]),
                         shift=tuple(data["shift"]), point_cloud_range=tuple(data["point_cloud_range"]),
                         voxel_size=tuple(data["voxel_size"]), anchors=data["anchors"])
    net = build(payload["model_cfg"], cfg)
    try:
        net.load_state_dict(payload["model_state"], strict=True)
    except RuntimeError as err:
        raise InputError(path, f"weights do not fit the detector they name: {str(err).splitlines()[0]}") from None
    return net.to(device).eval(), cfg, payload
