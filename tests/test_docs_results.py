"""README and docs quote result files through `omnilidar docs`: blocks are rewritten from the JSON
files, and a page that disagrees with its files fails the check."""

from __future__ import annotations

import json
import re
import tempfile
from pathlib import Path

import pytest

from omnilidar.cli import main
from omnilidar.report import readme

ROOT = Path(__file__).resolve().parents[1]


def _semkitti():
    def run(sup, gda):
        stats = lambda v: {"miou_mean": sum(v) / len(v), "miou_std": 0.01, "miou": v}  # noqa: E731
        return {"supervised_only": {"across_seeds": stats(sup)}, "gda": {"across_seeds": stats(gda)}, "seeds": len(sup),
                "miou_gain_per_seed": [g - s for g, s in zip(gda, sup)]}

    return {"runs": {"minkunet": run([0.10, 0.12], [0.13, 0.14])},
            "labeler": {"val_miou": 0.25, "val_iou": {"car": 0.8}},
            "labeler_check": {"compared": True, "warning": None}}


def test_blocks_are_rewritten_from_their_result_files_and_checked(tmp_path):
    (tmp_path / "semkitti_1pct.json").write_text(json.dumps(_semkitti()))
    page = tmp_path / "page.md"
    page.write_text("intro\n<!-- results:semkitti_1pct -->\nstale 99.99\n<!-- /results:semkitti_1pct -->\nend\n")
    assert main(["docs", str(page), "--results", str(tmp_path), "--check"]) == 1
    assert "stale" in page.read_text()  # --check changes nothing
    assert main(["docs", str(page), "--results", str(tmp_path)]) == 0
    text = page.read_text()
    assert "| minkunet | 2 | 11.00 +- 1.00 | 13.50 +- 1.00 | 3.00, 2.00 |" in text and "stale" not in text
    assert "val mIoU 25.00, car IoU 80.0; stronger than every student it labels for." in text
    assert text.startswith("intro\n") and text.endswith("<!-- /results:semkitti_1pct -->\nend\n")
    assert main(["docs", str(page), "--results", str(tmp_path), "--check"]) == 0
    # A block without its result file, or of an unknown kind: one clear error.
    page.write_text("<!-- results:gda_budget -->\n<!-- /results:gda_budget -->\n")
    assert main(["docs", str(page), "--results", str(tmp_path)]) != 0
    page.write_text("<!-- results:nonsense -->\n<!-- /results:nonsense -->\n")
    with pytest.raises(Exception, match="unknown results block"):
        readme.render_page(page.read_text(), tmp_path, page)


def test_an_earlier_decomposition_kept_under_its_own_name_renders_as_a_decomposition():
    """gda_decomposition_<name> blocks (an earlier run kept beside today's) use the decomposition's table."""
    results = ROOT / "docs" / "results"
    doc = json.loads((results / "gda_decomposition.json").read_text())
    page = "<!-- results:gda_decomposition_old -->\n<!-- /results:gda_decomposition_old -->\n"
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "gda_decomposition_old.json").write_text(json.dumps(doc))
        text = readme.render_page(page, Path(tmp))
    assert readme.gda_decomposition(doc).rstrip() in text


def test_a_short_student_check_renders_the_student_s_row_and_verdicts_alone():
    text = "<!-- results:student_1step_best_teacher.short -->\n<!-- /results:student_1step_best_teacher.short -->\n"
    short = readme.render_page(text, ROOT / "docs" / "results")
    full = readme.render_page(text.replace(".short", ""), ROOT / "docs" / "results")
    rows = [line for line in short.splitlines() if line.startswith("| ") and not line.startswith("| sampler")]
    assert len(rows) == 1 and rows[0].startswith("| student | 1 |") and rows[0] in full
    assert "- JSD: the 1-step student" in short and "- MMD: the 1-step student" in short and "- Speed:" in short
    assert "The teacher's" not in short and "The teacher's" in full


