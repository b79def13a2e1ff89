"""The Pi3DET experiment targets: supervised-only vs GDA per detector, with the labeler beside them.

Reads evaluate-detector outputs (:func:`read_evaluation`), groups them by
detector and role, and records per class 3D AP R11@0.5 and R40@0.5 (plus BEV),
the gain of GDA, recall, timings, and the labeler's own val AP. The paper's
numbers (Quadruped, Voxel R-CNN, 1 %) are put beside ours where they exist.
"""

from __future__ import annotations

import json
from pathlib import Path

from omnilidar.errors import InputError

# Paper, Pi3DET Quadruped, Voxel R-CNN, 3D AP R11@0.5 (REFERENCE section 9): (supervised-only, GDA).
PAPER = {("quadruped", "voxel_rcnn", 1): {"Car": (0.04, 20.46), "Pedestrian": (0.91, 33.05)}}
ROLES = ("supervised_only", "gda")


def read_evaluation(path: str | Path) -> dict:
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise InputError(path, f"not a readable detector evaluation ({err})") from None
    if not isinstance(doc, dict) or "ap" not in doc or "detector" not in doc:
        raise InputError(path, "not an evaluate-detector output (no ap / detector)")
    return doc | {"_path": str(path)}


def _scores(ev: dict) -> dict:
    return {c: {k: v for k, v in s.items() if not k.startswith("precision")} for c, s in ev["ap"].items()}


def _run(ev: dict) -> dict:
    train = ev["train"]
    return {"checkpoint": ev["checkpoint"], "iterations": train.get("iterations"),
            "train_frames": {"real": train.get("num_real"), "generated": train.get("num_generated")},
            "mixing": train.get("mixing") if train.get("info", {}).get("role") == "gda" else None,
            "ap": _scores(ev), "recall": ev["recall"], "is_labeler": train.get("info", {}).get("role") == "labeler"}


def run_role(ev: dict) -> str:
    """supervised_only or gda; the labeler (trained on 100 %) stands in for the supervised-only
    run at 100 % when the workflow found the two trainings identical."""
    info = ev["train"]["info"]
    return "supervised_only" if info["role"] == "labeler" and info.get("percent") == 100 else info["role"]


def compare(evals: list[dict], platform: str, percent: int) -> dict:
    runs: dict[str, dict] = {}
    for ev in evals:
        role = run_role(ev)
        if role in runs.setdefault(ev["detector"], {}):
            raise InputError(ev["_path"], f"a second {role} run of {ev['detector']}")
        runs[ev["detector"]][role] = ev
    out = {}
    for detector, roles in runs.items():
        missing = set(ROLES) - set(roles)
        if missing:
            raise InputError(None, f"{detector}: no {', '.join(sorted(missing))} evaluation given")
        sup, gda = _run(roles["supervised_only"]), _run(roles["gda"])
        gain = {c: {m: round(gda["ap"][c][m] - sup["ap"][c][m], 4) for m in ("3d_R11@0.5", "3d_R40@0.5")}
                for c in sup["ap"]}
        paper = PAPER.get((platform, detector, int(percent)))
        out[detector] = {"supervised_only": sup, "gda": gda, "gda_gain": gain,
                         "paper_3d_R11@0.5": None if paper is None else
                         {c: {"supervised_only": p[0], "gda": p[1]} for c, p in paper.items()}}
    return out


def labeler_record(ev: dict, sidecars: list[dict]) -> dict:
    boxes: dict[str, int] = {}
    for s in sidecars:
        for c, n in s["boxes"].items():
            boxes[c] = boxes.get(c, 0) + n
    return {"detector": ev["detector"], "checkpoint": ev["checkpoint"],
            "imported_from": ev["train"].get("imported_from"), "val_ap": _scores(ev), "recall": ev["recall"],
            "score_threshold": sidecars[0]["score_threshold"] if sidecars else None,
            "generated_scans": sum(s["scans"] for s in sidecars), "pseudo_boxes": boxes}


