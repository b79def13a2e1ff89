"""Atomic file and directory writes: write to a temporary name, then rename.

A failed or interrupted stage never leaves a half-written output behind. A
directory gets its content manifest (:mod:`omnilidar.manifest`) before the rename,
so whoever consumes it can digest it cheaply.
"""

from __future__ import annotations

import contextlib
import glob
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

from omnilidar.manifest import write_manifest


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, someone else's
        pass
    return True


def remove_stale_temporaries(path: Path) -> None:
    """Remove what a killed earlier write of ``path`` on this host left (its writer is gone)."""
    mark = f".{path.name}.{socket.gethostname()}-"
    for old in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        if not old.name.startswith(mark):
            continue
        pid = old.name[len(mark):].split(".", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling path; on success rename it to ``path``.

    Works for files and for directories (the caller creates whichever it needs at
    the yielded path; a directory gets ``MANIFEST.sha256``). On any exception the temporary is removed and ``path`` is
    left untouched; what a killed process left (SIGKILL runs no cleanup) is removed by the next write of ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    # Host and process in the name: a rerun on this host knows which leftovers are dead.
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.{socket.gethostname()}-{os.getpid()}.", suffix=".tmp",
                                dir=path.parent))
    target = tmp / path.name
    try:
        yield target
        if target.is_dir():
            write_manifest(target)
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        os.replace(target, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
