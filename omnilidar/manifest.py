"""Content manifests and digests: what a stage wrote, so consumers hash little.

Every directory a stage writes atomically (dataset shards, domain shards, sample
and pseudo-label shards, corrupted sets) carries ``MANIFEST.sha256``: one line
``<sha256>  <relative path>`` per file, the format ``sha256sum -c`` checks. A
consumer's input digest hashes that manifest, not the gigabytes it lists.

Real dataset roots have no manifest; they get a *listing* digest (relative names,
sizes and modification times), which catches added, removed, resized or rewritten
files but not a file rewritten with the same size while its modification time is
kept (``cp -p``, ``rsync -t`` of different content, or a filesystem without mtimes).

Stdlib only: the Snakefile imports this module at parse time.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

MANIFEST_NAME = "MANIFEST.sha256"
_CHUNK = 1 << 20


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def _files(directory: Path) -> list[Path]:
    """Every file under ``directory`` but its manifest, sorted by relative path."""
    found = []
    for base, dirs, names in os.walk(directory):
        dirs.sort()
        for name in names:
            path = Path(base, name)
            if path.parent == directory and name == MANIFEST_NAME:
                continue
            found.append(path)
    return sorted(found, key=lambda p: p.relative_to(directory).as_posix())


def manifest_text(directory: str | Path) -> str:
    directory = Path(directory)
    return "".join(f"{file_sha256(p)}  {p.relative_to(directory).as_posix()}\n" for p in _files(directory))


def write_manifest(directory: str | Path) -> str:
    """Write ``directory/MANIFEST.sha256`` and return its digest."""
    text = manifest_text(directory)
    (Path(directory) / MANIFEST_NAME).write_text(text)
    return hashlib.sha256(text.encode()).hexdigest()


def digest(path: str | Path) -> str:
    """Content digest of a file (its bytes) or a directory (its manifest; computed
    from the files when the directory has none)."""
    path = Path(path)
    if path.is_dir():
        manifest = path / MANIFEST_NAME
        text = manifest.read_text() if manifest.is_file() else manifest_text(path)
        return hashlib.sha256(text.encode()).hexdigest()
    if path.is_file():
        return file_sha256(path)
    raise FileNotFoundError(f"{path}: no such file or directory to digest")


def listing_digest(root: str | Path) -> dict:
    """Digest of a dataset root: directories holding a manifest count by their
    manifest (exact content); every other file by name, size and modification time."""
    root = Path(root)
    h = hashlib.sha256()
    files = manifests = 0
    for base, dirs, names in os.walk(root):
        dirs.sort()
        here = Path(base)
        rel = here.relative_to(root).as_posix()
        if MANIFEST_NAME in names:
            h.update(f"M {rel} {hashlib.sha256((here / MANIFEST_NAME).read_bytes()).hexdigest()}\n".encode())
            manifests += 1
            dirs[:] = []  # the manifest covers everything below
            continue
        for name in sorted(names):
            st = (here / name).stat()
            h.update(f"F {rel}/{name} {st.st_size} {st.st_mtime_ns}\n".encode())
            files += 1
    return {"digest": h.hexdigest(), "files": files, "manifests": manifests}