def box_labeler_check(labeler: dict, runs: dict, metric: str = "3d_R11@0.5") -> dict:
    """Is the box labeler stronger than every supervised-only detector it labels for? Per detector
    and class, its val AP against the student's; a ``warning`` sentence when it is not."""
    students = {}
    for detector, run in runs.items():
        students[detector] = {c: {"student_ap": run["supervised_only"]["ap"][c][metric],
                                  "labeler_ap": labeler["val_ap"][c][metric],
                                  "labeler_stronger": bool(labeler["val_ap"][c][metric] > run["supervised_only"]["ap"][c][metric])}
                              for c in run["supervised_only"]["ap"] if c in labeler["val_ap"]}
    weaker = [f"{d} {c} ({r['student_ap']:.2f} against the labeler's {r['labeler_ap']:.2f})"
              for d, per in students.items() for c, r in per.items() if not r["labeler_stronger"]]
    warning = None if not weaker else (
        f"the box labeler's val {metric} is not above the supervised-only {', '.join(weaker)}: its pseudo-boxes "
        "cannot teach that student")
    return {"metric": metric, "students": students, "warning": warning}


def timings(evals: list[dict], labeler: dict, sidecars: list[dict]) -> dict:
    """Wall time (s) per stage: labeler training, pseudo-boxing, every training and evaluation."""
    t = {"labeler_train": labeler["train"].get("seconds"), "labeler_evaluate": labeler["timings"]["evaluate_seconds"],
         "pseudo_boxes": round(sum(s["seconds"] for s in sidecars), 2)}
    for ev in evals:
        name = f"{ev['detector']}_{run_role(ev)}"
        t[f"train_{name}"] = ev["train"].get("seconds")
        t[f"evaluate_{name}"] = ev["timings"]["evaluate_seconds"]
        t[f"inference_per_frame_{name}"] = ev["timings"]["inference_seconds_per_frame"]
    return t


def figure_panels(evals: list[dict]) -> list[dict]:
    """One panel per detector and class: precision curves of supervised-only and GDA, with their APs."""
    panels = []
    by_detector: dict[str, dict] = {}
    for ev in evals:
        by_detector.setdefault(ev["detector"], {})[run_role(ev)] = ev
    for detector, roles in sorted(by_detector.items()):
        for cls in roles["supervised_only"]["classes"]:
            panels.append({"title": f"{detector} - {cls} (3D, IoU 0.5)", "series": {
                ("supervised-only" if r == "supervised_only" else "GDA"): {
                    "precision": roles[r]["ap"][cls].get("precision_3d@0.5", []),
                    "r11": roles[r]["ap"][cls]["3d_R11@0.5"], "r40": roles[r]["ap"][cls]["3d_R40@0.5"]}
                for r in ROLES if r in roles}})
    return panels


def summary_table(results: list[dict], metrics: tuple[str, ...] = ("3d_R11@0.5", "3d_R40@0.5")) -> dict:
    """The Pi3DET targets as one table: per platform and label fraction, each detector's
    supervised-only and GDA AP per class, the labeler's val AP, pseudo-boxes and check, and each
    target's provenance (``results``: pi3det-result documents, ``_path`` naming their files)."""
    def ap(scores: dict) -> dict:
        return {c: {m: s[m] for m in metrics} for c, s in scores.items()}

    rows = []
    for doc in sorted(results, key=lambda d: (d["platform"], d["label_percent"])):
        runs = {det: {"real_frames": r["supervised_only"]["train_frames"]["real"],
                      "generated_frames": r["gda"]["train_frames"]["generated"],
                      "iterations": r["supervised_only"]["iterations"],
                      "supervised_only_is_labeler": r["supervised_only"]["is_labeler"],
                      "supervised_only": ap(r["supervised_only"]["ap"]), "gda": ap(r["gda"]["ap"])}
                for det, r in sorted(doc["runs"].items())}
        lab = doc["labeler"]
        rows.append({"platform": doc["platform"], "label_percent": doc["label_percent"], "runs": runs,
                     "labeler": {"val_ap": ap(lab["val_ap"]), "pseudo_boxes": lab["pseudo_boxes"],
                                 "generated_scans": lab["generated_scans"]},
                     "labeler_warning": (doc.get("labeler_check") or {}).get("warning"),
                     "source": {"file": doc.get("_path"), "config_hash": doc.get("config_hash"),
                                "code_hash": doc.get("code_hash"), "data_source": doc.get("data_source"),
                                "seeds": doc.get("seeds"), "created": doc.get("created")}})
    return {"experiment": "pi3det_summary", "metrics": list(metrics), "targets": rows}
