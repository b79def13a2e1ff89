"""Continuous cosine logSNR schedule and the three samplers: end points, x0 recovery, consistency."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from omnilidar.generator.samplers import (SAMPLER_NAMES, SAMPLERS, DDIMScheduler, DDPMScheduler,
                                         DPMSolverPlusPlus2MScheduler, make_scheduler, time_grid)
from omnilidar.generator.schedule import CosineLogSNRSchedule, alpha_sigma, min_snr_weight, predict_x0

S = CosineLogSNRSchedule()


def test_logsnr_end_points_and_monotone():
    t = torch.tensor([0.0, 1.0], dtype=torch.float64)
    l = S.logsnr(t)
    assert l[0].item() == pytest.approx(15.0, abs=1e-9) and l[1].item() == pytest.approx(-15.0, abs=1e-9)
    grid = S.logsnr(torch.linspace(0, 1, 1001, dtype=torch.float64))
    assert torch.all(grid[1:] < grid[:-1])
    # outside [0, 1] clamps instead of producing NaN (tan past pi/2)
    assert torch.isfinite(S.logsnr(torch.tensor([-0.5, 1.5]))).all()
    # the cosine schedule: logSNR(0.5) = -2 log tan(pi/4) = 0 for symmetric bounds
    assert S.logsnr(torch.tensor(0.5, dtype=torch.float64)).item() == pytest.approx(0.0, abs=1e-12)
    back = S.t_of_logsnr(grid)
    torch.testing.assert_close(back, torch.linspace(0, 1, 1001, dtype=torch.float64), atol=1e-9, rtol=0)


def test_alpha_sigma_variance_preserving_and_finite_at_ends():
    l = torch.tensor([-15.0, 0.0, 15.0])
    a, s = alpha_sigma(l)
    torch.testing.assert_close(a**2 + s**2, torch.ones(3))
    assert a[0].item() == pytest.approx(math.sqrt(1 / (1 + math.exp(15))), rel=1e-5)  # ~5.5e-4
    assert s[2].item() == pytest.approx(math.sqrt(1 / (1 + math.exp(15))), rel=1e-5)


def test_min_snr_weight():
    l = torch.tensor([-15.0, 0.0, math.log(5.0), 15.0])
    w = min_snr_weight(l, 5.0)
    torch.testing.assert_close(w, torch.tensor([1.0, 1.0, 1.0, 5.0 * math.exp(-15.0)]))
    assert torch.equal(min_snr_weight(l, 0.0), torch.ones(4))


def test_x0_recovery_where_alpha_is_tiny():
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(4, 2, 8, 16, generator=g) * 2 - 1
    eps = torch.randn(x0.shape, generator=g)
    for l in (-15.0, -5.0, 0.0, 15.0):
        a, s = alpha_sigma(torch.tensor(l))
        xt = a * x0 + s * eps
        rec = predict_x0(xt, eps, torch.tensor(l))  # exact epsilon: exact x0 up to float error
        assert torch.isfinite(rec).all()
        torch.testing.assert_close(rec, x0, atol=2e-3 if l == -15.0 else 1e-5, rtol=0)
    # a wrong epsilon at alpha ~ 5e-4 is amplified ~1800x: clamping keeps x0 in range
    a, s = alpha_sigma(torch.tensor(-15.0))
    bad = predict_x0(a * x0 + s * eps, eps + 0.5, torch.tensor(-15.0))
    assert bad.abs().max() <= 1.0 and torch.isfinite(bad).all()
    inf_eps = predict_x0(x0, torch.full_like(x0, float("nan")), torch.tensor(-15.0))
    assert torch.isfinite(inf_eps).all()


@pytest.mark.parametrize("name", ["ddpm", "ddim", "dpmpp_2m", "dpmpp_3m", "unipc", "unipc_karras", "dpmpp_3m_logsnr"])
@pytest.mark.parametrize("steps", [1, 2, 7])
def test_samplers_cover_t1_to_t0_and_stay_finite(name, steps):
    sched = make_scheduler(name)
    sched.set_timesteps(steps)
    assert sched.timesteps[0].item() == 1.0 and len(sched.timesteps) == steps
    assert sched.logsnr_at(1.0).item() == pytest.approx(-15.0, abs=1e-5)
    g = [torch.Generator().manual_seed(i) for i in range(3)]
    x = torch.randn(3, 2, 4, 8)
    for t in sched.timesteps:
        # extreme model outputs (huge, zero) must not produce NaN/Inf
        out = sched.step(torch.full_like(x, 1e6) if t > 0.5 else torch.zeros_like(x), t, x, generator=g)
        x = out.prev_sample
        assert torch.isfinite(x).all() and out.pred_original_sample.abs().max() <= 1.0
    # at t = 0 (logSNR 15) the sample is the clamped x0 prediction up to sigma ~5.5e-4
    assert x.clamp(-1, 1).abs().max() <= 1.0
    with pytest.raises(RuntimeError):
        sched.step(torch.zeros_like(x), 0.0, x, generator=g)


def test_oracle_epsilon_recovers_the_data_with_every_sampler():
    x0 = torch.rand(2, 2, 4, 8, generator=torch.Generator().manual_seed(1)) * 1.6 - 0.8
    for name in SAMPLER_NAMES:
        sched = make_scheduler(name)
        sched.set_timesteps(10)
        g = [torch.Generator().manual_seed(i) for i in range(2)]
        x = torch.randn(x0.shape, generator=torch.Generator().manual_seed(2))
        for t in sched.timesteps:
            a, s = alpha_sigma(sched.logsnr_at(t))
            eps = (x - a * x0) / s  # the exact noise a perfect denoiser would predict
            x = sched.step(eps, t, x, generator=g).prev_sample
        torch.testing.assert_close(x.clamp(-1, 1), x0, atol=2e-3, rtol=0)


def test_ddpm_equals_ddim_eta1_and_dpm_first_order_equals_ddim():
    x = torch.randn(2, 2, 4, 8)
    eps = torch.randn(2, 2, 4, 8)
    ddpm, ddim1 = DDPMScheduler(), DDIMScheduler(eta=1.0)
    ddpm.set_timesteps(5)
    ddim1.set_timesteps(5)
    t = ddpm.timesteps[1]
    for s in (ddpm, ddim1):
        s._step_index = 1
    a = ddpm.step(eps, t, x, generator=torch.Generator().manual_seed(0)).prev_sample
    b = ddim1.step(eps, t, x, generator=torch.Generator().manual_seed(0)).prev_sample
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    ddim0, dpm = DDIMScheduler(), DPMSolverPlusPlus2MScheduler()
    for s in (ddim0, dpm):
        s.set_timesteps(5)
    torch.testing.assert_close(ddim0.step(eps, 1.0, x).prev_sample, dpm.step(eps, 1.0, x).prev_sample, atol=1e-5, rtol=1e-5)


def test_ddim_matches_diffusers_on_a_shared_grid():
    """Our continuous DDIM step equals diffusers' DDIMScheduler when both use the same alphas."""
    from diffusers import DDIMScheduler as HFDDIM

    n_train = 1000
    t_grid = torch.arange(1, n_train + 1, dtype=torch.float64) / n_train  # train step k <-> t = (k+1)/n
    abar = torch.sigmoid(S.logsnr(t_grid))
    betas = 1 - abar / torch.cat([torch.ones(1, dtype=torch.float64), abar[:-1]])
    hf = HFDDIM(num_train_timesteps=n_train, trained_betas=betas.numpy(), clip_sample=True, set_alpha_to_one=False,
                steps_offset=0, timestep_spacing="leading")
    hf.set_timesteps(4)  # timesteps 750, 500, 250, 0
    k, k_prev = int(hf.timesteps[1]), int(hf.timesteps[2])
    x = torch.randn(1, 2, 4, 8, dtype=torch.float64).float()
    eps = torch.randn(1, 2, 4, 8).float()
    # diffusers re-derives epsilon from the clipped x0 only when asked; we always do
    ref = hf.step(eps, k, x, eta=0.0, use_clipped_model_output=True).prev_sample
    ours = DDIMScheduler()
    ours.set_timesteps(2)  # then place our grid on diffusers' two timesteps (t = (k + 1) / n)
    ours._grid = torch.tensor([(k + 1) / n_train, (k_prev + 1) / n_train, 0.0], dtype=torch.float64)
    ours._logsnr = S.logsnr(ours._grid)
    got = ours.step(eps, ours._grid[0], x).prev_sample
    np.testing.assert_allclose(got.numpy(), ref.numpy(), atol=1e-4)


