"""Assembling the segmentation experiment targets from evaluation files.

Each evaluation file (``evaluate-segmentor``) names its run through the
checkpoint's training info (role, backbone, label percent, generated domains).
An experiment groups them into supervised-only vs GDA per backbone, adds what
the paper reports (REFERENCE section 9) and, for the corrupted sets, mCE / mRR.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from omnilidar.downstream.seg.robustness import ROBO3D_MINKUNET18, robustness
from omnilidar.errors import InputError
from omnilidar.io.json_file import read_json

KINDS = ("semkitti", "semkittic", "nusc_beam32", "semanticstf")

# The paper's mIoU (percent): backbone -> percent -> (supervised-only, OmniLiDAR GDA).
PAPER = {
    "semkitti": {
        "minkunet": {1: (40.39, 59.49), 10: (60.90, 65.07), 20: (62.84, 66.59)},
        "spvcnn": {1: (37.86, 59.73), 10: (59.07, 65.99), 20: (61.16, 66.36)},
    },
    "nusc_beam32": {"spvcnn": {1: (30.45, 38.38)}},
    "semkittic": {"minkunet": {"supervised_only": {"mce": 100.0},
                               "gda": {"mce": 91.02, "miou": {"fog": 59.14, "wet_ground": 61.34, "snow": 54.79,
                                                              "beam_missing": 61.37}}}},
}


def read_evaluation(path: str | Path) -> dict:
    path = Path(path)
    doc = read_json(path, "evaluation file not found")
    if not isinstance(doc, dict) or "sets" not in doc or "train" not in doc:
        raise InputError(path, "not an evaluate-segmentor output")
    doc["_path"] = str(path)
    return doc


def _summary(scores: dict) -> dict:
    return {k: scores[k] for k in ("miou", "miou_nanmean", "accuracy", "iou", "num_scans")}


def labeler_quality(evaluation: dict) -> dict:
    """The labeler's own val scores (mIoU both ways, per-class IoU by name), as a GDA result records them."""
    val = evaluation["sets"].get("val")
    if val is None:
        raise InputError(evaluation["_path"], "the labeler's evaluation has no 'val' set")
    return {
        "val_miou": val["miou"], "val_miou_nanmean": val["miou_nanmean"], "val_accuracy": val["accuracy"],
        "val_iou": val["iou"], "val_scans": val["num_scans"],
        "label_space": evaluation["label_space"], "evaluation": evaluation["_path"],
    }


def labeler_against_students(labeler: dict, evals: list[dict]) -> dict:
    """Is the fixed labeler stronger than every supervised-only student it labels for? Per backbone,
    its val mIoU against the students' (mean over their seeds), where both score the same label
    space; a ``warning`` sentence when it is not (its pseudo-labels then cannot teach the student)."""
    students: dict[str, list[float]] = {}
    for ev in evals:
        if ev["train"]["info"]["role"] == "supervised_only" and "val" in ev["sets"]:
            if ev["label_space"] == labeler["label_space"]:
                students.setdefault(ev["model"]["backbone"], []).append(ev["sets"]["val"]["miou"])
    if not students:
        return {"compared": False, "warning": None,
                "note": f"no supervised-only student scored on val in the labeler's label space ({labeler['label_space']})"}
    per = {b: {"student_val_miou": float(np.mean(m)), "student_seeds": len(m), "labeler_val_miou": labeler["val_miou"],
               "labeler_stronger": bool(labeler["val_miou"] > float(np.mean(m)))} for b, m in sorted(students.items())}
    weaker = [f"{b} ({100 * r['student_val_miou']:.2f})" for b, r in per.items() if not r["labeler_stronger"]]
    warning = None if not weaker else (
        f"the labeler (val mIoU {100 * labeler['val_miou']:.2f}) scores below the supervised-only "
        f"{', '.join(weaker)} it labels for: its pseudo-labels cannot teach that student")
    return {"compared": True, "students": per, "warning": warning}


def runs_by_seed(evals: list[dict]) -> dict:
    """backbone -> role -> evaluation documents, one per seed, lowest seed (the configured one) first."""
    runs: dict[str, dict[str, list[dict]]] = {}
    for ev in evals:
        backbone, role = ev["model"]["backbone"], ev["train"]["info"]["role"]
        docs = runs.setdefault(backbone, {}).setdefault(role, [])
        if any(d["seed"] == ev["seed"] for d in docs):
            raise InputError(ev["_path"], f"a second {role} run of {backbone} with seed {ev['seed']}")
        docs.append(ev)
    for roles in runs.values():
        for docs in roles.values():
            docs.sort(key=lambda d: d["seed"])
    return runs