def test_the_speed_line_says_whether_the_study_timed_its_rows_side_by_side():
    """A study that timed every setting in its own job says so; an earlier one, whose rows carry the
    sets' own sampling times, says that instead."""
    doc = json.loads((ROOT / "docs" / "results" / "student_1step_best_teacher.json").read_text())
    earlier = [line for line in readme.student_check(doc).splitlines() if line.startswith("- Speed:")]
    for p in doc["points"]:
        p["set_seconds_per_scan"] = p["seconds_per_scan"]
    timed = [line for line in readme.student_check(doc).splitlines() if line.startswith("- Speed:")]
    assert len(earlier) == len(timed) == 1
    assert "each row timed by its own sampling job" in earlier[0] and "side by side" in timed[0]


def test_a_student_calibrated_on_candidates_says_which_setting_each_domain_took_and_the_scans_it_was_scored_on():
    text = "<!-- results:student_1step_candidates_heldout.short -->\n<!-- /results:student_1step_candidates_heldout.short -->\n"
    short = readme.render_page(text, ROOT / "docs" / "results")
    doc = json.loads((ROOT / "docs" / "results" / "student_1step_candidates_heldout.json").read_text())
    chosen = doc["student"]["calibration_sampler"]
    line = next(line for line in short.splitlines() if line.startswith("- Its returns and ranges calibrated on"))
    for setting in set(chosen.values()):
        domains = ", ".join(d for d, s in chosen.items() if s == setting)
        assert f"{setting.replace(':', ' x ')} in {domains}" in line
    assert "held-out real scans per domain (pi3det drone_val, pi3det quadruped_val, semantickitti val)" in short


def test_a_student_calibrated_per_azimuth_sector_says_so():
    doc = json.loads((ROOT / "docs" / "results" / "student_1step_candidates_heldout.json").read_text())
    assert "azimuth sectors" not in readme.student_check(doc)  # per row: nothing to say
    doc["student"]["calibration_sectors"] = 8
    line = next(line for line in readme.student_check(doc).splitlines()
                if line.startswith("- Its returns and ranges calibrated on"))
    assert line.endswith(", per image row in each of 8 azimuth sectors.")
    doc["student"]["calibration_rule"] = "first_holding"  # the rule that chose each domain's setting
    line = next(line for line in readme.student_check(doc).splitlines()
                if line.startswith("- Its returns and ranges calibrated on"))
    assert line.endswith("azimuth sectors (each domain's first candidate whose teacher scans hold the best of each "
                         "metric on its training scans).")
    doc["student"]["calibration_sampler"] = "ddpm:32"  # one setting for every domain
    assert "- Its returns and ranges calibrated, per image row in each of 8 azimuth sectors." in \
        readme.student_check(doc).splitlines()


def test_readme_and_docs_agree_with_the_results_kept_in_docs():
    """Every number README and docs/ quote in a results block is what docs/results/*.json holds."""
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    assert sum("<!-- results:" in p.read_text() for p in pages) >= 3
    assert main(["docs", *map(str, pages), "--results", str(ROOT / "docs" / "results"), "--check"]) == 0


def test_readme_is_a_front_door():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) < 200
    for link in set(re.findall(r"\]\((docs/[^)#]+)\)", text)):
        assert (ROOT / link).is_file(), link


def test_a_short_block_renders_the_same_file_in_one_line(tmp_path):
    doc = {"target": "results/semkitti_1pct.json", "commit": "abc1234", "elapsed_seconds": 1158.0, "jobs": 63,
           "disk_mb": {"data": 1024.0, "work": 512.0},
           "job_seconds": {"cpu": 120.0, "wall": 150.0, "by_folder": {"downstream/train": {"jobs": 2, "cpu": 120.0,
                                                                                            "wall": 150.0}}}}
    (tmp_path / "run_cost.json").write_text(json.dumps(doc))
    page = tmp_path / "page.md"
    page.write_text("<!-- results:run_cost.short -->\n<!-- /results:run_cost.short -->\n"
                    "<!-- results:run_cost -->\n<!-- /results:run_cost -->\n")
    assert main(["docs", str(page), "--results", str(tmp_path)]) == 0
    short, full = page.read_text().split("<!-- results:run_cost -->")
    assert "19 min 18 s, 63 jobs" in short and "1.5 GB on disk" in short and "|" not in short
    assert "| `downstream/train` | 2 | 2.0 | 2.5 |" in full and "The jobs held 2.0 CPU-minutes" in full


