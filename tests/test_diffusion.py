"""Noise schedule and DDIM/DDPM sampling: determinism, exact CFG = 0 reproduction, Gaussian sanity."""

import math

import pytest
import torch
from torch import nn

from cmtool.core.errors import CmtoolError
from cmtool.diffusion.noise import step_generator
from cmtool.diffusion.samplers import StepInfo, sample
from cmtool.diffusion.schedule import NoiseSchedule
from cmtool.model.config import ControlConfig, DiTConfig, ScheduleConfig
from cmtool.model.controlmap import ControlMap
from cmtool.model.dit import DiT
from tests.conftest import perturb

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny models run fastest single-threaded

SCHEDULE = NoiseSchedule(ScheduleConfig())
CONTROL = ControlConfig(num_blocks=2, widths=(16, 16, 32, 32), groups=8)


@pytest.fixture(scope="module")
def models():
    """A perturbed small DiT and a "trained-looking" ControlMap on it (branch perturbed too)."""
    torch.manual_seed(0)
    dit = DiT(DiTConfig(depth=3, hidden=64, heads=4))
    perturb(dit)
    cm = ControlMap(dit, CONTROL)
    perturb(cm.encoder), perturb(cm.proj), perturb(cm.copies), perturb(cm.zero)
    return dit, cm


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


Y = torch.tensor([0, 3])
CTRL = torch.rand(2, 3, 128, 128, generator=gen(9))


def test_min_snr_weights_count_nearly_clean_steps_less():
    t = torch.tensor([0, 100, 500, 999])
    w = SCHEDULE.min_snr_weight(t, 5.0)
    ab = SCHEDULE.alphas_cumprod[t]
    snr = ab / (1 - ab)
    assert torch.allclose(w, (torch.minimum(snr, torch.tensor(5.0)) / snr).float())
    assert w[0] < 0.01 and w[-1] == 1.0  # t = 0: SNR about 1e4; t = 999: SNR far below 5
    assert torch.all(w[1:] >= w[:-1])


def test_linear_and_cosine_schedules():
    assert SCHEDULE.betas[0].item() == pytest.approx(1e-4) and SCHEDULE.betas[-1].item() == pytest.approx(0.02)
    for schedule in (SCHEDULE, NoiseSchedule(ScheduleConfig(kind="cosine"))):
        ab = schedule.alphas_cumprod
        assert ab.shape == (1000,) and (ab.diff() < 0).all() and 0 < ab[-1] < 0.01 and ab[0] > 0.99
    with pytest.raises(CmtoolError, match="schedule.kind"):
        NoiseSchedule(ScheduleConfig(kind="sigmoid"))


def test_q_sample_predict_x0_roundtrip():
    g = gen()
    x0, noise = torch.randn(5, 64, 8, 8, generator=g), torch.randn(5, 64, 8, 8, generator=g)
    t = torch.tensor([0, 1, 250, 500, 999])
    x_t = SCHEDULE.q_sample(x0, t, noise)
    assert torch.allclose(SCHEDULE.predict_x0(x_t, t, noise), x0, atol=1e-3)
    ab = SCHEDULE.alphas_cumprod[500].item()
    assert torch.allclose(x_t[3], math.sqrt(ab) * x0[3] + math.sqrt(1 - ab) * noise[3], atol=1e-6)


def test_timesteps():
    ts = SCHEDULE.timesteps(50)
    assert len(ts) == 50 and ts[0] == 999 and ts[-1] == 0
    steps = [a - b for a, b in zip(ts, ts[1:])]
    assert min(steps) >= 20 and max(steps) <= 21
    assert SCHEDULE.timesteps(1000) == list(range(999, -1, -1))
    assert SCHEDULE.timesteps(1) == [999]
    for bad in (0, 1001):
        with pytest.raises(ValueError, match="steps"):
            SCHEDULE.timesteps(bad)


