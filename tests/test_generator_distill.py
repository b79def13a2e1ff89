"""Progressive and consistency distillation: the targets' algebra, real tiny distillation runs,
resume, provenance, sampling with the student in every domain, and the workflow's wiring."""

from __future__ import annotations

import copy
import json
import re
import shutil

import numpy as np
import pytest
import torch

from omnilidar.errors import InputError
from omnilidar.generator.checkpoint import load_generator
from omnilidar.generator.diffusion import generate
from omnilidar.generator.distill import (_grid_logsnr, compression_loss, consistency_loss, ddim_move, distillation_loss,
                                        two_step_target)
from omnilidar.generator.distill_steps import compression_iterations, round_at, round_iterations, student_sampler, student_steps
from omnilidar.generator.samplers import SPACINGS, make_scheduler, time_grid
from omnilidar.generator.sampling import sample_shard, student_sampling
from omnilidar.generator.schedule import BF16_MIN_LOGSNR, CosineLogSNRSchedule, alpha_sigma, bf16_safe, predict_x0
from omnilidar.generator.text import build_prompt_cache, load_prompt_cache
from omnilidar.generator.training import _CALIBRATION_KEYS, train_generator
from test_generator_fixtures import TINY_DOMAINS, make_domains, one_torch_thread, tiny_settings  # noqa: F401
from test_generator_training import FakeEncoder
from workflow_helpers import copy_workflow, planned_jobs, snakemake

DISTILL = {"teacher_steps": 4, "rounds": 2, "iterations_per_round": 2, "lr": 1e-3}


def distill_settings(**distillation) -> dict:
    s = tiny_settings()
    s["training"].update(iterations=4, checkpoint_interval=1)
    s["distillation"].update(DISTILL, **distillation)
    return s


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    root = tmp_path_factory.mktemp("distill")
    settings = distill_settings()
    index = make_domains(root, settings)
    prompts = root / "prompts.pt"
    torch.save(build_prompt_cache(settings["prompts"], FakeEncoder()), prompts)
    train_generator(settings, index, prompts, root / "teacher_work", root / "model.pt", seed=3)
    student = train_generator(settings, index, prompts, root / "student_work", root / "student.pt", seed=3,
                              teacher=root / "model.pt")
    return root, settings, index, prompts, student


def _state(path):
    return torch.load(path, map_location="cpu", weights_only=True)["state_dict"]


def test_one_student_step_lands_where_two_teacher_steps_do():
    g = torch.Generator().manual_seed(0)
    z_t = torch.randn(3, 2, 4, 8, generator=g)
    x0a, x0b = (torch.rand(3, 2, 4, 8, generator=g) * 2 - 1 for _ in range(2))
    l_t, l_mid, l_end = torch.tensor([-15.0, -2.0, 3.0]), torch.tensor([-6.0, 1.0, 6.0]), torch.tensor([-1.0, 4.0, 15.0])
    z_end = ddim_move(x0b, ddim_move(x0a, z_t, l_t, l_mid), l_mid, l_end)
    target = two_step_target(z_t, z_end, l_t, l_end)
    torch.testing.assert_close(ddim_move(target, z_t, l_t, l_end), z_end, atol=1e-4, rtol=1e-4)


class PointMass(torch.nn.Module):
    """The exact denoiser of data that is one image ``c``: its x0 estimate is always ``c``."""

    def __init__(self, c: torch.Tensor):
        super().__init__()
        self.c = c

    def forward(self, z, logsnr, domain, tokens, mask, columns=None):
        a, s = alpha_sigma(logsnr.double())
        c = self.c if columns is None else torch.gather(self.c.expand(len(z), -1, -1, -1), 3,
                                                        columns[:, None, None, :].expand(-1, *z.shape[1:3], -1))
        return ((z.double() - a[:, None, None, None] * c) / s[:, None, None, None]).float()


@pytest.mark.parametrize("spacing", SPACINGS)
@pytest.mark.parametrize("crop_width", [None, 4])
def test_the_exact_teacher_teaches_itself_and_a_wrong_student_pays_its_error(crop_width, spacing):
    c = torch.linspace(-0.5, 0.5, 2 * 4 * 8).reshape(1, 2, 4, 8)
    image = c.expand(3, -1, -1, -1).clone()
    args = (image, torch.zeros(3, dtype=torch.long), torch.zeros(3, 2, 5), torch.ones(3, 2, dtype=torch.bool),
            CosineLogSNRSchedule(), 2)
    exact = PointMass(c)
    loss = distillation_loss(exact, exact, *args, torch.Generator().manual_seed(1), crop_width=crop_width,
                             spacing=spacing)
    assert float(loss) < 1e-6
    wrong = distillation_loss(PointMass(c + 0.1), exact, *args, torch.Generator().manual_seed(1), crop_width=crop_width,
                              spacing=spacing)
    assert float(wrong) >= 0.01 * (1 - 1e-3)  # x0 off by 0.1 everywhere, weight max(SNR, 1) >= 1