def test_a_target_built_after_another_says_so_and_adds_the_runs(tmp_path):
    """run_cost.py --after: the clone built the quick start first, was interrupted once, then built the rest."""
    runs = [{"target": "results/semkitti_1pct.json", "log": "a.log", "elapsed_seconds": 1548.0, "jobs": 63},
            {"target": None, "log": "b.log", "elapsed_seconds": 335.0, "jobs": 2},
            {"target": "results/gda_decomposition.json", "log": "c.log", "elapsed_seconds": 4800.0, "jobs": 88}]
    doc = {"target": "results/gda_decomposition.json", "commit": "abc1234", "elapsed_seconds": 6683.0, "jobs": 153,
           "runs": runs, "disk_mb": {"data": 1024.0}}
    (tmp_path / "run_cost.json").write_text(json.dumps(doc))
    page = tmp_path / "page.md"
    page.write_text("<!-- results:run_cost.short -->\n<!-- /results:run_cost.short -->\n")
    assert main(["docs", str(page), "--results", str(tmp_path)]) == 0
    assert ("`results/gda_decomposition.json` from a clean clone in 3 runs (`results/semkitti_1pct.json` 25 min 48 s, "
            "an interrupted run 5 min 35 s, then the rest 80 min 00 s) (commit abc1234): 111 min 23 s, 153 jobs"
            ) in page.read_text()


def test_run_cost_adds_the_runs_a_target_was_built_in(tmp_path):
    """benchmarks/run_cost.py on a clone's Snakemake logs: the quick start's run, an interrupted run, the rest."""
    import subprocess
    import sys

    logs = tmp_path / "run" / ".snakemake" / "log"
    logs.mkdir(parents=True)

    def log(name, start, end, output, jobs):
        finished = "".join(f"Finished jobid: {i}\n" for i in range(jobs))
        (logs / name).write_text(f"[Sat Nov 28 {start} 2026]\nrule x:\n    output: {output}\n{finished}"
                                 f"[Sat Nov 28 {end} 2026]\n")

    log("2026-11-28T1000.snakemake.log", "10:00:00", "10:25:48", "results/semkitti_1pct.json", 63)
    log("2026-11-28T1100.snakemake.log", "11:00:00", "11:05:35", "data/a.pt", 2)
    log("2026-11-28T1200.snakemake.log", "12:00:00", "13:20:00", "results/gda_decomposition.json", 88)
    out = tmp_path / "run_cost.json"
    subprocess.run([sys.executable, "benchmarks/run_cost.py", "--run-dir", str(tmp_path / "run"), "--target",
                    "results/gda_decomposition.json", "--after", "results/semkitti_1pct.json",
                    "--after", "2026-11-28T1100.snakemake.log", "--out", str(out), "--commit", "abc1234",
                    "--machine", "one NVIDIA H200 GPU with 16 CPU cores"], cwd=ROOT, check=True, capture_output=True)
    doc = json.loads(out.read_text())
    assert doc["elapsed_seconds"] == 1548 + 335 + 4800 and doc["jobs"] == 63 + 2 + 88
    # A run directory without git history (a copy on another machine) takes the commit it is given.
    assert doc["commit"] == "abc1234" and doc["machine"] == "one NVIDIA H200 GPU with 16 CPU cores"
    (tmp_path / "page.md").write_text("<!-- results:run_cost.short -->\n<!-- /results:run_cost.short -->\n")
    assert main(["docs", str(tmp_path / "page.md"), "--results", str(tmp_path)]) == 0
    assert "153 jobs, on one NVIDIA H200 GPU with 16 CPU cores, install excluded" in (tmp_path / "page.md").read_text()
    assert [r["target"] for r in doc["runs"]] == ["results/semkitti_1pct.json", None, "results/gda_decomposition.json"]