def test_unknown_sampler_and_bad_steps():
    with pytest.raises(ValueError):
        make_scheduler("euler")
    with pytest.raises(ValueError):
        DDIMScheduler().set_timesteps(0)
    s = DDPMScheduler()
    s.set_timesteps(2)
    with pytest.raises(ValueError):  # ancestral steps need an explicit generator
        s.step(torch.zeros(1, 2, 2, 2), 1.0, torch.zeros(1, 2, 2, 2), generator=None)
    with pytest.raises(ValueError):  # a timestep off the grid
        d = DDIMScheduler()
        d.set_timesteps(2)
        d.step(torch.zeros(1, 2, 2, 2), 0.3, torch.zeros(1, 2, 2, 2))


# Gaussian data N(MU, SD^2): the exact denoiser is known, and the probability-flow ODE keeps
# (x_t - alpha MU) / sqrt(alpha^2 SD^2 + sigma^2) constant, so every solver's error is measurable.
MU, SD = 0.3, 0.2


def _gaussian_ode_error(name: str, steps: int) -> float:
    sched = make_scheduler(name, clip_sample=False)
    sched.set_timesteps(steps)
    x1 = torch.randn(2048, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x = x1.clone()
    for t in sched.timesteps:
        a, s = (v.double() for v in alpha_sigma(sched.logsnr_at(t).double()))
        x0 = MU + a * SD**2 / (a**2 * SD**2 + s**2) * (x - a * MU)
        x = sched.step(((x - a * x0) / s).float(), t, x.float()).prev_sample.double()
    (a1, s1), (a0, s0) = (alpha_sigma(torch.tensor(v, dtype=torch.float64)) for v in (-15.0, 15.0))
    exact = a0 * MU + torch.sqrt(a0**2 * SD**2 + s0**2) * (x1 - a1 * MU) / torch.sqrt(a1**2 * SD**2 + s1**2)
    return float((x - exact).abs().max())


@pytest.mark.parametrize("name,order", [("ddim_logsnr", 1), ("dpmpp_2m_logsnr", 2), ("dpmpp_3m_logsnr", 2),
                                        ("unipc_logsnr", 3)])
def test_solvers_converge_at_their_order_on_gaussian_data(name, order):
    """Doubling the steps divides the error by about 2^order (UniPC-2 with its corrector is third
    order; DPM-Solver++ 3M's first-order last step holds it at second order)."""
    coarse, fine = _gaussian_ode_error(name, 64), _gaussian_ode_error(name, 128)
    assert coarse / fine > 0.8 * 2**order, (coarse, fine)


def test_higher_order_solvers_beat_ddim_at_a_small_budget():
    ddim = _gaussian_ode_error("ddim_logsnr", 16)
    for name in ("dpmpp_2m_logsnr", "dpmpp_3m_logsnr", "unipc_logsnr"):
        assert _gaussian_ode_error(name, 16) < ddim / 3, name


@pytest.mark.parametrize("spacing", ["uniform", "logsnr", "karras"])
def test_time_grids_run_from_1_to_0_and_karras_is_densest_near_the_data(spacing):
    schedule = CosineLogSNRSchedule()
    grid = time_grid(schedule, 12, spacing)
    assert grid[0] == 1.0 and grid[-1] == 0.0 and len(grid) == 13 and (grid.diff() < 0).all()
    if spacing == "karras":  # sigma steps shrink toward the data: the last sigma step is the smallest
        sigma = torch.exp(-0.5 * schedule.logsnr(grid))
        steps = -sigma.diff()
        assert steps[-1] < steps[0] / 100


def test_sampler_names_and_the_schemas_agree():
    import yaml

    from workflow_helpers import ROOT

    assert {n.rsplit("_", 1)[0] if n.endswith(("_logsnr", "_karras")) else n for n in SAMPLER_NAMES} == set(SAMPLERS)
    for schema, path in (("generator", ("properties", "sampling", "properties", "sampler")),
                         ("evaluation", ("properties", "sampler"))):
        node = yaml.safe_load((ROOT / "workflow" / "schemas" / f"{schema}.schema.yaml").read_text())
        for key in path:
            node = node[key]
        assert node["enum"] == list(SAMPLER_NAMES), schema
    assert make_scheduler("dpmpp_3m_karras").spacing == "karras" and make_scheduler("unipc").spacing == "uniform"
    with pytest.raises(ValueError, match="unknown sampler"):
        make_scheduler("unipc_cosine")


@pytest.mark.parametrize("spacing", ["uniform", "logsnr", "karras"])
def test_a_grid_started_part_way_runs_from_there_to_the_data(spacing):
    schedule = CosineLogSNRSchedule()
    grid = time_grid(schedule, 5, spacing, start=0.4)
    assert grid[0] == 0.4 and grid[-1] == 0.0 and len(grid) == 6 and (grid.diff() < 0).all()
    if spacing != "uniform":  # the spacing is kept between logSNR(0.4) and the clean end
        full = schedule.logsnr(time_grid(schedule, 5, spacing, start=1.0))
        assert schedule.logsnr(grid)[0] > full[0] + 10
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="starts in"):
            time_grid(schedule, 5, spacing, start=bad)


def test_oracle_epsilon_from_a_part_way_start_recovers_the_data():
    """A scan noised to t = 0.5 and run down from there by every solver comes back."""
    x0 = torch.rand(2, 2, 4, 8, generator=torch.Generator().manual_seed(1)) * 1.6 - 0.8
    for name in SAMPLER_NAMES:
        sched = make_scheduler(name)
        sched.set_timesteps(5, start=0.5)
        assert sched.timesteps[0].item() == 0.5
        a, s = alpha_sigma(sched.logsnr_at(0.5))
        x = a * x0 + s * torch.randn(x0.shape, generator=torch.Generator().manual_seed(2))
        g = [torch.Generator().manual_seed(i) for i in range(2)]
        for t in sched.timesteps:
            a, s = alpha_sigma(sched.logsnr_at(t))
            x = sched.step((x - a * x0) / s, t, x, generator=g).prev_sample
        torch.testing.assert_close(x.clamp(-1, 1), x0, atol=2e-3, rtol=0)