@pytest.mark.parametrize("spacing", SPACINGS)
def test_the_student_trains_on_the_grid_its_ddim_sampler_walks(spacing):
    """Step k of an n-step student starts and ends where the n-step DDIM sampler of that spacing
    does, and its midpoint is the 2n-step grid's: what a round teaches is what sampling walks."""
    schedule, n = CosineLogSNRSchedule(), 4
    index = torch.arange(n, 0, -1)  # the sampler's order: from noise (index n) to data (index 1)
    start, mid, end = _grid_logsnr(schedule, n, spacing, index, (0, 1, 2))
    sampler = make_scheduler(student_sampler({"spacing": spacing}), schedule)
    sampler.set_timesteps(n)
    walked = schedule.logsnr(time_grid(schedule, n, spacing))
    torch.testing.assert_close(start, walked[:-1])
    torch.testing.assert_close(end, walked[1:])
    torch.testing.assert_close(mid, schedule.logsnr(time_grid(schedule, 2 * n, spacing))[1::2])
    torch.testing.assert_close(sampler._logsnr, walked)
    if spacing != "uniform":  # another grid than uniform in t: the four steps' starts differ from it
        assert not torch.allclose(start, _grid_logsnr(schedule, n, "uniform", index, (0,))[0])


@pytest.mark.parametrize("crop_width", [None, 4])
def test_consistency_the_exact_denoiser_is_consistent_and_the_boundary_pins_a_wrong_one(crop_width):
    """The exact denoiser's x0 is c at every t, so it agrees with itself one step later; at s = 0 the
    target is the teacher's landing (about c), so a student whose x0 is off by 0.1 pays there."""
    c = torch.linspace(-0.5, 0.5, 2 * 4 * 8).reshape(1, 2, 4, 8)
    image = c.expand(3, -1, -1, -1).clone()
    args = (image, torch.zeros(3, dtype=torch.long), torch.zeros(3, 2, 5), torch.ones(3, 2, dtype=torch.bool),
            CosineLogSNRSchedule())
    exact = PointMass(c)
    assert float(consistency_loss(exact, exact, *args, 4, torch.Generator().manual_seed(1), crop_width=crop_width)) < 1e-5
    wrong = consistency_loss(PointMass(c + 0.1), exact, *args, 1, torch.Generator().manual_seed(1), crop_width=crop_width)
    assert float(wrong) >= 0.01 * 0.9  # every draw is at the boundary on a one-step grid


def test_a_student_distilled_on_another_spacing_samples_with_ddim_on_it(teacher, tmp_path):
    root, settings, index, prompts, _ = teacher
    other = copy.deepcopy(settings)
    other["distillation"]["spacing"] = "logsnr"
    train_generator(other, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                    teacher=root / "model.pt")
    den, payload = load_generator(tmp_path / "student.pt")
    assert payload["student"]["sampler"] == "ddim_logsnr"
    uniform, logsnr = _state(root / "student.pt"), _state(tmp_path / "student.pt")
    assert not all(torch.equal(uniform[k], logsnr[k]) for k in uniform)
    sampling = student_sampling(dict(settings["sampling"], student=True), payload, tmp_path / "student.pt")
    assert (sampling["sampler"], sampling["steps"]) == ("ddim_logsnr", 1)
    stats = sample_shard(den, payload, load_prompt_cache(prompts), "Fog", 0, 2, sampling, 5, tmp_path / "Fog",
                         log=lambda *_: None)
    assert stats["generated"] == 2


def test_a_tiny_consistency_distillation_writes_its_student(teacher, tmp_path):
    root, settings, index, prompts, _ = teacher
    cd = copy.deepcopy(settings)
    cd["distillation"]["method"] = "consistency"
    summary = train_generator(cd, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                              teacher=root / "model.pt")
    assert summary["iterations"] == 4
    payload = torch.load(tmp_path / "student.pt", map_location="cpu", weights_only=True)
    assert payload["student"]["method"] == "consistency" and payload["student"]["steps"] == 1
    progressive, consistency = _state(root / "student.pt"), _state(tmp_path / "student.pt")
    assert not all(torch.equal(progressive[k], consistency[k]) for k in progressive)


def test_a_tiny_distillation_writes_a_one_step_student(teacher):
    root, settings, _, _, summary = teacher
    assert summary["iterations"] == 4 and summary["resumed_from"] == 0
    payload = torch.load(root / "student.pt", map_location="cpu", weights_only=True)
    assert payload["student"] == {"sampler": "ddim", "steps": 1, "teacher": str(root / "model.pt"),
                                  "teacher_steps": 4, "teacher_substeps": 1, "rounds": 2, "method": "progressive",
                                  "return_calibration": 0, "range_calibration": 0, "calibration_sectors": 1,
                                  "calibration_rule": "closest",
                                  "calibration_sampler": "ddim:4"}
    assert "return_thresholds" not in payload and "range_map" not in payload  # uncalibrated by default
    assert student_steps(settings["distillation"]) == 1
    prov = payload["provenance"]
    assert prov["command"] == "distill-generator" and set(prov["inputs"]) == {"domains", "prompts", "teacher"}
    assert payload["domains"] == list(TINY_DOMAINS) and payload["config"] == settings
    teacher_state, student_state = _state(root / "model.pt"), _state(root / "student.pt")
    assert teacher_state.keys() == student_state.keys()
    assert not all(torch.equal(teacher_state[k], student_state[k]) for k in teacher_state)
    # The teacher's own checkpoint says nothing about distillation: its provenance leaves that section out.
    assert "distillation" not in torch.load(root / "model.pt", weights_only=True)["provenance"]["settings"]