def test_a_benchmark_writes_the_result_file_its_docs_table_is_rendered_from(tmp_path):
    """A real (tiny) benchmark run with --out: its rows, the command without --out, and the page."""
    import subprocess
    import sys

    out = tmp_path / "bench_kernel_map.json"
    subprocess.run([sys.executable, "benchmarks/bench_kernel_map.py", "--voxels", "2000", "--repeats", "1",
                    "--out", str(out)], cwd=ROOT, check=True, capture_output=True)
    doc = json.loads(out.read_text())
    assert doc["command"] == "python benchmarks/bench_kernel_map.py --voxels 2000 --repeats 1"
    (row,) = doc["rows"]
    assert row["what"].startswith("submanifold 3^3 kernel map of 2k voxels") and " vs " in row["median"]
    assert doc["figures"]["maps"][0]["same_pairs"] is True and doc["machine"]["cpus"] >= 1
    page = tmp_path / "page.md"
    page.write_text("<!-- results:bench_kernel_map -->\n<!-- /results:bench_kernel_map -->\n")
    assert main(["docs", str(page), "--results", str(tmp_path)]) == 0
    text = page.read_text()
    assert f"| {row['what']} | {row['median']} |  |" in text
    assert f"`{doc['command']}` (commit {doc['commit']}" in text


def test_a_benchmark_with_its_own_columns_renders_them(tmp_path):
    """bench_parameters: a table whose columns are its own (part, one per text encoder, reference)."""
    import subprocess
    import sys

    out = tmp_path / "bench_parameters.json"
    subprocess.run([sys.executable, "benchmarks/bench_parameters.py", "--config", "config/config.yaml",
                    "--text-dims", "384", "--out", str(out)], cwd=ROOT, check=True, capture_output=True)
    doc = json.loads(out.read_text())
    assert doc["columns"] == ["part", "text tokens of 384", "reference"]
    counts = doc["figures"]["parameters"]["384"]
    assert counts["total"] == sum(v for k, v in counts.items() if k != "total") and counts["cdfm"] > 0
    page = tmp_path / "page.md"
    page.write_text("<!-- results:bench_parameters -->\n<!-- /results:bench_parameters -->\n")
    assert main(["docs", str(page), "--results", str(tmp_path)]) == 0
    text = page.read_text()
    assert "| part | text tokens of 384 | reference |\n|---|---|---|" in text
    assert f"| total | {counts['total'] / 1e6:.2f} M | the paper's OmniLiDAR 97.73 M |" in text


def test_domain_reports_render_every_effect_beside_its_anchor_and_every_knob_with_its_default():
    fidelity = json.loads((ROOT / "docs/results/domain_fidelity.json").read_text())
    text = readme.domain_fidelity(fidelity)
    for effect in fidelity["effects"]:
        assert f"| {effect.replace('_', ' ')} |" in text
    assert "of ground" in text.split("| wet ground |")[1].split("\n")[0]  # wet ground loses ground points
    assert "LISA (Kilic 2021) / TripleMixer: every zero-remission point lost; 7-9 s per scan" in text
    tradeoff = json.loads((ROOT / "docs/results/effects_tradeoff.json").read_text())
    text = readme.effects_tradeoff(tradeoff)
    knobs = {(e, r["knob"]) for e, s in tradeoff["effects"].items() for r in s["rows"]}
    assert text.count("\n| ") == len(knobs)  # one row per effect and knob
    defaults = [r for s in tradeoff["effects"].values() for r in s["rows"] if r["is_default"]]
    assert text.count("**") == 2 * len(defaults) and defaults


def test_the_sampler_grid_names_the_best_solver_per_budget_and_the_students_check():
    doc = json.loads((ROOT / "docs/results/student_check.json").read_text())
    text = readme.sampler_grid(doc)
    rows = [line for line in text.splitlines() if re.match(r"\| \d+ \|", line)]
    assert [int(r.split("|")[1]) for r in rows] == sorted(int(b) for b in doc["best_per_budget"])
    best = doc["best_per_budget"]["20"]["JSD"]
    assert f"{best['sampler']}: {best['value']:.4g} +- {best['std']:.2g}" in rows[-1]
    assert "the 2-step student is within two standard deviations" in text and "Recommended" in text