@pytest.mark.parametrize("sampler, eta", [("ddpm", 0.0), ("ddpm-trailing", 0.0), ("ddim", 0.5), ("dpm++2m-sde", 0.0)])
def test_same_seed_same_samples(models, sampler, eta):
    dit, _ = models
    run = lambda seed: sample(dit, SCHEDULE, Y, steps=6, sampler=sampler, eta=eta, generator=gen(seed))
    a, b, c = run(1), run(1), run(2)
    assert a.shape == (2, 64, 8, 8) and torch.isfinite(a).all()
    assert torch.equal(a, b) and not torch.allclose(a, c)


def test_ddim_eta0_is_deterministic_given_the_noise(models):
    dit, _ = models
    noise = torch.randn(2, 64, 8, 8, generator=gen(5))
    a = sample(dit, SCHEDULE, Y, steps=6, sampler="ddim", noise=noise, generator=gen(1))
    b = sample(dit, SCHEDULE, Y, steps=6, sampler="ddim", noise=noise, generator=gen(2))
    assert torch.equal(a, b)


def test_step_noise_is_a_stream_apart_from_the_initial_noise(models):
    """Seeding the step noise like x_T would add x_T back in at the first DDPM step."""
    dit, _ = models
    shape = (len(Y), *dit.latent_shape)
    x_t = torch.randn(shape, generator=torch.Generator().manual_seed(3))
    assert torch.equal(torch.randn(shape, generator=torch.Generator().manual_seed(3)), x_t)  # the trap
    assert not torch.allclose(torch.randn(shape, generator=step_generator(3)), x_t, atol=0.5)
    run = lambda: sample(dit, SCHEDULE, Y, steps=3, sampler="ddpm", noise=x_t, generator=step_generator(3))
    assert torch.equal(run(), run())


def test_ddim_eta1_matches_ddpm(models):
    dit, _ = models
    a = sample(dit, SCHEDULE, Y, steps=8, sampler="ddim", eta=1.0, generator=gen(4))
    b = sample(dit, SCHEDULE, Y, steps=8, sampler="ddpm", generator=gen(4))
    assert torch.allclose(a, b, atol=1e-3, rtol=1e-3)


@pytest.mark.parametrize("sampler", ["ddim", "ddpm", "ddpm-trailing", "dpm++2m", "dpm++2m-sde"])
def test_cfg_zero_reproduces_the_base_model_exactly(models, sampler):
    dit, cm = models
    kw = dict(steps=6, sampler=sampler, eta=0.7)
    base = sample(dit, SCHEDULE, Y, generator=gen(3), **kw)
    assert torch.equal(sample(cm, SCHEDULE, Y, control=CTRL, cfg=0.0, generator=gen(3), **kw), base)
    assert torch.equal(sample(cm, SCHEDULE, Y, control=None, cfg=2.0, generator=gen(3), **kw), base)
    assert not torch.allclose(sample(cm, SCHEDULE, Y, control=CTRL, cfg=1.0, generator=gen(3), **kw), base)


def test_callback_sees_every_step_and_the_residuals(models):
    _, cm = models
    infos: list[StepInfo] = []
    out = sample(cm, SCHEDULE, Y, control=CTRL, cfg=0.5, steps=5, generator=gen(), callback=infos.append)
    assert [i.step for i in infos] == list(range(5)) and [i.t for i in infos] == SCHEDULE.timesteps(5)
    for info in infos:
        assert info.x_t.shape == info.x0.shape == info.eps.shape == info.eps_cond.shape == (2, 64, 8, 8)
        assert torch.allclose(info.eps, info.eps_uncond + 0.5 * (info.eps_cond - info.eps_uncond))
        assert len(info.residuals) == 2 and all(r.shape == (2, 64, 64) for r in info.residuals)
        assert all(r.abs().sum() > 0 for r in info.residuals)
    assert not torch.equal(infos[0].x_t, infos[1].x_t) and not torch.equal(infos[-1].x_t, out)
    t = torch.full((2,), infos[2].t)
    assert torch.allclose(infos[2].x0, SCHEDULE.predict_x0(infos[2].x_t, t, infos[2].eps))
    plain: list[StepInfo] = []
    sample(cm, SCHEDULE, Y, control=CTRL, cfg=0.0, steps=3, generator=gen(), callback=plain.append)
    assert len(plain) == 3 and all(i.eps_cond is None and i.residuals is None for i in plain)
    assert all(torch.equal(i.eps, i.eps_uncond) for i in plain)