def test_the_student_samples_every_domain_in_its_own_steps(teacher, tmp_path):
    root, settings, _, prompts, _ = teacher
    den, payload = load_generator(root / "student.pt")
    asked = dict(settings["sampling"], student=True, sampler="dpmpp_2m", steps=20)
    sampling = student_sampling(asked, payload, root / "student.pt")
    assert (sampling["sampler"], sampling["steps"]) == ("ddim", 1)
    cache = load_prompt_cache(prompts)
    images = {}
    for domain in TINY_DOMAINS:
        stats = sample_shard(den, payload, cache, domain, 0, 2, sampling, 5, tmp_path / domain, log=lambda *_: None)
        assert stats["generated"] == 2
        images[domain] = np.load(tmp_path / domain / "range" / "000000.npz")["image"]
    # Same seed, different domain and prompt: the conditioning still steers the one-step student.
    assert not np.array_equal(images["Vehicle"], images["Fog"])
    with pytest.raises(InputError, match="not a distilled student"):
        student_sampling(asked, load_generator(root / "model.pt")[1], root / "model.pt")


def test_compression_the_teacher_teaches_itself_and_a_wrong_student_pays_its_error():
    c = torch.linspace(-0.5, 0.5, 2 * 4 * 8).reshape(1, 2, 4, 8)
    args = (c.expand(3, -1, -1, -1).clone(), torch.zeros(3, dtype=torch.long), torch.zeros(3, 2, 5),
            torch.ones(3, 2, dtype=torch.bool), CosineLogSNRSchedule(), 4)
    assert float(compression_loss(PointMass(c), PointMass(c), *args, torch.Generator().manual_seed(1))) < 1e-6
    wrong = compression_loss(PointMass(c + 0.1), PointMass(c), *args, torch.Generator().manual_seed(1))
    assert float(wrong) >= 0.01 * (1 - 1e-3)


@pytest.fixture(scope="module")
def narrow_student(teacher, tmp_path_factory):
    """A student half its trained generator's width: compression first, then the rounds."""
    _, settings, index, prompts, _ = teacher
    narrow = copy.deepcopy(settings)
    narrow["model"]["base_channels"] = 2 * settings["model"]["base_channels"]
    narrow["distillation"].update(student_channels=settings["model"]["base_channels"], compression_iterations=3)
    work = tmp_path_factory.mktemp("narrow")
    train_generator(narrow, index, prompts, work / "teacher_work", work / "model.pt", seed=3)
    summary = train_generator(narrow, index, prompts, work / "work", work / "student.pt", seed=3,
                              teacher=work / "model.pt")
    return narrow, work, summary


def test_a_narrower_student_learns_the_generator_first_then_the_rounds_and_samples(teacher, narrow_student, tmp_path):
    _, settings, index, prompts, _ = teacher
    narrow, work, summary = narrow_student
    assert summary["iterations"] == 3 + 2 * 2
    den, payload = load_generator(work / "student.pt")
    assert payload["config"]["model"] == settings["model"]  # half the teacher's width
    assert payload["config"]["model"] != narrow["model"] and payload["student"]["steps"] == 1
    wide = sum(p.numel() for p in load_generator(work / "model.pt")[0].parameters())
    assert sum(p.numel() for p in den.parameters()) < wide / 2
    sampling = student_sampling(dict(settings["sampling"], student=True), payload, work / "student.pt")
    stats = sample_shard(den, payload, load_prompt_cache(prompts), "Fog", 0, 2, sampling, 5, tmp_path / "Fog",
                         log=lambda *_: None)
    assert stats["generated"] == 2
    # Without compression the narrow student starts the rounds from its random initial weights.
    cold = copy.deepcopy(narrow)
    cold["distillation"]["compression_iterations"] = 0
    assert train_generator(cold, index, prompts, tmp_path / "cold", tmp_path / "cold.pt", seed=3,
                           teacher=work / "model.pt")["iterations"] == 2 * 2
    a, b = _state(work / "student.pt"), _state(tmp_path / "cold.pt")
    assert not all(torch.equal(a[k], b[k]) for k in a)


def test_a_longer_final_round_moves_only_the_last_round_boundary():
    d = {"rounds": 3, "iterations_per_round": 4, "final_round_iterations": 10}
    assert round_iterations(d) == [4, 4, 10]
    assert [round_at(d, step) for step in (0, 3, 4, 7, 8, 17)] == [0, 0, 1, 1, 2, 2]
    assert round_iterations({**d, "final_round_iterations": None}) == [4, 4, 4]
    assert round_at({**d, "final_round_iterations": None}, 8) == 2


def test_a_distillation_with_a_longer_final_round_trains_it_and_samples(teacher, tmp_path):
    root, settings, index, prompts, _ = teacher
    longer = copy.deepcopy(settings)
    longer["distillation"]["final_round_iterations"] = 3
    summary = train_generator(longer, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                              teacher=root / "model.pt")
    assert summary["iterations"] == 2 + 3
    _, payload = load_generator(tmp_path / "student.pt")
    assert payload["student"]["steps"] == 1
    a, b = _state(root / "student.pt"), _state(tmp_path / "student.pt")  # one more step than the default
    assert not all(torch.equal(a[k], b[k]) for k in a)


