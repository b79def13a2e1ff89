"""The budget study: GDA gain against the generator's training compute, seed-paired, with a trend."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from omnilidar.cli import main
from omnilidar.errors import InputError
from omnilidar.report import budget as bg
from test_downstream_seg import _eval


def _seeded(role, miou, seed, tag="x"):
    doc = _eval("minkunet", role, miou)
    doc["seed"], doc["_path"] = seed, f"{role}_{tag}_{seed}.json"
    return doc


def _write(tmp_path, doc):
    path = tmp_path / doc["_path"]
    path.write_text(json.dumps({k: v for k, v in doc.items() if k != "_path"}))
    return str(path)


def test_trend_predicts_where_a_rising_gain_crosses_each_level():
    budgets = [{"iterations": n, "train_cpu_minutes": m, "gain_over_supervised": {"mean": g}}
               for n, m, g in ((100, 1.0, -0.06), (1000, 10.0, -0.02), (10000, 100.0, 0.02))]
    out = bg.trend(budgets, {"supervised_only": 0.0, "real_pseudo": 0.06})
    assert out["fit"]["slope_per_decade"] == pytest.approx(0.04)
    sup = out["crossings"]["supervised_only"]
    assert sup["first_measured_budget"] == 10000 and sup["first_measured_cpu_minutes"] == 100.0
    assert sup["trend_cpu_minutes"] == pytest.approx(10 ** 1.5) and sup["trend_iterations"] == 3162
    rp = out["crossings"]["real_pseudo"]
    assert rp["first_measured_budget"] is None and rp["trend_cpu_minutes"] == pytest.approx(1000.0)
    flat = bg.trend([{**b, "gain_over_supervised": {"mean": -0.05}} for b in budgets], {"supervised_only": 0.0})
    assert flat["crossings"]["supervised_only"]["trend_cpu_minutes"] is None
    assert "no crossing predicted" in flat["crossings"]["supervised_only"]["note"]


def test_a_rise_within_the_seeds_noise_places_no_crossing():
    """Seeds that scatter more than the means move: the slope is positive but within two standard
    errors of flat, so no crossing is extrapolated; the same means with tight seeds place one."""
    def budgets(spread):
        return [{"iterations": n, "train_cpu_minutes": m,
                 "gain_over_supervised": {"mean": g, "per_seed": [g - spread, g, g + spread]}}
                for n, m, g in ((100, 1.0, -0.09), (300, 3.0, -0.075), (600, 6.0, -0.081), (1000, 10.0, -0.084))]
    noisy = bg.trend(budgets(0.02), {"supervised_only": 0.0})
    assert noisy["fit"]["points"] == 12 and noisy["fit"]["slope_per_decade"] > 0
    assert noisy["fit"]["slope_per_decade"] < 2 * noisy["fit"]["slope_std_error"] and not noisy["fit"]["rises"]
    cross = noisy["crossings"]["supervised_only"]
    assert cross["trend_cpu_minutes"] is None and "within two standard errors of flat" in cross["note"]
    # The earliest crossing the seeds allow: the centre's line at slope + 2 standard errors.
    steepest = noisy["fit"]["slope_per_decade"] + 2 * noisy["fit"]["slope_std_error"]
    assert noisy["fit"]["steepest_slope_per_decade"] == pytest.approx(steepest)
    centre_x = np.mean(np.log10([1.0, 3.0, 6.0, 10.0]))
    assert np.log10(cross["earliest_cpu_minutes"]) == pytest.approx(centre_x + 0.0825 / steepest)
    assert cross["earliest_iterations"] == round(cross["earliest_cpu_minutes"] / 0.01)
    steady = [{**b, "gain_over_supervised": {"mean": g, "per_seed": [g] * 3}}
              for b, g in zip(budgets(0.0), (-0.09, -0.06, -0.045, -0.03))]
    tight = bg.trend(steady, {"supervised_only": 0.0})
    assert tight["fit"]["rises"] and tight["crossings"]["supervised_only"]["trend_cpu_minutes"] > 10.0


def test_budget_command_pairs_seeds_and_writes_result_and_figure(tmp_path, capsys):
    refs = [_seeded("supervised_only", m, s) for s, m in enumerate([0.10, 0.12, 0.11])]
    refs += [_seeded("real_pseudo", m, s) for s, m in enumerate([0.15, 0.16, 0.17])]
    source = '{"semantickitti": {"root": "data/synthetic/semantickitti", "kind": "synthetic"}}'
    args = ["gda-budget", "--settings", "{}", "--seed", "0", "--data-source", source,
            "--evaluations", *[_write(tmp_path, d) for d in refs],
            "--labeler-evaluation", _write(tmp_path, {**_eval("minkunet", "labeler", 0.3), "_path": "lab.json"}),
            "--out", str(tmp_path / "budget.json"), "--figure", str(tmp_path / "budget.png")]
    for n, cpu, gains in ((100, 60.0, [-0.05, -0.04, -0.06]), (1000, 600.0, [0.01, 0.0, 0.02])):
        gen = tmp_path / f"gen{n}.pt"
        torch.save({"iterations": n, "train_seconds": cpu / 2, "train_cpu_seconds": cpu,
                    "config": {"diffusion": {"loss_weighting": "v_uniform", "prior": "domain_mean"}}}, gen)
        quality = tmp_path / f"q{n}.json"
        quality.write_text(json.dumps({"metrics": {"FRD": 100.0 / n, "JSD": 0.3, "MMD": 1e-3}, "n_generated": 4}))
        args += ["--budget", f"{n}={gen}={quality}"]
        for s, g in enumerate(gains):
            args += ["--run", f"{n}={_write(tmp_path, _seeded('gda', [0.10, 0.12, 0.11][s] + g, s, n))}"]
    assert main(args) == 0
    doc = json.loads((tmp_path / "budget.json").read_text())
    low, high = doc["budgets"]
    assert low["gain_over_supervised"]["per_seed"] == pytest.approx([-0.05, -0.04, -0.06])
    assert low["train_cpu_minutes"] == pytest.approx(1.0) and high["train_cpu_minutes"] == pytest.approx(10.0)
    assert high["quality"]["FRD"] == pytest.approx(0.1)
    # The generators' loss weighting travels into the result (two curves can be told apart).
    assert low["loss_weighting"] == "v_uniform" and doc["setup"]["loss_weighting"] == ["v_uniform"]
    assert low["prior"] == "domain_mean" and doc["setup"]["prior"] == ["domain_mean"]
    assert doc["reference"]["real_pseudo_gain"]["mean"] == pytest.approx(0.05)
    assert doc["trend"]["crossings"]["supervised_only"]["first_measured_budget"] == 1000
    assert doc["trend"]["crossings"]["real_pseudo"]["trend_cpu_minutes"] > 10.0
    assert doc["labeler_check"]["students"]["minkunet"]["labeler_stronger"] is True
    assert (tmp_path / "budget.png").stat().st_size > 10_000
    out = capsys.readouterr().out
    assert "1000 it. (10.0 CPU-min): GDA gain 1.00 +- 1.00" in out
    # README's block is written from this file (omnilidar docs).
    from omnilidar.report.readme import gda_budget

    block = gda_budget(doc)
    assert "| 1000 | 10.0 | 0.1 | 0.3 | 0.001 | 1.00 +- 1.00 |" in block
    assert "- supervised only level (0.00): reached at 1000 iterations." in block
    assert "Generator loss weighting `v_uniform`, prior `domain_mean`. Supervised only" in block
    assert "- real pseudo level (5.00): not reached in the measured range; the trend" in block
    # A budget's runs with other seeds than the reference rows: one clear error, no result.
    (tmp_path / "budget.json").unlink()
    bad = [a if "gda_1000_2" not in a else a.replace("gda_1000_2", "gda_1000_1") for a in args]
    assert main(bad) != 0 and not (tmp_path / "budget.json").exists()


def test_a_generator_without_its_training_cost_is_refused():
    with pytest.raises(InputError, match="train_cpu_seconds"):
        bg.budget_record(100, {"path": "g.pt"}, {"metrics": {}, "n_generated": 2},
                         [_seeded("gda", 0.1, 0)], {"seeds": [0], "miou": [0.1]}, {"seeds": [0], "miou": [0.1]})


def test_an_earliest_crossing_out_of_any_reach_reads_as_such():
    """README's budget lines: a crossing the seeds place beyond 1e12 iterations is said to be out of
    reach, not printed as a 38-digit budget; a reachable one keeps its number."""
    from pathlib import Path

    from omnilidar.report.readme import gda_budget

    results = Path(__file__).resolve().parents[1] / "docs" / "results"
    flat = gda_budget(json.loads((results / "gda_budget_prior.json").read_text()))
    assert "reaches it beyond 1e12 iterations" in flat and "e+37" not in flat
    rising = json.loads((results / "gda_budget.json").read_text())
    cross = rising["trend"]["crossings"]["supervised_only"]
    assert cross["earliest_iterations"] < 1e12
    assert f"no earlier than {cross['earliest_iterations']:.3g} iterations" in gda_budget(rising)