def test_guidance_at_w1_is_one_pass_of_the_conditioned_rows(models):
    """At w = 1 the guided prediction is the conditioned one: one pass of the B conditioned rows, no unconditioned
    pass; each step's prediction equals the two-pass formula within float rounding."""
    _, cm = models
    infos: list[StepInfo] = []
    calls = {"cfg": 0}
    two_pass = cm.forward_cfg

    def counted(*args, **kwargs):
        calls["cfg"] += 1
        return two_pass(*args, **kwargs)

    cm.forward_cfg = counted
    try:
        sample(cm, SCHEDULE, Y, control=CTRL, cfg=1.0, steps=4, generator=gen(4), callback=infos.append)
    finally:
        del cm.forward_cfg
    assert calls["cfg"] == 0 and len(infos) == 4
    tokens = cm.encode_control(CTRL)
    for info in infos:
        assert info.eps_uncond is None and torch.equal(info.eps, info.eps_cond) and len(info.residuals) == 2
        with torch.no_grad():
            cond, uncond, _ = cm.forward_cfg(info.x_t, torch.full((2,), info.t), Y, tokens=tokens)
        assert torch.allclose(info.eps, uncond + 1.0 * (cond - uncond), atol=1e-5)


@pytest.mark.parametrize("cfg", [-0.1, float("nan"), float("inf")])
def test_invalid_cfg_raises(models, cfg):
    _, cm = models
    with pytest.raises(ValueError, match="cfg"):
        sample(cm, SCHEDULE, Y, control=CTRL, cfg=cfg, steps=2)


def test_city_cfg_is_guidance_on_the_city_label(models):
    dit, cm = models  # Y = [city 0, the null label 3]
    kw = dict(steps=4, sampler="ddpm")
    assert torch.equal(sample(cm, SCHEDULE, Y, control=CTRL, cfg=0.5, city_cfg=1.0, generator=gen(2), **kw),
                       sample(cm, SCHEDULE, Y, control=CTRL, cfg=0.5, generator=gen(2), **kw))
    infos: list[StepInfo] = []
    out = sample(cm, SCHEDULE, Y, control=CTRL, cfg=0.5, city_cfg=3.0, generator=gen(2), callback=infos.append, **kw)
    null = torch.full_like(Y, dit.null_label)
    for info in infos:
        t = torch.full((2,), info.t)
        with torch.no_grad():
            e_cond, e_city, e_null = cm(info.x_t, t, Y, CTRL), dit(info.x_t, t, Y), dit(info.x_t, t, null)
        expected = e_null + 3.0 * (e_city - e_null) + 0.5 * (e_cond - e_city)
        assert torch.allclose(info.eps, expected, rtol=1e-4, atol=1e-3)
        assert torch.allclose(info.eps, info.eps_uncond + 0.5 * (info.eps_cond - info.eps_uncond), atol=1e-6)
    plain = sample(cm, SCHEDULE, Y, control=CTRL, cfg=0.5, generator=gen(2), **kw)
    assert not torch.allclose(out[0], plain[0], atol=1e-3)  # the city's map moves ...
    assert torch.allclose(out[1], plain[1], rtol=1e-4, atol=1e-3)  # ... a map without a city does not
    with pytest.raises(ValueError, match="city_cfg"):
        sample(dit, SCHEDULE, Y, city_cfg=-1.0, steps=2)


def test_invalid_arguments_raise(models):
    dit, _ = models
    with pytest.raises(CmtoolError, match="control"):
        sample(dit, SCHEDULE, Y, control=CTRL, steps=2)
    with pytest.raises(CmtoolError, match="sampler"):
        sample(dit, SCHEDULE, Y, sampler="euler", steps=2)
    with pytest.raises(CmtoolError, match="noise"):
        sample(dit, SCHEDULE, Y, noise=torch.zeros(3, 64, 8, 8), steps=2)