def test_a_student_with_fewer_residual_blocks_starts_from_the_teachers_first_blocks(tmp_path):
    """distillation.student_res_blocks: the student keeps the first block of every level (and every
    other tensor) with the teacher's weights, learns the generator first, then runs the rounds."""
    settings = distill_settings()
    settings["model"]["num_res_blocks"] = 2
    index = make_domains(tmp_path, settings)
    prompts = tmp_path / "prompts.pt"
    torch.save(build_prompt_cache(settings["prompts"], FakeEncoder()), prompts)
    train_generator(settings, index, prompts, tmp_path / "teacher_work", tmp_path / "model.pt", seed=3)
    pruned = copy.deepcopy(settings)
    # A learning rate of 1e-12 leaves every weight where the student started.
    pruned["distillation"].update(student_res_blocks=1, compression_iterations=2, lr=1e-12)
    summary = train_generator(pruned, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                              teacher=tmp_path / "model.pt")
    assert summary["iterations"] == 2 + 2 * 2
    den, payload = load_generator(tmp_path / "student.pt")
    assert payload["config"]["model"]["num_res_blocks"] == 1 and payload["student"]["steps"] == 1
    student, teacher = _state(tmp_path / "student.pt"), _state(tmp_path / "model.pt")
    assert set(student) < set(teacher)
    assert {k for k in teacher if k not in student} == {k for k in teacher if ".blocks.1." in k}
    for name, value in student.items():
        torch.testing.assert_close(value, teacher[name], atol=1e-9, rtol=0)
    sampling = student_sampling(dict(settings["sampling"], student=True), payload, tmp_path / "student.pt")
    stats = sample_shard(den, payload, load_prompt_cache(prompts), "Beam32", 0, 2, sampling, 5,
                         tmp_path / "Beam32", log=lambda *_: None)
    assert stats["generated"] == 2
    # More blocks than the teacher has cannot start from it: one clear error before any training.
    wider = copy.deepcopy(settings)
    wider["distillation"]["student_res_blocks"] = 3
    with pytest.raises(InputError, match="student_res_blocks 3 exceeds .*num_res_blocks 2"):
        train_generator(wider, index, prompts, tmp_path / "wider", tmp_path / "wider.pt", seed=3,
                        teacher=tmp_path / "model.pt")
    assert not (tmp_path / "wider.pt").exists()

    # One number per level: the student keeps both blocks of the full-resolution level 0 and the
    # first of level 1 (encoder enc.1, decoder dec.0), and samples.
    per_level = copy.deepcopy(pruned)
    per_level["distillation"]["student_res_blocks"] = [2, 1]
    summary = train_generator(per_level, index, prompts, tmp_path / "per_level", tmp_path / "per_level.pt", seed=3,
                              teacher=tmp_path / "model.pt")
    assert summary["iterations"] == 2 + 2 * 2  # another architecture: compression first
    den, payload = load_generator(tmp_path / "per_level.pt")
    assert payload["config"]["model"]["num_res_blocks"] == [2, 1]
    assert [len(level.blocks) for level in den.enc] == [2, 1] and [len(level.blocks) for level in den.dec] == [1, 2]
    student = _state(tmp_path / "per_level.pt")
    assert {k for k in teacher if k not in student} == {
        k for k in teacher if k.startswith(("enc.1.blocks.1.", "dec.0.blocks.1."))}
    stats = sample_shard(den, payload, load_prompt_cache(prompts), "Fog", 0, 2,
                         student_sampling(dict(settings["sampling"], student=True), payload, tmp_path / "per_level.pt"),
                         5, tmp_path / "Fog", log=lambda *_: None)
    assert stats["generated"] == 2
    # The teacher's own blocks, listed per level, are its architecture: no compression phase.
    same = copy.deepcopy(pruned)
    same["distillation"]["student_res_blocks"] = [2, 2]
    assert compression_iterations(same) == 0 and compression_iterations(per_level) == 2
    # A list of another length, or more blocks at one level than the teacher has there: one clear
    # error before any training, naming the setting.
    for blocks, problem in (([1], "has 1 entries for 2 UNet levels"), ([1, 3], "exceeds .* at level 1")):
        bad = copy.deepcopy(pruned)
        bad["distillation"]["student_res_blocks"] = blocks
        with pytest.raises(InputError, match=f"student_res_blocks .*{problem}"):
            train_generator(bad, index, prompts, tmp_path / "bad", tmp_path / "bad.pt", seed=3,
                            teacher=tmp_path / "model.pt")
        assert not (tmp_path / "bad.pt").exists()


