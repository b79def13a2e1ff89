"""Config schema: defaults from one place, unknown keys rejected."""

from __future__ import annotations

import pytest
import yaml

from omnilidar.config import load_config, section_defaults, validate
from omnilidar.errors import InputError


def test_embedded_default_validates_and_fills_defaults(project_root):
    config = load_config(project_root / "config" / "config.yaml")
    assert config["datasets"]["semantickitti"]["root"] is None
    assert config["data_summary"]["max_scans"] >= 1
    assert isinstance(config["synthetic"], dict) and config["synthetic"]


def test_paper_config_validates(project_root):
    config = load_config(project_root / "config" / "paper.yaml")
    assert config["datasets"]["semantickitti"]["root"]


def test_unknown_key_is_an_error_naming_file_and_key(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"datasets": {"semantickitti": {"root": None, "rooot": "x"}}}))
    with pytest.raises(InputError) as err:
        load_config(path)
    assert str(path) in str(err.value) and "rooot" in str(err.value)


def test_unknown_top_level_key(tmp_path):
    with pytest.raises(InputError, match="typo_section"):
        validate({"typo_section": {}}, source="x.yaml")


def test_missing_config_file(tmp_path):
    with pytest.raises(InputError, match="config file not found"):
        load_config(tmp_path / "none.yaml")


def test_section_defaults_come_from_the_schema():
    assert section_defaults("data_summary") == {"reference_scans": [], "max_scans": 200}