class GaussianEps(nn.Module):
    """The exact noise predictor E[eps | x_t] for data x0 ~ N(mu, s^2) per channel."""

    latent_shape = (64, 8, 8)

    def __init__(self, schedule: NoiseSchedule, mu: torch.Tensor, s: torch.Tensor):
        super().__init__()
        self.ab, self.mu, self.s = schedule.alphas_cumprod, mu.view(1, -1, 1, 1), s.view(1, -1, 1, 1)

    def forward(self, x, t, y):
        ab = self.ab[t].float().view(-1, 1, 1, 1)
        return (1 - ab).sqrt() * (x - ab.sqrt() * self.mu) / (ab * self.s**2 + 1 - ab)


@pytest.mark.parametrize("sampler", ["ddpm", "ddim"])
def test_exact_predictor_recovers_a_gaussian(sampler):
    mu, s = torch.linspace(-1.0, 2.0, 64), torch.linspace(0.2, 1.5, 64)
    y = torch.zeros(64, dtype=torch.long)
    out = sample(GaussianEps(SCHEDULE, mu, s), SCHEDULE, y, steps=1000, sampler=sampler, generator=gen(7))
    per_channel = out.transpose(0, 1).reshape(64, -1)
    assert torch.allclose(per_channel.mean(1), mu, atol=0.08)
    assert torch.allclose(per_channel.std(1), s, rtol=0.06)


@pytest.mark.parametrize("sampler, steps", [("dpm++2m", 10), ("dpm++2m-sde", 20)])
def test_dpm_solvers_recover_a_gaussian_in_few_steps(sampler, steps):
    mu, s = torch.linspace(-1.0, 2.0, 64), torch.linspace(0.2, 1.5, 64)
    y = torch.zeros(64, dtype=torch.long)
    out = sample(GaussianEps(SCHEDULE, mu, s), SCHEDULE, y, steps=steps, sampler=sampler, generator=gen(7))
    per_channel = out.transpose(0, 1).reshape(64, -1)
    assert torch.allclose(per_channel.mean(1), mu, atol=0.08)
    assert torch.allclose(per_channel.std(1), s, rtol=0.08)


def test_dpm_solver_follows_the_ode_closer_than_ddim_in_as_many_steps():
    """The deterministic samplers solve one ODE from the same x_T: DDIM in 1,000 steps is its solution."""
    mu, s = torch.linspace(-1.0, 2.0, 64), torch.linspace(0.2, 1.5, 64)
    model, y = GaussianEps(SCHEDULE, mu, s), torch.zeros(16, dtype=torch.long)
    noise = torch.randn(16, 64, 8, 8, generator=gen(9))
    ode = sample(model, SCHEDULE, y, steps=1000, sampler="ddim", noise=noise)
    error = {name: float((sample(model, SCHEDULE, y, steps=10, sampler=name, noise=noise) - ode).abs().mean())
             for name in ("ddim", "dpm++2m")}
    assert error["dpm++2m"] < 0.5 * error["ddim"]


class CityGaussianEps(GaussianEps):
    """The exact predictor when label 0's data is N(mu, s^2) and, without a city (label 1), N(0, s^2)."""

    null_label = 1

    def forward(self, x, t, y):
        ab = self.ab[t].float().view(-1, 1, 1, 1)
        mu = self.mu * (y != self.null_label).float().view(-1, 1, 1, 1)
        return (1 - ab).sqrt() * (x - ab.sqrt() * mu) / (ab * self.s**2 + 1 - ab)


def test_city_guidance_of_gaussians_moves_the_mean_by_its_weight():
    # guided score 2 score(N(mu)) - score(N(0)) is the score of N(2 mu) at every noise level
    mu, s = torch.linspace(-0.5, 0.5, 64), torch.linspace(0.3, 1.0, 64)
    y = torch.tensor([0] * 64 + [1] * 64)
    out = sample(CityGaussianEps(SCHEDULE, mu, s), SCHEDULE, y, city_cfg=2.0, steps=1000, generator=gen(8))
    city, none = (part.transpose(0, 1).reshape(64, -1) for part in (out[:64], out[64:]))
    assert torch.allclose(city.mean(1), 2 * mu, atol=0.08) and torch.allclose(city.std(1), s, rtol=0.06)
    assert torch.allclose(none.mean(1), torch.zeros(64), atol=0.08)