def group_runs(evals: list[dict]) -> dict:
    """backbone -> role -> evaluation document (one each: experiments that run one seed)."""
    runs = runs_by_seed(evals)
    for backbone, roles in runs.items():
        for role, docs in roles.items():
            if len(docs) > 1:
                raise InputError(docs[1]["_path"], f"a second {role} run of {backbone}")
    return {b: {r: docs[0] for r, docs in roles.items()} for b, roles in runs.items()}


def seed_statistics(docs: list[dict], evalset: str = "val") -> dict:
    """Every seed's mIoU on one set, their mean and sample standard deviation (None for one seed),
    and the mean IoU per class."""
    mious = [d["sets"][evalset]["miou"] for d in docs]
    classes = docs[0]["sets"][evalset]["iou"]
    return {
        "seeds": [d["seed"] for d in docs], "miou": mious, "miou_mean": float(np.mean(mious)),
        "miou_std": float(np.std(mious, ddof=1)) if len(docs) > 1 else None,
        "iou_mean": {c: float(np.mean([d["sets"][evalset]["iou"][c] for d in docs])) for c in classes},
    }


def _paper_pair(kind: str, backbone: str, percent: float):
    pair = PAPER.get(kind, {}).get(backbone, {}).get(int(round(percent)))
    return None if pair is None else {"supervised_only": pair[0], "gda": pair[1]}


def _run_record(ev: dict, sets: list[str]) -> dict:
    info = ev["train"]["info"]
    return {
        "checkpoint": ev["checkpoint"], "model": ev["model"], "seed": ev["seed"],
        "train_scans": {"real": ev["train"]["num_real"], "generated": ev["train"]["num_generated"]},
        "mixing": ev["train"]["mixing"] if info["role"] == "gda" else None,
        "domains": info.get("domains", []), "iterations": ev["train"]["iterations"],
        "scores": {s: _summary(ev["sets"][s]) for s in sets},
    }


def compare(kind: str, evals: list[dict]) -> dict:
    """Supervised-only vs GDA per backbone on the 'val' set (semkitti, nusc_beam32), over every seed
    given (the records' scores are the configured seed's; across_seeds holds all of them)."""
    out = {}
    for backbone, roles in runs_by_seed(evals).items():
        missing = {"supervised_only", "gda"} - set(roles)
        if missing:
            raise InputError(None, f"{backbone}: no {', '.join(sorted(missing))} evaluation given")
        seeds = {role: [d["seed"] for d in docs] for role, docs in roles.items()}
        if seeds["supervised_only"] != seeds["gda"]:
            raise InputError(None, f"{backbone}: supervised-only seeds {seeds['supervised_only']} differ from "
                                   f"GDA seeds {seeds['gda']}")
        sup, gda = _run_record(roles["supervised_only"][0], ["val"]), _run_record(roles["gda"][0], ["val"])
        sup["across_seeds"] = seed_statistics(roles["supervised_only"])
        gda["across_seeds"] = seed_statistics(roles["gda"])
        gains = [g - s for g, s in zip(gda["across_seeds"]["miou"], sup["across_seeds"]["miou"])]
        pct = roles["gda"][0]["train"]["info"]["percent"]
        out[backbone] = {
            "supervised_only": sup, "gda": gda, "seeds": len(gains),
            "miou_gain": float(np.mean(gains)),
            "miou_gain_per_seed": gains,
            "gda_helped": bool(np.mean(gains) > 0),
            "paper_miou": _paper_pair(kind, backbone, pct),
        }
    return out


def _corruption_table(ev: dict) -> dict[str, dict[str, float]]:
    table: dict[str, dict[str, float]] = {}
    for name, scores in ev["sets"].items():
        if "/" in name:
            corruption, severity = name.split("/", 1)
            table.setdefault(corruption, {})[severity] = scores["miou"]
    return table


