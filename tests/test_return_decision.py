"""A distilled student's calibrated return decision and returns' ranges: the per-row thresholds and
range maps, how sampling applies them, their seeds, and real tiny distillations that calibrate their
students."""

from __future__ import annotations

import copy
import zlib

import numpy as np
import pytest
import torch

from omnilidar.data.range_image import decode
from omnilidar.errors import InputError
from omnilidar.generator.checkpoint import load_generator
from omnilidar.generator.data import rng_for
from omnilidar.generator.diffusion import apply_range_map, apply_return_thresholds, generate, scan_seed
from omnilidar.generator.return_decision import calibration_seeds, fit_by_sector, row_range_knots, row_thresholds
from omnilidar.generator.sampling import domain_points_spec
from omnilidar.generator.text import load_prompt_cache
from omnilidar.generator.training import train_generator
from test_generator_distill import teacher  # noqa: F401  (the module's tiny teacher and student)
from test_generator_fixtures import TINY_DOMAINS, one_torch_thread  # noqa: F401


def test_a_row_where_the_student_returns_more_loses_its_lowest_values_until_it_returns_as_often():
    rng = np.random.default_rng(0)
    values = rng.uniform(-0.5, 1.0, (4, 3, 50)).astype(np.float32)  # every pixel a return
    student_returns = np.ones(values.shape, bool)
    teacher_returns = np.zeros(values.shape, bool)
    teacher_returns[:, 0, :30] = True  # row 0: the teacher returns 60 %
    teacher_returns[:, 1] = True       # row 1: as often as the student
    # row 2: the teacher never returns
    thr = row_thresholds(values, student_returns, teacher_returns)
    kept = values > thr[None, :, None]
    assert kept[:, 0].sum() == 120 and kept[:, 1].all() and not kept[:, 2].any()
    assert thr[1] == -1.0
    # What row 0 keeps are its highest values.
    assert values[:, 0][kept[:, 0]].min() > values[:, 0][~kept[:, 0]].max()
    # A row where the student returns less than its teacher is left alone (nothing is added).
    fewer = student_returns.copy()
    fewer[:, 0, :] = False
    assert row_thresholds(values, fewer, teacher_returns)[0] == -1.0


def test_a_thresholded_pixel_is_empty_in_both_channels_and_others_keep_their_values():
    images = torch.tensor([[[[0.2, -0.3]], [[0.5, 0.6]]]])  # (1, 2, 1, 2)
    out = apply_return_thresholds(images, torch.tensor([-0.3]))
    assert out[0, :, 0, 1].tolist() == [-1.0, -1.0]
    assert torch.equal(out[0, :, 0, 0], images[0, :, 0, 0])


def test_calibration_noise_is_never_a_sampled_scan_s_noise():
    cal = set(calibration_seeds(0, "Drone", 64))
    assert len(cal) == 64 and cal == set(calibration_seeds(0, "Drone", 64))
    assert not cal & {scan_seed(0, "Drone", g) for g in range(10_000)}
    assert cal != set(calibration_seeds(1, "Drone", 64)) and cal != set(calibration_seeds(0, "Snow", 64))
    assert calibration_seeds(0, "Drone", 1)[0] == int(rng_for(0, zlib.crc32(b"Drone"), 0xCA1B, 0).integers(2**63 - 1))