def test_logsnr_timesteps_are_distinct_and_denser_near_the_data():
    for n in (2, 5, 10, 20, 999, 1000):
        ts = SCHEDULE.timesteps(n, "logsnr")
        assert len(ts) == n and ts[0] == 999 and ts[-1] == 0 and all(a > b for a, b in zip(ts, ts[1:]))
    assert SCHEDULE.timesteps(1, "logsnr") == [999]
    assert SCHEDULE.timesteps(10, "logsnr")[-2] < SCHEDULE.timesteps(10)[-2] / 10


def test_trailing_timesteps_leave_out_t0_and_the_last_step_lands_on_the_clean_estimate(models):
    for n in (1, 2, 3, 7, 50, 999, 1000):
        ts = SCHEDULE.timesteps(n, "trailing")
        assert len(ts) == n and ts[0] == 999 and all(a > b for a, b in zip(ts, ts[1:]))
        assert ts[-1] == round(1000 / n) - 1  # a whole interval above t = 0 (t = 0 only at 1000 steps)
    assert SCHEDULE.timesteps(2, "trailing") == [999, 499] and SCHEDULE.timesteps(2, "trailing", top=300) == [300, 149]
    with pytest.raises(CmtoolError, match="trailing steps"):
        SCHEDULE.timesteps(5, "trailing", top=3)
    _, cm = models
    infos: list[StepInfo] = []
    x = sample(cm, SCHEDULE, Y, control=CTRL, cfg=1.0, steps=2, sampler="ddpm-trailing", generator=gen(2),
               callback=infos.append)
    assert [i.t for i in infos] == [999, 499] and torch.equal(x, infos[-1].x0)
    calls = []  # from a start noised 0.3 of the way up, both steps run below it
    sample(cm, SCHEDULE, Y, control=CTRL, cfg=1.0, steps=2, sampler="ddpm-trailing", init=torch.zeros_like(x),
           strength=0.3, generator=gen(2), callback=lambda info: calls.append(info.t))
    assert calls == [300, 149]


@pytest.mark.parametrize("sampler", ["ddpm", "ddpm-trailing", "ddim", "dpm++2m-sde"])
def test_sdedit_keeps_more_of_the_start_the_lower_the_strength(models, sampler):
    dit, cm = models
    init = torch.randn(2, *dit.latent_shape, generator=gen(5))
    noise = torch.randn(2, *dit.latent_shape, generator=gen(6))
    dists = []
    for strength in (0.02, 0.3, 1.0):
        calls = []
        x = sample(cm, SCHEDULE, Y, control=CTRL, cfg=1.0, steps=20, sampler=sampler, noise=noise, init=init,
                   strength=strength, generator=gen(1), callback=lambda info: calls.append(info.t))
        assert max(calls) <= round(strength * (SCHEDULE.train_steps - 1)) and calls == sorted(calls, reverse=True)
        dists.append(float((x - init).pow(2).mean()))
    assert dists[0] < dists[1] < dists[2] and dists[0] < 0.05 * dists[2]  # a small strength keeps the start
    plain = sample(cm, SCHEDULE, Y, control=CTRL, cfg=1.0, steps=20, sampler=sampler, noise=noise, generator=gen(1))
    assert not torch.equal(plain, sample(cm, SCHEDULE, Y, control=CTRL, cfg=1.0, steps=20, sampler=sampler,
                                         noise=noise, init=init, strength=0.3, generator=gen(1)))
    for bad in (0.0, 1.5, math.nan):
        with pytest.raises(CmtoolError, match="strength"):
            sample(cm, SCHEDULE, Y, steps=3, init=init, strength=bad)
    with pytest.raises(CmtoolError, match="init: expected shape"):
        sample(cm, SCHEDULE, Y, steps=3, init=init[:1], strength=0.5)
