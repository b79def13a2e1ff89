"""SemanticKITTI-C-style corrupted sets: layout read back by our reader, severities,
regeneration from the sidecar, determinism."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ground_scenes import make_scene
from omnilidar.config import section_defaults
from omnilidar.data.index import build_index, write_index
from omnilidar.domains.builder import rebuild_scan
from omnilidar.domains.corruption import CORRUPTIONS, build_corrupted_set, corruption_scene
from omnilidar.errors import InputError
from omnilidar.io import semantickitti
from omnilidar.lidar.sensors import PRESETS

KITTI = PRESETS["kitti_hdl64e"]


@pytest.fixture(scope="module")
def val_root(tmp_path_factory):
    """SemanticKITTI root with two labelled ray-cast scans in val sequence 08."""
    root = tmp_path_factory.mktemp("skitti_val")
    seq = root / "sequences" / "08"
    (seq / "velodyne").mkdir(parents=True)
    (seq / "labels").mkdir()
    for i in range(2):
        scan = make_scene(KITTI, np.random.default_rng(20 + i), azimuth_steps=256)
        semantickitti.write_scan(scan, seq / "velodyne" / f"{i:06d}.bin", seq / "labels" / f"{i:06d}.label")
    index = root / "index.json"
    write_index(build_index("semantickitti", root), index)
    return root, index


def settings(**over):
    cfg = section_defaults("domains")["corrupted"]
    # The ray-cast test scenes fire at the nominal beam angles: nominal ring binning is exact.
    cfg.update({"max_scans": None, "fidelity": {"beam_missing": {"calibrate": False}}, **over})
    return cfg


@pytest.mark.parametrize("corruption", list(CORRUPTIONS))
def test_corrupted_set_reads_back_as_semantickitti(val_root, tmp_path, corruption):
    root, index = val_root
    out = tmp_path / corruption / "heavy"
    side = build_corrupted_set(corruption, "heavy", index, settings(), 0, out, progress=False)
    pairs = semantickitti.sequence_paths(out, "08")
    assert [p[0].name for p in pairs] == ["000000.bin", "000001.bin"]  # source frame names kept
    assert json.loads((out / "sidecar.json").read_text()) == side
    for (bin_path, label_path), rec in zip(pairs, side["scans"]):
        scan = semantickitti.read_scan(bin_path, label_path)  # counts match, remission in 0..1
        assert len(scan) == rec["num_points_out"] <= rec["num_points_in"]
        step = rec["effects"][0]
        assert step["name"] == CORRUPTIONS[corruption] and step["severity"] == "heavy"
        source = semantickitti.read_scan(rec["source"], rec["source_labels"])
        again = rebuild_scan(source, rec, KITTI)
        assert np.array_equal(again.points, scan.points) and np.array_equal(again.semantic, scan.semantic)
        assert len(scan) < len(source) or not np.array_equal(scan.points, source.points)  # corrupted


def test_beam_missing_severities_drop_more_beams(val_root, tmp_path):
    _, index = val_root
    kept, dropped = [], []
    for sev in ("light", "moderate", "heavy"):
        side = build_corrupted_set("beam_missing", sev, index, settings(max_scans=1), 0, tmp_path / sev,
                                   progress=False)
        rec = side["scans"][0]
        dropped.append(len(rec["effects"][0]["outcome"]["dropped_beams"]))
        kept.append(rec["num_points_out"] / rec["num_points_in"])
    assert dropped == [16, 32, 48]  # Robo3D's SemanticKITTI-C counts for 64 beams
    assert kept[0] > kept[1] > kept[2] > 0.05


def test_sets_are_deterministic_and_seeded(val_root, tmp_path):
    _, index = val_root
    paths = []
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        build_corrupted_set("fog", "moderate", index, settings(max_scans=1), seed, tmp_path / name, progress=False)
        paths.append((tmp_path / name / "sequences" / "08" / "velodyne" / "000000.bin").read_bytes())
    assert paths[0] == paths[1]
    assert paths[0] != paths[2]


def test_bad_requests_are_input_errors(val_root, tmp_path):
    _, index = val_root
    with pytest.raises(InputError, match="unknown corruption"):
        corruption_scene("motion_blur", "light")
    with pytest.raises(InputError, match="unknown severity"):
        corruption_scene("fog", "extreme")
    with pytest.raises(InputError, match="no split 'valid'"):
        build_corrupted_set("fog", "light", index, settings(split="valid"), 0, tmp_path / "x", progress=False)
    with pytest.raises(InputError, match="no scans to corrupt"):
        build_corrupted_set("fog", "light", index, settings(split="test"), 0, tmp_path / "x", progress=False)
    assert not (tmp_path / "x").exists()