def test_a_tiny_distillation_calibrates_its_student_to_its_teacher_s_returns(teacher, tmp_path):
    root, settings, index, prompts, _ = teacher
    calibrated = copy.deepcopy(settings)
    calibrated["distillation"]["return_calibration"] = 4
    train_generator(calibrated, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                    teacher=root / "model.pt")
    student, payload = load_generator(tmp_path / "student.pt")
    thresholds = payload["return_thresholds"]
    assert thresholds.shape == (len(TINY_DOMAINS), settings["range_image"]["height"])
    assert payload["student"]["return_calibration"] == 4
    # The same weights as the uncalibrated student of the same run: calibration only adds the decision.
    plain = torch.load(root / "student.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(plain[k], payload["state_dict"][k]) for k in plain)
    gen, _ = load_generator(root / "model.pt")
    uncalibrated, _ = load_generator(root / "student.pt")
    cache = load_prompt_cache(prompts)
    thresholded = 0
    for d, name in enumerate(TINY_DOMAINS):
        spec = domain_points_spec(payload["config"], payload, name)
        seeds = calibration_seeds(3, name, 4)
        entry = cache["domains"][name]

        def returns(net, steps):
            images = generate(net, d, entry["tokens"][0], entry["mask"][0], seeds, spec.shape, "ddim", steps)
            return np.stack([decode(img, spec)[2] for img in images.numpy()])

        teacher_rows = returns(gen, 4).mean(axis=(0, 2))
        plain_rows, calibrated_rows = returns(uncalibrated, 1).mean(axis=(0, 2)), returns(student, 1).mean(axis=(0, 2))
        # On its calibration noise, every row the student over-filled returns as often as the teacher.
        over = plain_rows > teacher_rows
        assert np.allclose(calibrated_rows[over], teacher_rows[over], atol=1 / (4 * spec.shape[1]))
        assert np.array_equal(calibrated_rows[~over], plain_rows[~over])
        thresholded += int(over.sum())
    assert thresholded  # the tiny student over-fills some rows, so the check above checks something


def test_calibrating_a_finished_distillation_again_resumes_it_and_does_not_distil_it_again(teacher, tmp_path):
    import shutil

    root, settings, index, prompts, plain = teacher
    work = tmp_path / "work"
    shutil.copytree(root / "student_work", work)  # the fixture's finished, uncalibrated distillation
    calibrated = copy.deepcopy(settings)
    calibrated["distillation"].update(return_calibration=4, range_calibration=3)
    again = train_generator(calibrated, index, prompts, work, tmp_path / "student.pt", seed=3, teacher=root / "model.pt")
    # Resumed at the last step: no step taken, the same weights, now with the calibration.
    assert again["resumed_from"] == plain["iterations"] == again["iterations"]
    assert again["weights_digest"] == plain["weights_digest"]
    payload = torch.load(tmp_path / "student.pt", weights_only=True)
    assert payload["return_thresholds"].shape[0] == len(TINY_DOMAINS) and payload["range_map"].shape[-1] == 3
    assert payload["student"]["return_calibration"] == 4 and payload["student"]["range_calibration"] == 3
    # Range maps per azimuth sector: calibrated again, still not distilled again.
    sectored = copy.deepcopy(calibrated)
    sectored["distillation"]["calibration_sectors"] = 4
    again = train_generator(sectored, index, prompts, work, tmp_path / "sectored.pt", seed=3, teacher=root / "model.pt")
    assert again["resumed_from"] == plain["iterations"] and again["weights_digest"] == plain["weights_digest"]
    student, sectors = load_generator(tmp_path / "sectored.pt")
    h, w = settings["range_image"]["height"], settings["range_image"]["width"]
    assert sectors["range_map"].shape == (len(TINY_DOMAINS), 4, h, 2, 3)
    assert sectors["return_thresholds"].shape == (len(TINY_DOMAINS), 4, h)
    assert sectors["student"]["calibration_sectors"] == 4
    # Each sector's map is fitted on its own columns: on the calibration noise the student's returns
    # in a mapped row of a sector span the teacher's there.
    name, spec = TINY_DOMAINS[0], domain_points_spec(sectors["config"], sectors, TINY_DOMAINS[0])
    entry = load_prompt_cache(prompts)["domains"][name]
    seeds = calibration_seeds(3, name, 4)
    t = generate(load_generator(root / "model.pt")[0], 0, entry["tokens"][0], entry["mask"][0], seeds, spec.shape,
                 "ddim", 4).numpy()
    s = generate(student, 0, entry["tokens"][0], entry["mask"][0], seeds, spec.shape, "ddim", 1).numpy()
    t_ret, s_ret = (np.stack([decode(img, spec)[2] for img in x]) for x in (t, s))
    mapped = 0
    for sector in range(4):
        cols = slice(sector * w // 4, (sector + 1) * w // 4)
        # The sector's return fraction per row is its teacher's (up to ties), where the student returned more.
        more = s_ret[:, :, cols].mean(axis=(0, 2)) >= t_ret[:, :, cols].mean(axis=(0, 2))
        np.testing.assert_allclose(s_ret[:, more, cols].mean(axis=(0, 2)), t_ret[:, more, cols].mean(axis=(0, 2)),
                                   atol=1.5 / (4 * w // 4))
        for row in range(h):
            knots = sectors["range_map"][0, sector, row].numpy()
            if np.array_equal(knots[0], knots[1]):
                continue
            own, theirs = s[:, 0, row, cols][s_ret[:, row, cols]], t[:, 0, row, cols][t_ret[:, row, cols]]
            np.testing.assert_allclose([own.min(), own.max()], [theirs.min(), theirs.max()], atol=1e-5)
            mapped += 1
    assert mapped
    wrong = copy.deepcopy(sectored)
    wrong["distillation"]["calibration_sectors"] = 3
    with pytest.raises(InputError, match="calibration_sectors 3 .*width 64"):
        train_generator(wrong, index, prompts, work, tmp_path / "wrong.pt", seed=3, teacher=root / "model.pt")
    assert not (tmp_path / "wrong.pt").exists()
    # A setting that changes what a step computes distils again from the start.
    longer = copy.deepcopy(calibrated)
    longer["distillation"]["iterations_per_round"] += 1
    fresh = train_generator(longer, index, prompts, work, tmp_path / "longer.pt", seed=3, teacher=root / "model.pt")
    assert fresh["resumed_from"] == 0 and fresh["iterations"] > plain["iterations"]


def test_of_several_calibration_settings_the_one_closest_to_the_training_scans_is_taken():
    """BEV JSD and MMD against the reference scans, each relative to the best candidate's: the
    reference's own scans win over the same scans with the lower half of their rows dropped, in
    either order."""
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.generation import closest_setting
    from test_generation_targets import tiny_generator_settings

    spec = range_image_spec(tiny_generator_settings())
    rng = np.random.default_rng(0)
    h, w = spec.shape
    reference = np.stack([np.stack([rng.uniform(-0.6, 0.6, (h, w)), rng.uniform(-1, 1, (h, w))]) for _ in range(4)])
    sparse = reference.copy()
    sparse[:, :, h // 2:] = -1.0
    for order in (("own", "sparse"), ("sparse", "own")):
        pick, scores = closest_setting({k: {"own": reference[::-1].copy(), "sparse": sparse}[k] for k in order},
                                       reference, spec)
        assert pick == "own" and scores["own"]["MMD"] < scores["sparse"]["MMD"] and scores["own"]["JSD"] < 1e-6


def test_first_holding_takes_the_first_candidate_that_holds_the_best_of_each_metric():
    """A candidate a little off the reference's own scans holds them (its excess is within two
    standard deviations over the groups), so listed first it is taken though the closest rule takes
    the reference's own; one that drops half of every scan misses, and the next one is taken."""
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.generation import closest_setting, first_holding_setting
    from test_generation_targets import tiny_generator_settings

    spec = range_image_spec(tiny_generator_settings())
    rng = np.random.default_rng(0)
    h, w = spec.shape
    reference = np.stack([np.stack([rng.uniform(-0.6, 0.6, (h, w)), rng.uniform(-1, 1, (h, w))]) for _ in range(8)])
    own, near, sparse = reference[::-1].copy(), reference[::-1].copy(), reference.copy()
    near[:, 0] += rng.normal(0, 0.001, near[:, 0].shape)
    sparse[:, :, h // 2:] = -1.0
    sets = {"near": near, "own": own}
    assert closest_setting(sets, reference, spec)[0] == "own"
    pick, scores = first_holding_setting(sets, reference, spec)
    assert pick == "near" and scores["near"]["excess"] <= 1.0 and scores["own"]["excess"] <= 1.0
    pick, scores = first_holding_setting({"sparse": sparse, "own": own}, reference, spec)
    assert pick == "own" and scores["sparse"]["excess"] > 1.0


def test_a_distillation_with_calibration_candidates_calibrates_each_domain_on_the_closest(teacher, tmp_path):
    """calibration_sampler as a list: each domain's return decision and range map are fitted on the
    candidate whose scans lie closest to its training scans, the checkpoint says which, and the
    distillation is calibrated again without distilling again."""
    import shutil

    from omnilidar.generator.data import load_range_image, read_domains_index
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.generation import choose_on_training_scans, closest_setting, first_holding_setting

    root, settings, index, prompts, plain = teacher
    work = tmp_path / "work"
    shutil.copytree(root / "student_work", work)
    calibrated = copy.deepcopy(settings)
    candidates = [("ddpm", 3), ("ddim", 4)]
    calibrated["distillation"].update(return_calibration=4, range_calibration=3,
                                      calibration_sampler=[{"sampler": n, "steps": k} for n, k in candidates])
    with pytest.raises(InputError, match="needs the rule that chooses"):  # train_generator alone has none
        train_generator(calibrated, index, prompts, work, tmp_path / "student.pt", seed=3, teacher=root / "model.pt")
    assert not (tmp_path / "student.pt").exists()
    import json

    from omnilidar.cli import main

    # The workflow's command passes the rule (choose_on_training_scans, calibration_rule closest).
    assert main(["distill-generator", "--settings", json.dumps(calibrated), "--seed", "3", "--teacher",
                 str(root / "model.pt"), "--domains", str(index), "--prompts", str(prompts), "--work-dir", str(work),
                 "--out", str(tmp_path / "student.pt")]) == 0
    payload = torch.load(tmp_path / "student.pt", weights_only=True)
    assert payload["resumed_from"] == plain["iterations"] == payload["iterations"]
    choice = payload["student"]["calibration_sampler"]
    assert set(choice) == set(TINY_DOMAINS) and set(choice.values()) <= {"ddpm:3", "ddim:4"}
    gen, _ = load_generator(root / "model.pt")
    cache, domains = load_prompt_cache(prompts), read_domains_index(index)
    h, w = settings["range_image"]["height"], settings["range_image"]["width"]
    for d, name in enumerate(TINY_DOMAINS):
        spec, entry = domain_points_spec(payload["config"], payload, name), cache["domains"][name]
        drawn = {f"{n}:{k}": generate(gen, d, entry["tokens"][0], entry["mask"][0], calibration_seeds(3, name, 4),
                                      spec.shape, n, k).numpy() for n, k in candidates}
        training = np.stack([load_range_image(f, (h, w)) for f in domains[name]["files"]])
        assert choice[name] == closest_setting(drawn, training, range_image_spec(payload["config"]))[0]
        # The range map's teacher knots are the chosen setting's quantiles.
        chosen = drawn[choice[name]]
        returns = np.stack([decode(img, spec)[2] for img in chosen])
        for row in range(h):
            knots = payload["range_map"][d, row].numpy()
            if not np.array_equal(knots[0], knots[1]):
                np.testing.assert_allclose(knots[1], np.quantile(chosen[:, 0, row][returns[:, row]], np.linspace(0, 1, 3)),
                                           rtol=1e-5, atol=1e-6)
    # calibration_rule first_holding calibrates the same distillation again, without distilling, and
    # takes in each domain the first candidate whose scans hold the best of each metric.
    ruled = copy.deepcopy(calibrated)
    ruled["distillation"]["calibration_rule"] = "first_holding"
    assert main(["distill-generator", "--settings", json.dumps(ruled), "--seed", "3", "--teacher",
                 str(root / "model.pt"), "--domains", str(index), "--prompts", str(prompts), "--work-dir", str(work),
                 "--out", str(tmp_path / "ruled.pt")]) == 0
    again = torch.load(tmp_path / "ruled.pt", weights_only=True)
    assert again["resumed_from"] == plain["iterations"] == again["iterations"]
    assert again["student"]["calibration_rule"] == "first_holding" and payload["student"]["calibration_rule"] == "closest"
    for d, name in enumerate(TINY_DOMAINS):
        spec, entry = domain_points_spec(payload["config"], payload, name), cache["domains"][name]
        drawn = {f"{n}:{k}": generate(gen, d, entry["tokens"][0], entry["mask"][0], calibration_seeds(3, name, 4),
                                      spec.shape, n, k).numpy() for n, k in candidates}
        training = np.stack([load_range_image(f, (h, w)) for f in domains[name]["files"]])
        assert again["student"]["calibration_sampler"][name] == \
            first_holding_setting(drawn, training, range_image_spec(payload["config"]))[0]
    one = copy.deepcopy(ruled)  # seed groups of one scan's set: one clear error before anything runs
    one["distillation"]["return_calibration"] = 1
    with pytest.raises(InputError, match="first_holding .*return_calibration >= 2"):
        train_generator(one, index, prompts, tmp_path / "one", tmp_path / "one.pt", seed=3, teacher=root / "model.pt",
                        choose_calibration=choose_on_training_scans(index, range_image_spec(settings), "first_holding"))
    assert not (tmp_path / "one.pt").exists()
    twice = copy.deepcopy(calibrated)
    twice["distillation"]["calibration_sampler"] = [{"sampler": "ddpm", "steps": 3}] * 2
    with pytest.raises(InputError, match="names a setting twice"):
        train_generator(twice, index, prompts, tmp_path / "twice", tmp_path / "twice.pt", seed=3, teacher=root / "model.pt",
                        choose_calibration=choose_on_training_scans(index, range_image_spec(settings)))


def test_a_checkpoint_whose_thresholds_do_not_fit_its_image_is_one_clear_error(teacher, tmp_path):
    root = teacher[0]
    payload = torch.load(root / "student.pt", weights_only=True)
    payload["return_thresholds"] = torch.zeros(1, 3)
    torch.save(payload, tmp_path / "bad.pt")
    with pytest.raises(InputError, match="return_thresholds"):
        load_generator(tmp_path / "bad.pt")


def test_a_range_map_moves_the_student_s_returns_onto_its_teacher_s_quantiles():
    rng = np.random.default_rng(1)
    student = rng.uniform(-0.4, 0.3, (6, 3, 40)).astype(np.float32)  # nearer and narrower
    teacher = rng.uniform(-0.5, 0.8, (6, 3, 40)).astype(np.float32)
    returns = np.ones(student.shape, bool)
    student_sparse = returns.copy()
    student_sparse[2:, 2] = False
    student_sparse[:2, 2, 2:] = False  # row 2: 4 student returns, too few for 5 knots
    knots = row_range_knots(student, student_sparse, teacher, returns, 5)
    assert knots.shape == (3, 2, 5)
    np.testing.assert_allclose(knots[0, 0], np.quantile(student[:, 0], np.linspace(0, 1, 5)), rtol=1e-6)
    np.testing.assert_allclose(knots[0, 1], np.quantile(teacher[:, 0], np.linspace(0, 1, 5)), rtol=1e-6)
    assert np.array_equal(knots[2, 0], knots[2, 1])  # the identity map
    images = torch.from_numpy(np.stack([student, rng.uniform(-1, 1, student.shape).astype(np.float32)], axis=1))
    images[0, 0, 1, :3] = -1.0  # drop-outs, below every knot
    mapped = apply_range_map(images, torch.from_numpy(knots))
    assert torch.equal(mapped[:, 1], images[:, 1]) and (mapped[0, 0, 1, :3] == -1.0).all()
    for row in (0, 1):  # np.interp is the same piecewise-linear map
        values = images[:, 0, row].numpy()
        ok = values >= knots[row, 0, 0]
        np.testing.assert_allclose(mapped[:, 0, row].numpy()[ok], np.interp(values[ok], knots[row, 0], knots[row, 1]),
                                   rtol=0, atol=1e-6)
    # The student's returns now spread as its teacher's: same extremes, nearly the same quantiles.
    row0 = mapped[1:, 0, 0].numpy()
    assert abs(row0.min() - teacher[:, 0].min()) < 1e-6 and abs(row0.max() - teacher[:, 0].max()) < 1e-6
    shift = abs(np.median(student[:, 0]) - np.median(teacher[:, 0]))
    assert abs(np.median(row0) - np.median(teacher[:, 0])) < 0.05 < shift
    assert torch.equal(mapped[:, 0, 2], images[:, 0, 2])  # the identity row is untouched


def test_a_calibration_per_azimuth_sector_fits_and_applies_each_sector_s_columns_on_their_own():
    """A pitched sensor's row is near on one side and far on the other: one map per row mixes the
    two, one map per row and sector moves each side onto its teacher's; and a threshold per row and
    sector empties the student's pixels on the side where its teacher's drop-outs lie."""
    rng = np.random.default_rng(2)
    n, h, w = 6, 3, 40
    half = (slice(0, w // 2), slice(w // 2, w))
    student = rng.uniform(-0.2, 0.2, (n, h, w)).astype(np.float32)  # the sides blurred together
    teacher = np.concatenate([rng.uniform(-0.8, -0.4, (n, h, w // 2)), rng.uniform(0.4, 0.8, (n, h, w // 2))],
                             axis=-1).astype(np.float32)  # near on the left, far on the right
    returns = np.ones(student.shape, bool)
    knots = fit_by_sector(lambda *a: row_range_knots(*a, 5), (student, returns, teacher, returns), 2)
    assert knots.shape == (2, h, 2, 5)
    for s, cols in enumerate(half):  # each sector: its own columns' quantiles
        np.testing.assert_array_equal(knots[s], row_range_knots(student[..., cols], returns[..., cols],
                                                                teacher[..., cols], returns[..., cols], 5))
    np.testing.assert_array_equal(fit_by_sector(lambda *a: row_range_knots(*a, 5), (student, returns, teacher,
                                                                                     returns), 1)[0],
                                  row_range_knots(student, returns, teacher, returns, 5))
    images = torch.from_numpy(np.stack([student, np.zeros_like(student)], axis=1))
    by_sector = apply_range_map(images, torch.from_numpy(knots))
    for s, cols in enumerate(half):
        assert torch.equal(by_sector[..., cols], apply_range_map(images[..., cols], torch.from_numpy(knots[s])))
    left, right = by_sector[:, 0, :, half[0]].numpy(), by_sector[:, 0, :, half[1]].numpy()
    assert left.max() <= -0.4 + 1e-6 and right.min() >= 0.4 - 1e-6  # each side where its teacher's is
    per_row = apply_range_map(images, torch.from_numpy(row_range_knots(student, returns, teacher, returns, 5)))
    assert (per_row[:, 0, :, half[0]] > 0).float().mean() > 0.3  # one map per row sends the left side far too

    # The teacher drops a third of the right side's returns (the sky behind a pitched sensor), none on
    # the left; the student returns everywhere, lowest (its ground) on the left.
    dropped = np.ones(student.shape, bool)
    dropped[..., w // 2:] = rng.random((n, h, w // 2)) > 1 / 3
    lowest_left = student - 0.5 * (np.arange(w) < w // 2)
    thresholds = fit_by_sector(row_thresholds, (lowest_left, returns, dropped), 2)
    assert thresholds.shape == (2, h) and (thresholds[0] == -1).all() and (thresholds[1] > -1).all()
    kept = apply_return_thresholds(torch.from_numpy(np.stack([lowest_left, lowest_left], axis=1)),
                                   torch.from_numpy(thresholds))[:, 0].numpy() > -1
    assert kept[..., half[0]].all()  # the left keeps every return
    np.testing.assert_allclose(kept[..., half[1]].mean(), dropped[..., half[1]].mean(), atol=0.01)
    one_per_row = row_thresholds(lowest_left, returns, dropped)
    emptied = lowest_left <= one_per_row[None, :, None]  # one threshold per row: the left's ground goes instead
    assert emptied[..., half[0]].mean() > 0.3 and not emptied[..., half[1]].any()
    with pytest.raises(ValueError, match="3 azimuth sectors"):
        fit_by_sector(row_thresholds, (student, returns, teacher), 3)
    with pytest.raises(ValueError, match="3 azimuth sectors"):
        apply_range_map(images, torch.zeros(3, h, 2, 5))


@pytest.mark.parametrize("calibrated_on", [None, ("ddpm", 3)], ids=["learnt-path", "ddpm"])
def test_a_tiny_distillation_maps_its_student_s_returns_onto_its_teacher_s(teacher, tmp_path, calibrated_on):
    """On the DDIM path the student learnt (the tiny teacher's DDIM x 4), or on the scans of the
    teacher's sampler that ``calibration_sampler`` names (an ancestral one, DDPM x 3)."""
    root, settings, index, prompts, _ = teacher
    calibrated = copy.deepcopy(settings)
    calibrated["distillation"].update(return_calibration=4, range_calibration=5)
    teacher_sampler = ("ddim", 4)
    if calibrated_on:
        calibrated["distillation"]["calibration_sampler"] = dict(zip(("sampler", "steps"), calibrated_on))
        teacher_sampler = calibrated_on
    train_generator(calibrated, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                    teacher=root / "model.pt")
    student, payload = load_generator(tmp_path / "student.pt")
    h = settings["range_image"]["height"]
    assert payload["range_map"].shape == (len(TINY_DOMAINS), h, 2, 5)
    assert payload["student"]["range_calibration"] == 5
    assert payload["student"]["calibration_sampler"] == "{}:{}".format(*teacher_sampler)
    gen, _ = load_generator(root / "model.pt")
    cache = load_prompt_cache(prompts)
    mapped_rows = 0
    for d, name in enumerate(TINY_DOMAINS):
        spec = domain_points_spec(payload["config"], payload, name)
        entry = cache["domains"][name]

        def sample(net, sampler, steps):
            images = generate(net, d, entry["tokens"][0], entry["mask"][0], calibration_seeds(3, name, 4), spec.shape,
                              sampler, steps).numpy()
            return images[:, 0], np.stack([decode(img, spec)[2] for img in images])

        (t_range, t_ret), (s_range, s_ret) = sample(gen, *teacher_sampler), sample(student, "ddim", 1)
        for row in range(h):
            knots = payload["range_map"][d, row].numpy()
            if np.array_equal(knots[0], knots[1]):
                continue
            # On its calibration noise the student's returns in a mapped row span its teacher's.
            assert s_ret[:, row].sum() >= 5
            np.testing.assert_allclose([s_range[:, row][s_ret[:, row]].min(), s_range[:, row][s_ret[:, row]].max()],
                                       [t_range[:, row][t_ret[:, row]].min(), t_range[:, row][t_ret[:, row]].max()],
                                       atol=1e-5)
            mapped_rows += 1
    assert mapped_rows  # some rows are mapped, so the check above checks something
    if calibrated_on:  # a calibration sampler that cannot run: one clear error, no student
        for change, match in (({"calibration_sampler": {"sampler": "euler", "steps": 3}}, "unknown sampler 'euler'"),
                              ({"return_calibration": 0, "range_calibration": 0}, "ddpm:3 samples the return")):
            wrong = copy.deepcopy(calibrated)
            wrong["distillation"].update(change)
            with pytest.raises(InputError, match=match):
                train_generator(wrong, index, prompts, tmp_path / "wrong", tmp_path / "wrong.pt", seed=3,
                                teacher=root / "model.pt")
            assert not (tmp_path / "wrong.pt").exists()
        return
    # Without the return calibration's scans there is nothing to map on: one clear error, no student.
    alone = copy.deepcopy(settings)
    alone["distillation"].update(range_calibration=5)
    with pytest.raises(InputError, match="range_calibration 5 .*return_calibration"):
        train_generator(alone, index, prompts, tmp_path / "alone", tmp_path / "alone.pt", seed=3,
                        teacher=root / "model.pt")
    assert not (tmp_path / "alone.pt").exists()


def test_a_checkpoint_whose_range_map_does_not_fit_its_image_is_one_clear_error(teacher, tmp_path):
    payload = torch.load(teacher[0] / "student.pt", weights_only=True)
    for shape in ((len(TINY_DOMAINS), 3, 2, 5), (len(TINY_DOMAINS), 3, 16, 2, 5)):  # 3 sectors do not split 64
        payload["range_map"] = torch.zeros(shape)
        torch.save(payload, tmp_path / "bad.pt")
        with pytest.raises(InputError, match="range_map"):
            load_generator(tmp_path / "bad.pt")
