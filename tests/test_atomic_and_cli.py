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


ALLOCATOR_PROBE = """
import ctypes, sys
import numpy as np
if sys.argv[1] == "keep":
    from omnilidar.allocator import keep_freed_memory
    assert keep_freed_memory()
class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL(None)
if not hasattr(libc, "mallinfo2"):  # glibc older than 2.33
    print("no mallinfo2")
    raise SystemExit
mallinfo2 = libc.mallinfo2
mallinfo2.restype = MallInfo2
block = np.ones(64 * 2**20, np.uint8)  # 64 MB: above glibc's largest mmap threshold
mapped = mallinfo2().hblkhd
del block
print(mapped >= 64 * 2**20, mallinfo2().fordblks >= 64 * 2**20)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_keep_freed_memory_serves_big_blocks_from_the_heap_and_keeps_them():
    """Every stage keeps freed tensors' memory for the next one: by default glibc maps a 64 MB
    block afresh and unmaps it on free; once told to keep freed memory, it serves the block from
    the heap and keeps it after the free."""
    def probe(mode: str) -> str:
        return subprocess.run([sys.executable, "-c", ALLOCATOR_PROBE, mode], capture_output=True, text=True,
                              check=True).stdout.strip()

    if probe("default") == "no mallinfo2":
        pytest.skip("this C library has no mallinfo2 to read the allocator's state with")
    assert probe("default") == "True False"
    assert probe("keep") == "False True"
