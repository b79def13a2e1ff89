"""Atomic writes and the CLI's error contract."""

from __future__ import annotations

import subprocess
import sys

import pytest

from omnilidar.cli import main
from omnilidar.io.atomic import atomic_path, write_text_atomic


def test_atomic_file_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []


def test_atomic_directory_replaces_whole(tmp_path):
    target = tmp_path / "shard"
    for content in ("first", "second"):
        with atomic_path(target) as tmp:
            tmp.mkdir()
            (tmp / "a.txt").write_text(content)
    assert (target / "a.txt").read_text() == "second"
    assert [p.name for p in tmp_path.iterdir()] == ["shard"]


def test_write_text_atomic_overwrites(tmp_path):
    target = tmp_path / "x.json"
    write_text_atomic(target, "1")
    write_text_atomic(target, "2")
    assert target.read_text() == "2"


def test_help_lists_stages():
    out = subprocess.run([sys.executable, "-m", "omnilidar.cli", "--help"], capture_output=True, text=True, check=True)
    assert "index-dataset" in out.stdout


def test_input_error_is_one_line_and_exit_2(tmp_path, capsys):
    missing = tmp_path / "nowhere"
    code = main(["index-dataset", "semantickitti", "--root", str(missing), "--out", str(tmp_path / "i.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith("omnilidar index-dataset: error: ")
    assert str(missing) in err[-1] and "not found" in err[-1]
    assert not (tmp_path / "i.json").exists()