def robustness_result(evals: list[dict]) -> dict:
    """mCE / mRR of supervised-only and GDA, normalised by our supervised-only model
    (the paper's convention) and by Robo3D's MinkUNet18 table."""
    out = {}
    for backbone, roles in group_runs(evals).items():
        if set(roles) != {"supervised_only", "gda"}:
            raise InputError(None, f"{backbone}: need one supervised-only and one GDA evaluation")
        base = _corruption_table(roles["supervised_only"])
        if not base:
            raise InputError(roles["supervised_only"]["_path"], "holds no corrupted sets (NAME = corruption/severity)")
        res = {}
        for role, ev in roles.items():
            table = _corruption_table(ev)
            if set(table) != set(base):
                raise InputError(ev["_path"], "corrupted sets differ from the supervised-only run's")
            clean = ev["sets"]["val"]["miou"]
            unknown = [c for c in table if c not in ROBO3D_MINKUNET18]
            res[role] = {
                **_run_record(ev, list(ev["sets"])),
                "clean_miou": clean,
                "corrupted_miou": {c: {s: v for s, v in sorted(t.items())} for c, t in table.items()},
                "normalised_by_supervised_only": robustness(table, clean, baseline_sets=base),
                "normalised_by_robo3d_minkunet18": None if unknown else robustness(
                    table, clean, baseline_table=ROBO3D_MINKUNET18),
            }
        out[backbone] = {**res, "paper": PAPER["semkittic"].get(backbone)}
    return out


def weather_result(evals: list[dict]) -> dict:
    """Per weather subset: supervised-only vs GDA mIoU (plus the clean val set)."""
    out = {}
    for backbone, roles in group_runs(evals).items():
        if set(roles) != {"supervised_only", "gda"}:
            raise InputError(None, f"{backbone}: need one supervised-only and one GDA evaluation")
        sets = list(roles["supervised_only"]["sets"])
        out[backbone] = {
            "supervised_only": _run_record(roles["supervised_only"], sets),
            "gda": _run_record(roles["gda"], sets),
            "miou_gain": {s: roles["gda"]["sets"][s]["miou"] - roles["supervised_only"]["sets"][s]["miou"]
                          for s in sets},
        }
    return out


def figure_panels(kind: str, evals: list[dict]) -> list[dict]:
    """Per-class IoU panels (supervised-only vs GDA) for the figure of an experiment."""
    panels = []
    for backbone, by_seed in sorted(runs_by_seed(evals).items()):
        roles = {role: docs[0] for role, docs in by_seed.items()}  # the configured seed's run
        sets = ["val"] if kind in ("semkitti", "nusc_beam32") else list(roles["supervised_only"]["sets"])
        for s in sets:
            classes = roles["supervised_only"]["class_names"]
            series = {("supervised-only" if r == "supervised_only" else "GDA"): _series(by_seed[r], s)
                      for r in ("supervised_only", "gda") if r in roles}
            panels.append({"title": f"{backbone} - {s}", "classes": classes, "series": series})
    return panels


def _series(docs: list[dict], evalset: str) -> dict:
    """One bar series: a run's scores on ``evalset``, or with several seeds their mean per class with
    the standard deviations (``iou_std``, ``miou_std``) and the seed count."""
    if len(docs) == 1:
        return docs[0]["sets"][evalset]
    stats = seed_statistics(docs, evalset)
    iou_std = {c: float(np.std([d["sets"][evalset]["iou"][c] for d in docs], ddof=1)) for c in stats["iou_mean"]}
    return {"iou": stats["iou_mean"], "miou": stats["miou_mean"], "iou_std": iou_std,
            "miou_std": stats["miou_std"], "seeds": len(docs)}


def timings(evals: list[dict], pseudo_sidecars: list[dict]) -> dict:
    """Wall time (s) per stage: labeler, pseudo-labelling, every training and evaluation."""
    t: dict[str, float] = {}
    labelers = {json.dumps(s["labeler"].get("train", {}).get("seconds")) for s in pseudo_sidecars}
    if pseudo_sidecars:
        t["labeler"] = pseudo_sidecars[0]["labeler"].get("train", {}).get("seconds")
        t["pseudo_labels"] = round(sum(s["seconds"] for s in pseudo_sidecars), 2)
        if len(labelers) > 1:
            raise InputError(None, "pseudo-label shards were made by different labelers")
    for ev in evals:
        name = f"{ev['model']['backbone']}_{ev['train']['info']['role']}"
        if f"train_{name}" in t:  # an extra seed of the same run
            name += f"_seed{ev['seed']}"
        t[f"train_{name}"] = ev["train"]["seconds"]
        t[f"evaluate_{name}"] = ev["seconds"]
    return t
