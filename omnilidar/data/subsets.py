"""Deterministic label subsets: one scan out of every k of a split.

A fraction f keeps scans 0, k, 2k, ... of the split in index order with
k = round(1 / f) (1 % = every 100th scan, 10 % = every 10th, 100 % = all). The
choice involves no randomness, so the same index always gives the same subset,
and the scans are spread evenly over the sequences instead of clustered.

A subset file is JSON::

    {"dataset": str, "split": str, "fraction": float, "every": k,
     "num_scans": int, "source_scans": int, "entries": [index entries...]}

where each entry is the dataset index's own entry (``points``, ``labels``, ...).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from omnilidar.data.index import read_index
from omnilidar.errors import InputError
from omnilidar.io.json_file import read_json
from omnilidar.io.atomic import write_text_atomic
from omnilidar.manifest import digest

FORMAT = "omnilidar-subset/1"


def every_k(fraction: float) -> int:
    """k of "one scan out of every k" for a fraction in (0, 1]."""
    if not 0 < fraction <= 1:
        raise InputError(None, f"subset fraction must lie in (0, 1], got {fraction}")
    return max(1, round(1.0 / fraction))


def select_every_k(entries: list[dict], fraction: float) -> list[dict]:
    """Scans 0, k, 2k, ... of ``entries`` (at least one scan when any exist)."""
    return list(entries[:: every_k(fraction)])


def make_subset(index_path: str | Path, split: str, fraction: float) -> dict:
    """The subset of ``split`` of a dataset index, as the JSON document above."""
    index = read_index(index_path)
    splits = index.get("splits", {})
    if split not in splits:
        raise InputError(index_path, f"has no split {split!r} (splits: {', '.join(splits)})")
    entries = splits[split]
    missing = [e["points"] for e in entries if not e.get("labels")]
    if missing:
        raise InputError(missing[0], f"scan of split {split} has no label file; label subsets need labels")
    chosen = select_every_k(entries, fraction)
    if not chosen:
        raise InputError(index_path, f"split {split} holds no scans")
    return {
        "format": FORMAT,
        "dataset": index.get("dataset"),
        "split": split,
        "fraction": float(fraction),
        "every": every_k(fraction),
        "num_scans": len(chosen),
        "source_scans": len(entries),
        # The index's content digest (it records its root's): trainers key resumable state by it.
        "index_digest": digest(index_path),
        "entries": chosen,
    }


def _split_entries(index_path: str | Path, split: str) -> tuple[dict, list[dict]]:
    index = read_index(index_path)
    entries = index.get("splits", {}).get(split)
    if entries is None:
        raise InputError(index_path, f"has no split {split!r}")
    return index, entries


def _evenly_spread(rest: list[dict], count: int) -> list[dict]:
    """``count`` of ``rest`` at even steps in index order (no randomness)."""
    picks = np.unique(np.floor(np.arange(count) * len(rest) / count).astype(int))
    return [rest[i] for i in picks]


def _labelled(entries: list[dict], split: str, what: str) -> None:
    missing = [e["points"] for e in entries if not e.get("labels")]
    if missing:
        raise InputError(missing[0], f"scan of split {split} has no label file; {what} needs true labels")


def _sequence_of(entry: dict, index_path: str | Path) -> str:
    if entry.get("sequence") is None:
        raise InputError(index_path, f"entry {entry['points']} names no sequence; held-out sets take whole sequences")
    return str(entry["sequence"])


def _pick_document(index: dict, index_path, split: str, entries: list[dict], chosen: list[dict], excludes: dict) -> dict:
    return {
        "format": FORMAT, "dataset": index.get("dataset"), "split": split,
        "fraction": len(chosen) / len(entries), "every": None, "num_scans": len(chosen),
        "source_scans": len(entries), "index_digest": digest(index_path),
        "excludes": excludes, "entries": chosen,
    }


def make_pool(index_path: str | Path, split: str, exclude: dict, count: int, exclude_path: str | Path,
              heldout: dict | None = None, heldout_path: str | Path | None = None) -> dict:
    """``count`` further scans of ``split`` that are not in the subset ``exclude`` (nor in any sequence
    of ``heldout``), spread evenly over the rest of the split in index order (no randomness): the real
    scans the decomposition study adds with their true labels, with the labeler's labels, or
    unlabelled (LaserMix)."""
    index, entries = _split_entries(index_path, split)
    taken = {e["points"] for e in exclude["entries"]}
    held = set()
    if heldout:
        held = set(heldout.get("excludes", {}).get("sequences") or
                   (_sequence_of(e, heldout_path) for e in heldout["entries"]))
    rest = [e for e in entries if e["points"] not in taken and (not held or _sequence_of(e, index_path) not in held)]
    outside = f"the subset {exclude_path}" + (f" and the sequences of {heldout_path}" if held else "")
    if count < 1 or count > len(rest):
        raise InputError(index_path, f"split {split} holds {len(rest)} scans outside {outside}; cannot take {count}")
    _labelled(rest, split, "the pool")
    excludes = {"subset": str(exclude_path), "num_scans": exclude["num_scans"]}
    if held:
        excludes["heldout_sequences"] = sorted(held)
    return _pick_document(index, index_path, split, entries, _evenly_spread(rest, count), excludes)


def make_heldout(index_path: str | Path, split: str, exclude: dict, count: int, exclude_path: str | Path) -> dict:
    """``count`` scans of whole sequences of ``split`` that hold no scan of ``exclude``, taken from the
    split's last sequences (as many as hold ``count`` scans) and spread evenly over them: train scans
    a study's runs never see, from scenes none of them trains on, as val's own sequence is. The
    decomposition study checks its regime there (never on val); its pool leaves these sequences out."""
    index, entries = _split_entries(index_path, split)
    taken = {_sequence_of(e, index_path) for e in exclude["entries"]}
    by_sequence: dict[str, list[dict]] = {}
    for e in entries:
        by_sequence.setdefault(_sequence_of(e, index_path), []).append(e)
    chosen_sequences, held = [], []
    for sequence in reversed([q for q in by_sequence if q not in taken]):
        if len(held) >= count:
            break
        chosen_sequences.insert(0, sequence)
        held = by_sequence[sequence] + held
    if count < 1 or count > len(held):
        raise InputError(index_path, f"split {split} holds {len(held)} scans in sequences without a scan of "
                                     f"{exclude_path}; cannot take {count}")
    _labelled(held, split, "the held-out set")
    excludes = {"subset": str(exclude_path), "num_scans": exclude["num_scans"], "sequences": chosen_sequences}
    return _pick_document(index, index_path, split, entries, _evenly_spread(held, count), excludes)


def write_subset(subset: dict, path: str | Path) -> None:
    write_text_atomic(path, json.dumps(subset, indent=1))


def read_subset(path: str | Path) -> dict:
    """Read a subset file written by :func:`write_subset`, checking its shape."""
    path = Path(path)
    doc = read_json(path, "subset list not found (run the make_subset rule)")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or not isinstance(doc.get("entries"), list):
        raise InputError(path, f"not a subset list ({FORMAT})")
    if not doc["entries"]:
        raise InputError(path, "subset list holds no scans")
    return doc