@pytest.mark.parametrize("until", [2, 4])  # inside compression, and inside the first round
def test_an_interrupted_narrow_distillation_resumes_to_the_same_student(teacher, narrow_student, tmp_path, until):
    _, _, index, prompts, _ = teacher
    narrow, work, _ = narrow_student
    train_generator(narrow, index, prompts, tmp_path / "work", tmp_path / "seg.json", seed=3, until=until,
                    teacher=work / "model.pt")
    resumed = train_generator(narrow, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                              teacher=work / "model.pt")
    assert resumed["resumed_from"] == until
    a, b = _state(work / "student.pt"), _state(tmp_path / "student.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("until", [2, 3])  # a round boundary, and inside the second round
def test_an_interrupted_distillation_resumes_to_the_same_student(teacher, tmp_path, until):
    root, settings, index, prompts, _ = teacher
    work = tmp_path / "work"
    train_generator(settings, index, prompts, work, tmp_path / "seg.json", seed=3, until=until,
                    teacher=root / "model.pt")
    resumed = train_generator(settings, index, prompts, work, tmp_path / "student.pt", seed=3,
                              teacher=root / "model.pt")
    assert resumed["resumed_from"] == until
    a, b = _state(root / "student.pt"), _state(tmp_path / "student.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_changed_distillation_settings_or_teacher_start_afresh(teacher, tmp_path):
    root, settings, index, prompts, _ = teacher
    work = tmp_path / "work"
    shutil.copytree(root / "student_work", work)
    other = copy.deepcopy(settings)
    other["distillation"]["lr"] = 3e-3
    changed = train_generator(other, index, prompts, work, tmp_path / "lr.pt", seed=3, teacher=root / "model.pt")
    assert changed["resumed_from"] == 0
    assert not all(torch.equal(a, b) for a, b in zip(_state(root / "student.pt").values(),
                                                     _state(tmp_path / "lr.pt").values()))
    # Another teacher (one more training iteration) is another input: the state is not reused either.
    longer = copy.deepcopy(settings)
    longer["training"]["iterations"] = 5
    train_generator(longer, index, prompts, root / "teacher_work", tmp_path / "model5.pt", seed=3)
    moved = train_generator(settings, index, prompts, work, tmp_path / "s5.pt", seed=3, teacher=tmp_path / "model5.pt")
    assert moved["resumed_from"] == 0


def test_the_distillation_seed_picks_the_student_without_the_run_seed(teacher, tmp_path):
    """distillation.seed null distils with the run's seed (the fixture's student, bit for bit); a set
    distillation seed gives another student, the same one under any run seed."""
    import json

    from omnilidar.cli import main

    root, settings, index, prompts, _ = teacher

    def distil(name, run_seed, seed):
        chosen = copy.deepcopy(settings)
        chosen["distillation"]["seed"] = seed
        assert main(["distill-generator", "--settings", json.dumps(chosen), "--seed", str(run_seed),
                     "--teacher", str(root / "model.pt"), "--domains", str(index), "--prompts", str(prompts),
                     "--work-dir", str(tmp_path / f"{name}_work"), "--out", str(tmp_path / f"{name}.pt")]) == 0
        return _state(tmp_path / f"{name}.pt")

    run_seed = distil("run", 3, None)
    fixture = _state(root / "student.pt")
    assert all(torch.equal(run_seed[k], fixture[k]) for k in fixture)
    own, own_other_run = distil("own", 3, 4), distil("own_other_run", 7, 4)
    assert not all(torch.equal(own[k], fixture[k]) for k in fixture)
    assert all(torch.equal(own[k], own_other_run[k]) for k in own)


def test_a_teacher_that_does_not_fit_is_one_clear_error(teacher, tmp_path):
    root, settings, index, prompts, _ = teacher
    wider = copy.deepcopy(settings)
    wider["model"]["base_channels"] = 16
    with pytest.raises(InputError, match="other generator.model settings"):
        train_generator(wider, index, prompts, tmp_path / "w", tmp_path / "s.pt", seed=3, teacher=root / "model.pt")
    with pytest.raises(InputError, match="already a distilled student"):
        train_generator(settings, index, prompts, tmp_path / "w", tmp_path / "s.pt", seed=3, teacher=root / "student.pt")
    odd = distill_settings(teacher_steps=6, rounds=2)
    with pytest.raises(InputError, match="cannot be halved"):
        train_generator(odd, index, prompts, tmp_path / "w", tmp_path / "s.pt", seed=3, teacher=root / "model.pt")
    assert not (tmp_path / "s.pt").exists()


def test_the_workflow_samples_from_the_student_when_asked(tmp_path):
    wf = copy_workflow(tmp_path)
    (tmp_path / "student.yaml").write_text("generator: {sampling: {student: true}}\n")
    target = "data/samples/Vehicle/shard_0"
    teacher_jobs = planned_jobs(wf, target, "--configfile", "config/test.yaml")
    student_jobs = planned_jobs(wf, target, "--configfile", "config/test.yaml", str(tmp_path / "student.yaml"))
    assert "distill_generator" not in teacher_jobs and student_jobs["distill_generator"] == 1
    assert student_jobs["train_generator"] == teacher_jobs["train_generator"] == 1


def test_a_decomposition_attempt_samples_the_student_without_retraining(tmp_path):
    wf = copy_workflow(tmp_path)
    (tmp_path / "attempt.yaml").write_text(
        "downstream: {experiments: {gda_decomposition: {attempts: {student: {generator: {sampling: {student: true}}}}}}}\n")
    jobs = planned_jobs(wf, "data/samples/attempt-student/Vehicle/shard_0", "--configfile", "config/test.yaml",
                        str(tmp_path / "attempt.yaml"))
    assert jobs["distill_generator"] == jobs["train_generator"] == jobs["sample_attempt"] == 1
    assert "train_generator_attempt" not in jobs


def test_the_sampler_study_samples_and_times_the_generator_s_own_sampler_like_every_setting(tmp_path):
    """With the generator's own sampler in its grid, the study samples it in its own job (no reuse of
    sample_domain's scans, which were timed in another batch and another run)."""
    wf = copy_workflow(tmp_path)
    (tmp_path / "study.yaml").write_text(
        "generator: {sampling: {sampler: unipc, steps: 3}}\n"
        "evaluation: {tradeoff: {samplers: {unipc: [3], ddim: [2]}, student: true, domains: [Vehicle]}}\n")
    out = snakemake(wf, "--dry-run", "--printshellcmds", "results/tradeoff.json", "--configfile", "config/test.yaml",
                    str(tmp_path / "study.yaml")).stdout
    study = out.split("rule sampler_tradeoff:", 1)[1].split("output:", 1)[0]
    assert "data/eval_samples/full/unipc_3/Vehicle/shard_0" in study and "data/samples/" not in study
    assert "--default-sampler unipc:3" in out.split("rule sampler_tradeoff:", 1)[1]


def test_the_teacher_s_evaluation_sets_do_not_read_the_distillation_settings(tmp_path):
    """Changing how the student is distilled reruns the student's sets (through its checkpoint),
    not the teacher's: their settings leave the distillation section out, as sample_domain's do."""
    wf = copy_workflow(tmp_path)
    (tmp_path / "study.yaml").write_text(
        "evaluation: {tradeoff: {samplers: {ddim: [2]}, student: true, domains: [Vehicle]}}\n")
    (tmp_path / "other.yaml").write_text("generator: {distillation: {spacing: karras, lr: 0.002}}\n")

    def sample_commands(*extra):
        out = snakemake(wf, "--dry-run", "--printshellcmds", "results/tradeoff.json", "--configfile",
                        "config/test.yaml", str(tmp_path / "study.yaml"), *extra).stdout
        return {line.split("--out ")[1].split()[0]: line for line in out.splitlines()
                if "omnilidar sample " in line}

    before, after = sample_commands(), sample_commands(str(tmp_path / "other.yaml"))
    teacher = [k for k in before if "/full/ddim_2/" in k]
    student = [k for k in before if "/student/" in k]
    assert teacher and student and before.keys() == after.keys()
    assert all(before[k] == after[k] and "distillation" not in before[k] for k in teacher)
    assert all("data/generator/full/student.pt" in before[k] for k in student)


def test_the_student_check_trains_no_segmentor_and_the_full_study_keeps_its_curve(tmp_path):
    """config/student.yaml turns the study's downstream curve off: the student against its teacher
    needs no labeler, pseudo-labels or students; the default study still plans and reads the curve."""
    wf = copy_workflow(tmp_path)
    check = planned_jobs(wf, "results/tradeoff.json", "--configfile", "config/test.yaml", "config/student.yaml")
    assert check["distill_generator"] == 1 and check["sampler_tradeoff"] == 1
    assert not {"train_labeler", "gda_curve", "train_gda_curve", "pseudo_label"} & set(check), check
    out = snakemake(wf, "--dry-run", "--printshellcmds", "results/tradeoff.json", "--configfile", "config/test.yaml",
                    "config/student.yaml").stdout
    assert "--gda-curve" not in out.split("rule sampler_tradeoff:", 1)[1]
    full = planned_jobs(wf, "results/tradeoff.json", "--configfile", "config/test.yaml")
    assert full["gda_curve"] == 1 and full["train_labeler"] == 1


def _planned_settings(wf, *configfiles):
    """The distillation and sampler-study settings (the evaluation section) a dry run of results/tradeoff.json plans."""
    out = snakemake(wf, "--dry-run", "--printshellcmds", "results/tradeoff.json", "--configfile", *configfiles).stdout
    distill = re.search(r"distill-generator .*--settings '(\{.*?\})'", out)
    study = json.loads(re.search(r"sampler-tradeoff .*--settings '(\{.*?\})'", out)[1])
    return json.loads(distill[1])["distillation"] if distill else None, study, out


def test_the_one_step_recipe_distils_a_calibrated_pruned_student_and_checks_it_on_12_scans(tmp_path):
    """config/student_1step.yaml (laid over config/student.yaml): the distillation job gets the
    recipe's settings and the check its 12 scans in 4 groups."""
    wf = copy_workflow(tmp_path)
    configfiles = ("config/test.yaml", "config/student.yaml", "config/student_1step.yaml")
    assert planned_jobs(wf, "results/tradeoff.json", "--configfile", *configfiles)["distill_generator"] == 1
    distill, tradeoff, _ = _planned_settings(wf, *configfiles)
    assert {k: distill[k] for k in ("teacher_steps", "teacher_substeps", "rounds", "student_res_blocks",
                                    "return_calibration", "range_calibration")} == {
        "teacher_steps": 32, "teacher_substeps": 2, "rounds": 5, "student_res_blocks": 1, "return_calibration": 8,
        "range_calibration": 17}
    assert (tradeoff["tradeoff"]["scans"], tradeoff["tradeoff"]["seed_groups"]) == (12, 4)


def test_the_best_teacher_check_on_every_domain_samples_its_settings_in_each(tmp_path):
    """config/student_1step_best_teacher_8domains.yaml: the best-teacher check's settings and the
    recipe's student in every domain the generator knows, instead of three."""
    wf = copy_workflow(tmp_path)
    configfiles = ("config/test.yaml", "config/student.yaml", "config/student_1step.yaml",
                   "config/student_1step_best_teacher.yaml")

    def check(*overlay):
        _, study, out = _planned_settings(wf, *configfiles, *overlay)
        return study["tradeoff"], set(re.findall(r"--samples ([\w-]+)/(\w+)=", out))

    three, given_three = check()
    every, given_every = check("config/student_1step_best_teacher_8domains.yaml")
    assert every["domains"] == [] and every["samplers"] == three["samplers"]
    settings = {s for s, _ in given_three}
    assert {d for _, d in given_three} == set(three["domains"]) and "student-1" in settings
    domains = {d for _, d in given_every}
    assert domains > set(three["domains"]) and given_every == {(s, d) for s in settings for d in domains}


def test_the_calibration_candidates_check_fits_each_domain_on_the_closer_best_setting_and_scores_held_out(tmp_path):
    """config/student_1step_calibration_candidates.yaml: the recipe's distillation with both best
    teacher settings as calibration candidates, held against them in every domain, on the held-out sets."""
    wf = copy_workflow(tmp_path)
    distill, study, out = _planned_settings(wf, "config/test.yaml", "config/student.yaml", "config/student_1step.yaml",
                                            "config/student_1step_calibration_candidates.yaml")
    assert distill["calibration_sampler"] == [{"sampler": "ddpm", "steps": 32}, {"sampler": "unipc_logsnr", "steps": 4}]
    assert distill["rounds"] == 5 and distill["range_calibration"] == 17  # the recipe's
    tradeoff = study["tradeoff"]
    assert tradeoff["domains"] == [] and {"ddpm", "unipc_logsnr"} <= set(tradeoff["samplers"])
    assert "--reference data/domains_heldout/index.json" in out
    rows = set(re.findall(r"--samples ([\w-]+)/(\w+)=", out))
    assert {d for s, d in rows if s == "student-1"} == {d for s, d in rows if s == "ddpm-32"} and len(rows) > 8


def test_the_long_last_round_check_extends_the_candidates_check_s_last_round_only(tmp_path):
    """config/student_1step_long_last_round.yaml: the calibration-candidates check with a last round
    three times as long, nothing else changed (so it resumes that check's finished distillation)."""
    wf = copy_workflow(tmp_path)
    configfiles = ("config/test.yaml", "config/student.yaml", "config/student_1step.yaml",
                   "config/student_1step_calibration_candidates.yaml")

    def distillation(*overlay):
        return _planned_settings(wf, *configfiles, *overlay)[0]

    base, longer = distillation(), distillation("config/student_1step_long_last_round.yaml")
    assert longer["final_round_iterations"] == 3 * base["iterations_per_round"]
    assert {k: v for k, v in longer.items() if k != "final_round_iterations"} == \
        {k: v for k, v in base.items() if k != "final_round_iterations"}
    assert longer["lr_decay"] == "constant"  # the rate under which the longer round resumes


@pytest.mark.parametrize("overlays, key, before, after", [
    (("config/student_1step_sectors.yaml",), "calibration_sectors", 1, 8),
    (("config/student_1step_sectors.yaml", "config/student_1step_first_holding.yaml"), "calibration_rule", "closest",
     "first_holding")])
def test_the_calibration_checks_change_only_one_calibration_key(tmp_path, overlays, key, before, after):
    """config/student_1step_sectors.yaml (a range map per azimuth sector over the long-last-round
    check) and config/student_1step_first_holding.yaml (over that, another rule for the calibration
    target) each change one calibration key, so each calibrates the check's finished distillation
    again."""
    wf = copy_workflow(tmp_path)
    configfiles = ("config/test.yaml", "config/student.yaml", "config/student_1step.yaml",
                   "config/student_1step_calibration_candidates.yaml", "config/student_1step_long_last_round.yaml")

    def distillation(*overlay):
        return _planned_settings(wf, *configfiles, *overlay)[0]

    base, changed = distillation(*overlays[:-1]), distillation(*overlays)
    assert base[key] == before and changed[key] == after
    assert {k: v for k, v in changed.items() if k != key} == {k: v for k, v in base.items() if k != key}
    assert key in _CALIBRATION_KEYS


_RECIPE = ("config/student_1step.yaml", "config/student_1step_calibration_candidates.yaml",
           "config/student_1step_long_last_round.yaml", "config/student_1step_sectors.yaml",
           "config/student_1step_first_holding.yaml")


def test_the_recipe_grid_puts_the_recipe_s_student_in_the_full_grid(tmp_path):
    """config/sampler_grid_recipe.yaml, laid last over the recipe's overlays and the grid (the
    commands on their first lines): the grid's solvers, domains, scans and seed groups, so its teacher
    sets are the grid run's, with the first_holding recipe's student instead of the schema's default."""
    wf = copy_workflow(tmp_path)
    default, grid, grid_out = _planned_settings(wf, "config/config.yaml", "config/sampler_grid.yaml")
    recipe, _, _ = _planned_settings(wf, "config/config.yaml", "config/student.yaml", *_RECIPE)
    distill, mixed, out = _planned_settings(wf, "config/config.yaml", "config/student.yaml", *_RECIPE,
                                            "config/sampler_grid.yaml", "config/sampler_grid_recipe.yaml")
    assert distill == recipe != default and distill["calibration_rule"] == "first_holding"
    assert mixed["tradeoff"] == grid["tradeoff"]

    def teacher_sets(text):
        return set(re.findall(r"--samples ((?!student)[\w-]+/\w+=\S+)", text))
    assert teacher_sets(out) == teacher_sets(grid_out) and len(teacher_sets(out)) > 30


def test_the_twelve_group_check_scores_the_recipe_s_student_on_every_domain(tmp_path):
    """config/student_1step_check_g12.yaml over the recipe: the same distillation (its student is not
    distilled again), the three teacher rows beside the student on all eight domains, 24 scans in 12
    seed groups, against the held-out sets (the command on its first lines)."""
    wf = copy_workflow(tmp_path)
    recipe, _, _ = _planned_settings(wf, "config/config.yaml", "config/student.yaml", *_RECIPE)
    distill, study, out = _planned_settings(wf, "config/config.yaml", *_RECIPE, "config/student_1step_check_g12.yaml")
    check = study["tradeoff"]
    assert distill == recipe
    assert check["samplers"] == {"ddpm": [32], "unipc": [10], "unipc_logsnr": [4]}
    assert (check["domains"], check["scans"], check["seed_groups"], check["student"]) == ([], 24, 12, True)
    assert "--reference data/domains_heldout/index.json" in out and "--gda-curve" not in out
    assert study["scans_per_set"] == 16


def test_a_narrow_student_of_a_prior_teacher_centres_on_the_teachers_means(teacher, tmp_path):
    """diffusion.prior domain_mean: a student of another width, which cannot load its teacher's state,
    still takes the teacher's domain means, so both denoise the same residual."""
    _, settings, index, prompts, _ = teacher
    wide = copy.deepcopy(settings)
    wide["diffusion"]["prior"] = "domain_mean"
    wide["model"]["base_channels"] = 2 * settings["model"]["base_channels"]
    wide["distillation"].update(student_channels=settings["model"]["base_channels"])
    wide["training"]["iterations"] = 1
    train_generator(wide, index, prompts, tmp_path / "teacher_work", tmp_path / "model.pt", seed=3)
    with torch.no_grad():  # a teacher whose means differ from what the data would give
        trained = torch.load(tmp_path / "model.pt", weights_only=True)
        trained["state_dict"]["prior_mean"] += 0.25
        torch.save(trained, tmp_path / "model.pt")
    train_generator(wide, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                    teacher=tmp_path / "model.pt")
    student, _ = load_generator(tmp_path / "student.pt")
    teacher_den, _ = load_generator(tmp_path / "model.pt")
    assert torch.equal(student.prior_mean, teacher_den.prior_mean)


def test_distillation_runs_in_float32_where_training_autocasts_bf16(teacher, tmp_path, monkeypatch):
    """On a CPU that multiplies bf16 natively (faked) the generator trains under bf16 autocast; a
    distillation does not: at the noisy end an epsilon network's bf16 rounding is an x0 error
    larger than the data, and the distillation losses compare x0."""
    from omnilidar.generator import training

    root, settings, index, prompts, _ = teacher
    settings = copy.deepcopy(settings)
    settings["training"]["bf16"] = True
    monkeypatch.setattr(training, "cpu_has_native_bf16", lambda: True)
    seen = set()
    original = torch.nn.Conv2d.forward
    monkeypatch.setattr(torch.nn.Conv2d, "forward", lambda self, x: seen.add((out := original(self, x)).dtype) or out)
    summary = train_generator(settings, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                              teacher=root / "model.pt")
    assert summary["precision"] == "fp32" and seen == {torch.float32}


def test_bf16_sampling_evaluates_the_noisy_end_in_float32(teacher):
    """A 2-step sample under bf16 autocast (CPU autocast stands in for CUDA's) stays the float32
    sample up to bf16 rounding: its first step, at logSNR -15, runs in float32. Evaluated in bf16
    there, the x0 it implies would carry the rounding of epsilon times sigma / alpha ~ 1800."""
    root, settings, _, prompts, _ = teacher
    den, payload = load_generator(root / "model.pt")
    entry = load_prompt_cache(prompts)["domains"][TINY_DOMAINS[0]]
    shape = tuple(den.coords.shape[1:])
    run = lambda bf16: generate(den, 0, entry["tokens"][0], entry["mask"][0], [1, 2], shape, "ddim", 2,  # noqa: E731
                                autocast_bf16=bf16)
    assert (run(True) - run(False)).abs().max() < 0.05
    assert not bf16_safe(torch.tensor([-15.0, 0.0])) and bf16_safe(torch.tensor([BF16_MIN_LOGSNR, 15.0]))
    z = torch.randn(1, 2, *shape, generator=torch.Generator().manual_seed(0))
    tok, msk = entry["tokens"][0][None].float(), entry["mask"][0][None].bool()
    noisy = torch.tensor([-15.0])
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        eps_bf16 = den(z, noisy, torch.tensor([0]), tok, msk).float()
    with torch.no_grad():
        eps = den(z, noisy, torch.tensor([0]), tok, msk)
    assert (predict_x0(z, eps_bf16, noisy, clamp=False) - predict_x0(z, eps, noisy, clamp=False)).abs().max() > 0.5


def test_a_pseudo_huber_error_is_minimised_by_the_median_where_a_squared_one_averages():
    from omnilidar.generator.distill import pixel_error

    d = torch.tensor([0.001, 0.5])
    assert torch.allclose(pixel_error(d), d.square())
    huber = pixel_error(d, 0.01)
    assert abs(huber[0] / (0.001**2 / 0.02) - 1) < 1e-2 and abs(huber[1] - (0.5 - 0.01)) < 1e-3  # quadratic, then linear
    # Three drop-outs (-1) and two returns (0.4) that a student cannot tell apart.
    targets = torch.tensor([-1.0, -1.0, -1.0, 0.4, 0.4])
    grid = torch.linspace(-1, 1, 2001)
    best = {c: grid[torch.stack([pixel_error(x - targets, c).mean() for x in grid]).argmin()].item()
            for c in (None, 0.01)}
    assert abs(best[None] - targets.mean().item()) < 2e-3 and abs(best[0.01] + 1.0) < 2e-2


def test_a_distillation_with_a_pseudo_huber_error_trains_another_student(teacher, tmp_path):
    root, settings, index, prompts, _ = teacher
    huber = copy.deepcopy(settings)
    huber["distillation"]["huber_c"] = 0.01
    shutil.copytree(root / "student_work", tmp_path / "work")  # the finished squared-error distillation's state
    summary = train_generator(huber, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                              teacher=root / "model.pt")
    assert summary["resumed_from"] == 0  # another loss is another distillation: it starts afresh
    a, b = _state(root / "student.pt"), _state(tmp_path / "student.pt")
    assert not all(torch.equal(a[k], b[k]) for k in a)
    den, payload = load_generator(tmp_path / "student.pt")
    assert payload["config"]["distillation"]["huber_c"] == 0.01
    assert torch.isfinite(generate(den, 0, *_first_prompt(prompts), [1], tuple(settings["range_image"][k] for k in
                                                                               ("height", "width")), "ddim", 1)).all()


def _first_prompt(prompts):
    entry = next(iter(load_prompt_cache(prompts)["domains"].values()))
    return entry["tokens"][0], entry["mask"][0]