def test_the_sampler_grid_names_its_real_scans_and_the_teacher_settings_that_hold_every_domain():
    import copy

    doc = json.loads((ROOT / "docs/results/sampler_grid.json").read_text())
    text = readme.sampler_grid(doc)
    assert "held-out real scans per domain" in text and "training scans" not in text
    line = next(row for row in text.splitlines() if row.startswith("- Teacher settings within"))
    held = line.split(": ", 1)[1].split(" (of ")[0].split(", ")
    checks = doc["teacher_settings_check"]
    assert held and all(not v["missed"] for s in held for v in checks[s].values())
    assert not any("by the same rule" in row for row in text.splitlines())  # one line, not one per setting
    # A held setting that misses one domain leaves the line; the training-scan phrase returns without
    # a held-out reference.
    worse = copy.deepcopy(doc)
    worse["teacher_settings_check"][held[0]]["JSD"]["missed"] = {"Fog": 0.1}
    worse.pop("reference")
    text = readme.sampler_grid(worse)
    assert held[0] + "," not in text and not text.rstrip().endswith(f": {held[0]} (of {len(checks)}).")
    assert "of each domain's training scans (the generator's own)" in text


def test_step_times_reads_each_trainers_logged_steps_and_divergence(tmp_path):
    """benchmarks/step_times.py on a run's job logs: per trainer the logged step times, the jobs whose
    loss went non-finite, and the machine the run happened on (not this one)."""
    import subprocess
    import sys

    def log(path, times, diverged=False):
        path.parent.mkdir(parents=True, exist_ok=True)
        lines = [f"11/28 18:00:{i:02d} - mmengine - INFO - Iter(train) [{5 * i:3d}/200]  lr: 1e-2  eta: 0:01:00  "
                 f"time: {t:.4f}  data_time: 0.01  loss: 1.0" for i, t in enumerate(times, 1)]
        if diverged:
            lines.append("FloatingPointError: training diverged (non-finite loss); lower schedule.lr")
        path.write_text("\n".join(lines) + "\n")

    log(tmp_path / "logs/generator/train_full.log", [1.0, 1.2, 1.4])
    log(tmp_path / "logs/downstream/train/semantickitti_spvcnn_1pct_study-truth48_seed0.log", [1.5, 1.7], diverged=True)
    log(tmp_path / "logs/downstream/train/semantickitti_spvcnn_1pct_study-real48_seed0.log", [1.6, 1.6, 1.6])
    out = tmp_path / "bench_step_times_gpu.json"
    subprocess.run([sys.executable, "benchmarks/step_times.py", "--run-dir", str(tmp_path), "--machine-gpu",
                    "NVIDIA H200", "--machine-cpus", "16", "--torch", "2.11.0", "--out", str(out)],
                   cwd=ROOT, check=True, capture_output=True)
    doc = json.loads(out.read_text())
    assert set(doc["figures"]) == {"generator", "SPVCNN student"}
    assert doc["figures"]["generator"]["median_s"] == 1.2
    spvcnn = doc["figures"]["SPVCNN student"]
    assert spvcnn["jobs"] == 2 and spvcnn["diverged"] == {"semantickitti_spvcnn_1pct_study-truth48_seed0.log": 10}
    assert doc["machine"] == {"cpus": 16, "processor": "x86_64", "torch": "2.11.0", "gpu": "NVIDIA H200"}
    (tmp_path / "page.md").write_text("<!-- results:bench_step_times_gpu -->\n<!-- /results:bench_step_times_gpu -->\n")
    assert main(["docs", str(tmp_path / "page.md"), "--results", str(tmp_path)]) == 0
    assert "1 diverged (non-finite loss) after iteration 10-10" in (tmp_path / "page.md").read_text()
    assert "one NVIDIA H200, 16 CPUs" in (tmp_path / "page.md").read_text()


def test_run_cost_compares_the_jobs_an_earlier_run_also_has(tmp_path):
    """run_cost.py --reference: per group of benchmark files, the wall seconds of the jobs both runs have
    (jobs only one run has are left out), their ratio, and a table in the page."""
    import subprocess
    import sys

    def run(name, walls):
        root = tmp_path / name
        (root / ".snakemake" / "log").mkdir(parents=True)
        (root / ".snakemake" / "log" / "a.snakemake.log").write_text(
            "[Sat Nov 28 10:00:00 2026]\nrule x:\n    output: results/semkitti_1pct.json\nFinished jobid: 1\n"
            "[Sat Nov 28 10:20:00 2026]\n")
        for job, wall in walls.items():
            tsv = root / "benchmarks" / "out" / job
            tsv.parent.mkdir(parents=True, exist_ok=True)
            tsv.write_text(f"s\th:m:s\tcpu_time\n{wall}\t0:00:00\t{wall}\n")
        return root

    here = run("here", {"train/minkunet_a.tsv": 150, "train/minkunet_b.tsv": 160, "train/spvcnn_a.tsv": 200,
                        "labeler.tsv": 450, "only_here.tsv": 9})
    there = run("there", {"train/minkunet_a.tsv": 120, "train/minkunet_b.tsv": 130, "train/spvcnn_a.tsv": 250,
                          "labeler.tsv": 500})
    out = tmp_path / "run_cost.json"
    subprocess.run([sys.executable, "benchmarks/run_cost.py", "--run-dir", str(here), "--reference", str(there),
                    "--group", "MinkUNet=train/*minkunet*", "--group", "SPVCNN=train/*spvcnn*", "--group",
                    "labeler=labeler.tsv", "--group", "none=missing/*", "--out", str(out), "--commit", "new1234"],
                   cwd=ROOT, check=True, capture_output=True)
    ref = json.loads(out.read_text())["against_reference"]
    assert ref["groups"] == {"MinkUNet": {"jobs": 2, "wall": 310.0, "reference_wall": 250.0, "ratio": 1.24},
                             "SPVCNN": {"jobs": 1, "wall": 200.0, "reference_wall": 250.0, "ratio": 0.8},
                             "labeler": {"jobs": 1, "wall": 450.0, "reference_wall": 500.0, "ratio": 0.9}}
    page = tmp_path / "page.md"
    page.write_text("<!-- results:run_cost -->\n<!-- /results:run_cost -->\n")
    assert main(["docs", str(page), "--results", str(tmp_path)]) == 0
    assert "| MinkUNet | 2 | 5.2 | 4.2 | 1.24 |" in page.read_text()
    # Without groups, one per folder (or top-level file) of the jobs both runs have.
    subprocess.run([sys.executable, "benchmarks/run_cost.py", "--run-dir", str(here), "--reference", str(there),
                    "--out", str(out)], cwd=ROOT, check=True, capture_output=True)
    assert set(json.loads(out.read_text())["against_reference"]["groups"]) == {"train", "labeler.tsv"}


def test_a_student_check_names_how_each_teacher_setting_holds_the_best():
    from omnilidar.commands.sampler_tradeoff import teacher_settings_check

    doc = json.loads((ROOT / "docs/results/student_pruned_1step_check12.json").read_text())
    assert "teacher_settings_check" not in doc  # an earlier run's file renders as before
    plain = readme.student_check(doc)
    doc["teacher_settings_check"] = teacher_settings_check(doc["points"], doc["metrics"])
    text = readme.student_check(doc)
    lines = [line for line in text.splitlines() if line.startswith("- The teacher's ")]
    assert len(lines) == len(doc["points"]) - 1 and text.startswith(plain.split("- Speed")[0])
    best = doc["student_check"]["metrics"]["JSD"]["teacher_best"]
    assert f"- The teacher's {best['sampler']} x {best['steps']} by the same rule: JSD in 8 of 8" in text
