"""Tests of the joint hysteresis GP (diffaccel.hysteresis.hgp)."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from botorch.acquisition import UpperConfidenceBound, qLogExpectedImprovement
from botorch.fit import fit_gpytorch_mll
from botorch.models import SingleTaskGP
from botorch.models.transforms.input import Normalize
from botorch.optim import optimize_acqf
from gpytorch.constraints import Positive
from gpytorch.kernels import LinearKernel
from gpytorch.likelihoods import (
    BernoulliLikelihood,
    FixedNoiseGaussianLikelihood,
    GaussianLikelihood,
    MultitaskGaussianLikelihood,
    StudentTLikelihood,
)
from gpytorch.likelihoods.gaussian_likelihood import _GaussianLikelihoodBase
from gpytorch.likelihoods.noise_models import HeteroskedasticNoise
from gpytorch.means import ConstantMean
from gpytorch.mlls import ExactMarginalLogLikelihood
from linear_operator.utils.errors import NotPSDError

from diffaccel.hysteresis import (
    HysteresisGP,
    PreisachMesh,
    PreisachModel,
    fit_hysteresis_gp,
)
from diffaccel.hysteresis.hgp import magnetization_feature

DT = torch.float64
I_MAX = 10.0


@pytest.fixture(autouse=True)
def _quiet_numerics_one_thread():
    # ~50-point GPs are fastest single-threaded; with several threads the
    # OpenMP workers spin against each other on a busy 2-core machine
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*not p.d.*")
        warnings.filterwarnings("ignore", message=".*unit cube.*")
        yield
    torch.set_num_threads(threads)


def _cycles(n_cycles: int, n_per_cycle: int) -> torch.Tensor:
    half = n_per_cycle // 2
    up = torch.linspace(0.0, I_MAX, half + 1, dtype=DT)[:-1]
    down = torch.linspace(I_MAX, 0.0, half + 1, dtype=DT)[:-1]
    return torch.cat([up, down] * n_cycles)


def _preisach(n: int = 10, density: torch.Tensor | None = None) -> PreisachModel:
    pm = PreisachModel(PreisachMesh.triangular(n=n), input_range=(0.0, I_MAX))
    if density is not None:
        pm.density = density
    return pm


def _truth(n: int = 20) -> PreisachModel:
    pm = _preisach(n)
    a, b = pm.alpha, pm.beta
    pm.density = (
        torch.exp(-((a + b - 1) ** 2) / 0.08 - (a - b - 0.35) ** 2 / 0.04) + 0.02
    )
    return pm


def _data(seed: int, noise: float, n_cycles: int = 3, n_per_cycle: int = 20):
    gen = torch.Generator().manual_seed(seed)
    u = _cycles(n_cycles, n_per_cycle)
    with torch.no_grad():
        m = _truth().magnetization(u)
    f = 0.15 + 0.8 * torch.exp(-((m - 0.25) ** 2) / (2 * 0.35**2))
    y = f + noise * torch.randn(f.shape, generator=gen, dtype=DT)
    return u.unsqueeze(-1), y.unsqueeze(-1), f


def _small_model(
    seed: int = 0, d_plain: int = 0, smoothing: float | None = None
) -> HysteresisGP:
    X, Y, _ = _data(seed, 0.02, n_cycles=2, n_per_cycle=16)
    gen = torch.Generator().manual_seed(seed + 1)
    if d_plain:
        plain = torch.rand(X.shape[0], d_plain, generator=gen, dtype=DT)
        X = torch.cat([X, plain], dim=-1)
        Y = Y + 0.1 * plain.sum(-1, keepdim=True)
    return HysteresisGP(
        X, Y, hysteresis={0: _preisach(8)}, candidate_smoothing=smoothing
    )


# ----------------------------------------------------------------- identity


def test_no_hysteresis_equals_single_task_gp_with_same_hyperparameters() -> None:
    gen = torch.Generator().manual_seed(0)
    X = torch.rand(25, 2, generator=gen, dtype=DT) * 4.0 - 1.0
    Y = torch.sin(2 * X[:, :1]) + X[:, 1:] ** 2
    bounds = torch.tensor([[-1.0, -1.0], [3.0, 3.0]], dtype=DT)
    stgp = SingleTaskGP(X, Y, input_transform=Normalize(d=2, bounds=bounds))
    hgp = HysteresisGP(X, Y, hysteresis={}, bounds=bounds)
    with torch.no_grad():
        for m in (stgp, hgp.gp):
            m.covar_module.lengthscale = torch.tensor([[0.4, 0.9]], dtype=DT)
            m.likelihood.noise = torch.tensor([3e-3], dtype=DT)
            m.mean_module.constant.fill_(0.2)
    Xt = torch.rand(7, 3, 2, generator=gen, dtype=DT) * 4.0 - 1.0
    p1, p2 = stgp.posterior(Xt), hgp.posterior(Xt)
    # same model, same float64 linear algebra: agreement to round-off
    torch.testing.assert_close(p2.mean, p1.mean, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(
        p2.distribution.covariance_matrix,
        p1.distribution.covariance_matrix,
        rtol=1e-8,
        atol=1e-10,
    )


def test_no_hysteresis_fit_reaches_single_task_gp_optimum() -> None:
    gen = torch.Generator().manual_seed(1)
    X = torch.rand(30, 1, generator=gen, dtype=DT)
    Y = torch.sin(6 * X) + 0.05 * torch.randn(30, 1, generator=gen, dtype=DT)
    bounds = torch.tensor([[0.0], [1.0]], dtype=DT)
    stgp = SingleTaskGP(X, Y, input_transform=Normalize(d=1, bounds=bounds))
    mll = ExactMarginalLogLikelihood(stgp.likelihood, stgp)
    fit_gpytorch_mll(mll)
    stgp.train()
    with torch.no_grad():
        ref = float(mll(stgp(*stgp.train_inputs), stgp.train_targets))
    hgp = HysteresisGP(X, Y, hysteresis={}, bounds=bounds)
    res = fit_hysteresis_gp(hgp, restarts=1)
    # both run L-BFGS-B to convergence on the same objective: optimum agrees to
    # the optimiser tolerance, far below the MLL differences between fits
    assert res.mll == pytest.approx(ref, abs=1e-4)


def test_fixed_noise_without_hysteresis_equals_single_task_gp() -> None:
    gen = torch.Generator().manual_seed(2)
    X = torch.rand(20, 1, generator=gen, dtype=DT)
    Y = torch.cos(5 * X)
    Yvar = 1e-3 + 4e-3 * torch.rand(20, 1, generator=gen, dtype=DT)
    bounds = torch.tensor([[0.0], [1.0]], dtype=DT)
    stgp = SingleTaskGP(X, Y, Yvar, input_transform=Normalize(d=1, bounds=bounds))
    hgp = HysteresisGP(X, Y, hysteresis={}, bounds=bounds, train_Yvar=Yvar)
    assert isinstance(hgp.likelihood, FixedNoiseGaussianLikelihood)
    with torch.no_grad():
        for m in (stgp, hgp.gp):
            m.covar_module.lengthscale = torch.tensor([[0.3]], dtype=DT)
            m.mean_module.constant.fill_(-0.1)
    Xt = torch.rand(4, 3, 1, generator=gen, dtype=DT)
    for noise in (False, True):
        p1 = stgp.posterior(Xt, observation_noise=noise)
        p2 = hgp.posterior(Xt, observation_noise=noise)
        # same fixed-noise model, float64: agreement to round-off
        torch.testing.assert_close(p2.mean, p1.mean, rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(p2.variance, p1.variance, rtol=1e-8, atol=1e-10)
    # the model's noise is the given one, in units of train_Y
    assert float(hgp.noise_sigma) == pytest.approx(float(Yvar.mean().sqrt()), 1e-12)
    X2, Y2 = (
        torch.tensor([[0.2], [0.7]], dtype=DT),
        torch.tensor([[0.1], [0.3]], dtype=DT),
    )
    with pytest.raises(ValueError, match="Yvar is required exactly"):
        hgp.condition_on_observations(X2, Y2)
    new = hgp.condition_on_observations(X2, Y2, noise=torch.full_like(Y2, 2e-3))
    assert isinstance(new.likelihood, FixedNoiseGaussianLikelihood)
    torch.testing.assert_close(new.train_Yvar[-2:], torch.full_like(Y2, 2e-3))


def _dense_exact_mll(model: HysteresisGP) -> torch.Tensor:
    """Exact MLL per point with priors, written out independently of GPyTorch."""
    pm = model.hysteresis_models[0]  # carries the model's density
    with torch.no_grad():
        m = pm.magnetization(model.train_X[:, 0])
    feats = (0.5 * (m + 1.0)).unsqueeze(-1)
    ls = model.gp.covar_module.lengthscale.squeeze()
    diff = (feats - feats.T) / ls
    noise = model.likelihood.noise.squeeze()
    n = feats.shape[0]
    cov = torch.exp(-0.5 * diff**2) + noise * torch.eye(n, dtype=DT)
    y = model.gp.train_targets
    mean = model.gp.mean_module.constant.expand(n)
    value = torch.distributions.MultivariateNormal(mean, cov).log_prob(y)
    value = value + model.gp.likelihood.noise_covar.noise_prior.log_prob(noise)
    value = value + model.gp.covar_module.lengthscale_prior.log_prob(ls)
    magnet = model.gp.features.magnets[0]
    value = value + magnet.density_prior.log_prob(magnet.raw_density).sum()
    return value / n


def test_fit_objective_is_gpytorch_exact_mll() -> None:
    X, Y, _ = _data(0, 0.02, n_cycles=2, n_per_cycle=16)
    model = HysteresisGP(X, Y, hysteresis={0: _truth(8)}, density_prior_scale=0.5)
    gen = torch.Generator().manual_seed(9)
    with torch.no_grad():  # move off the prior centre so the density prior counts
        magnet = model.gp.features.magnets[0]
        magnet.raw_density.add_(
            0.3 * torch.randn(magnet.raw_density.shape, generator=gen, dtype=DT)
        )
    mll = model.marginal_log_likelihood()
    assert type(mll) is ExactMarginalLogLikelihood
    model.train()
    with torch.no_grad():
        gp_value = mll(model.gp(*model.gp.train_inputs), model.gp.train_targets)
    # the same Gaussian density, computed densely: float64 round-off
    torch.testing.assert_close(
        gp_value, _dense_exact_mll(model), rtol=1e-10, atol=1e-12
    )
    res = fit_hysteresis_gp(model, restarts=1, max_iter=40)
    model.train()
    with torch.no_grad():
        after = mll(model.gp(*model.gp.train_inputs), model.gp.train_targets)
    assert res.mll == pytest.approx(float(after), abs=1e-12)
    assert res.mll > float(gp_value) + 0.1  # the fit climbed this objective


def test_priors_are_registered() -> None:
    X, Y, _ = _data(0, 0.02, n_cycles=1, n_per_cycle=10)
    plain = HysteresisGP(X, Y, hysteresis={0: _preisach(5)})
    names = {name for name, *_ in plain.gp.named_priors()}
    assert names == {
        "likelihood.noise_covar.noise_prior",
        "covar_module.lengthscale_prior",
    }
    with_density = HysteresisGP(
        X, Y, hysteresis={0: _preisach(5)}, density_prior_scale=0.7
    )
    priors = {name: prior for name, _, prior, *_ in with_density.gp.named_priors()}
    prior = priors["features.magnets.0.density_prior"]
    raw = with_density.gp.features.magnets[0].raw_density
    torch.testing.assert_close(prior.loc, raw.detach(), rtol=0, atol=0)
    assert float(prior.scale.max()) == pytest.approx(0.7)


def test_density_is_constrained_raw_parameter() -> None:
    model = _small_model()
    magnet = model.gp.features.magnets[0]
    assert isinstance(magnet.raw_density_constraint, Positive)
    with torch.no_grad():
        magnet.raw_density.fill_(-40.0)  # softplus keeps it positive
    assert (magnet.density > 0).all()
    # hysteresis_models carries the model's density (same softplus map)
    torch.testing.assert_close(
        model.hysteresis_models[0].density, magnet.density, rtol=0, atol=0
    )


class _HeteroskedasticGaussian(_GaussianLikelihoodBase):
    def __init__(self) -> None:
        super().__init__(noise_covar=HeteroskedasticNoise(ConstantMean()))


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (BernoulliLikelihood, "needs a Gaussian likelihood; got BernoulliLikelihood"),
        (StudentTLikelihood, "needs a Gaussian likelihood; got StudentTLikelihood"),
        (_HeteroskedasticGaussian, "homoskedastic .* HeteroskedasticNoise"),
        (
            lambda: FixedNoiseGaussianLikelihood(noise=torch.full((10,), 1e-3)),
            "train_Yvar",
        ),
        (lambda: MultitaskGaussianLikelihood(num_tasks=2), "homoskedastic"),
    ],
    ids=[
        "bernoulli",
        "student-t",
        "heteroskedastic",
        "fixed-noise-object",
        "multitask",
    ],
)
def test_unsupported_likelihood_raises(make, match: str) -> None:
    X, Y, _ = _data(0, 0.02, n_cycles=1, n_per_cycle=10)
    with pytest.raises(ValueError, match=match):
        HysteresisGP(X, Y, hysteresis={0: _preisach(5)}, likelihood=make())


def test_train_yvar_checks() -> None:
    X, Y, _ = _data(0, 0.02, n_cycles=1, n_per_cycle=10)
    with pytest.raises(ValueError, match="negative"):
        HysteresisGP(X, Y, hysteresis={}, train_Yvar=-torch.ones_like(Y))
    with pytest.raises(ValueError, match=r"shape \(n, 1\)"):
        HysteresisGP(X, Y, hysteresis={}, train_Yvar=torch.ones(3, 1, dtype=DT))
    with pytest.raises(ValueError, match="not both"):
        HysteresisGP(
            X,
            Y,
            hysteresis={},
            train_Yvar=torch.ones_like(Y),
            likelihood=GaussianLikelihood(),
        )


# ----------------------------------------------------------- state handling


def test_history_features_are_normalised_magnetisation() -> None:
    model = _small_model()
    pm = model.hysteresis_models[0]
    with torch.no_grad():
        m = pm.magnetization(model.train_X[:, 0])
        feats = model.train_features()
    torch.testing.assert_close(feats[:, 0], 0.5 * (m + 1.0), rtol=0, atol=1e-12)


@pytest.mark.parametrize("q", [1, 3], ids=["q1", "q3"])
def test_next_step_batch_continues_from_current_state(q: int) -> None:
    model = _small_model(smoothing=0.0)
    pm = model.hysteresis_models[0]
    gen = torch.Generator().manual_seed(3)
    X = torch.rand(5, q, 1, generator=gen, dtype=DT) * I_MAX
    feats = model.features(X)
    for b in range(5):
        with torch.no_grad():
            full = torch.cat([model.train_X[:, 0], X[b, :, 0]])
            m = pm.magnetization(full)[-q:]
        # exact relays both ways: identical up to float64 summation order
        torch.testing.assert_close(feats[b, :, 0], 0.5 * (m + 1.0), rtol=0, atol=1e-12)


def test_future_sequence_is_state_consistent() -> None:
    model = _small_model(smoothing=0.0)
    pm = model.hysteresis_models[0]
    future = torch.tensor([2.0, 8.0, 4.0, 6.0, 5.0, 9.5, 0.5], dtype=DT)
    feats = model.features(future.view(1, -1, 1))[0, :, 0]
    with torch.no_grad():
        m = pm.magnetization(torch.cat([model.train_X[:, 0], future]))[-7:]
    torch.testing.assert_close(feats, 0.5 * (m + 1.0), rtol=0, atol=1e-12)


def test_posterior_sequence_uses_exact_states() -> None:
    smooth = _small_model()
    exact = _small_model(smoothing=0.0)
    future = torch.tensor([[2.0], [8.0], [4.0], [6.0]], dtype=DT)
    p_seq = smooth.posterior_sequence(future)
    p_exact = exact.posterior(future.unsqueeze(0))
    assert p_seq.mean.shape == (4, 1)
    # same hyperparameters, same exact features: identical up to round-off
    torch.testing.assert_close(
        p_seq.mean, p_exact.mean.squeeze(0), rtol=1e-10, atol=1e-12
    )
    torch.testing.assert_close(
        p_seq.variance, p_exact.variance.squeeze(0), rtol=1e-8, atol=1e-12
    )


def test_q_batch_fantasises_state_sequentially() -> None:
    model = _small_model()
    # same second setting, reached from above (after 10 A) or below (after 0 A):
    # the hysteresis must show in candidate 2's feature and posterior mean
    X = torch.tensor([[[10.0], [5.0]], [[0.0], [5.0]]], dtype=DT)
    feats = model.features(X)
    assert feats[0, 1, 0] - feats[1, 1, 0] > 0.05  # descending branch is higher
    one_step = model.features(torch.tensor([[[5.0]]], dtype=DT))
    assert not torch.allclose(one_step[0, 0], feats[0, 1]) or not torch.allclose(
        one_step[0, 0], feats[1, 1]
    )


def test_posterior_shapes_and_history_posterior() -> None:
    model = _small_model(d_plain=1)
    fit_hysteresis_gp(model, restarts=1, max_iter=30)
    X = torch.rand(4, 3, 2, dtype=DT) * torch.tensor([I_MAX, 1.0], dtype=DT)
    post = model.posterior(X)
    assert post.mean.shape == (4, 3, 1)
    assert post.variance.shape == (4, 3, 1)
    assert post.distribution.covariance_matrix.shape[-2:] == (3, 3)
    hist = model.posterior_on_history(observation_noise=True)
    assert hist.mean.shape == (model.train_X.shape[0], 1)
    assert (hist.variance > model.noise_sigma.detach() ** 2 * 0.999).all()


def test_feature_gradient_in_density_gradcheck() -> None:
    model = _small_model()
    pm = model.hysteresis_models[0]
    states = model.history_states(0)
    raw = (0.3 * torch.randn(pm.raw_density.shape, dtype=DT)).requires_grad_(True)

    def feats(r: torch.Tensor) -> torch.Tensor:
        return magnetization_feature(states, pm.area * torch.nn.functional.softplus(r))

    assert torch.autograd.gradcheck(feats, (raw,))


def test_candidate_gradient_is_nonnegative_in_current() -> None:
    # Preisach magnetisation never decreases when the current increases
    model = _small_model()
    X = (torch.rand(16, 1, 1, dtype=DT) * I_MAX).requires_grad_(True)
    model.features(X)[..., 0].sum().backward()
    assert (X.grad >= 0).all()
    assert (X.grad > 0).any()


def test_smooth_candidates_start_at_history_state_and_tend_to_exact() -> None:
    exact = _small_model(smoothing=0.0)
    smooth = _small_model()
    last = exact.train_X[-1:].view(1, 1, 1)
    # re-applying the last setting leaves the state unchanged, smooth or not
    torch.testing.assert_close(
        smooth.features(last)[0, 0, 0],
        smooth.train_features()[-1, 0],
        rtol=0,
        atol=1e-12,
    )
    X = torch.linspace(0.0, I_MAX, 21, dtype=DT).view(-1, 1, 1)
    fine = _small_model(smoothing=1e-4)
    diff_fine = (fine.features(X) - exact.features(X)).abs().max()
    diff_default = (smooth.features(X) - exact.features(X)).abs().max()
    # width 1e-4 of the range: only hysterons within ~1e-3 of a grid input move
    assert diff_fine < 1e-3
    # default width, a quarter mesh spacing: within about one hysteron step
    assert diff_default < 0.1


# ------------------------------------------------------------- fitting


def test_fit_recovers_noise_where_plain_gp_inflates_it() -> None:
    noise = 0.02
    X, Y, f = _data(seed=4, noise=noise, n_cycles=3, n_per_cycle=20)
    bounds = torch.tensor([[0.0], [I_MAX]], dtype=DT)
    stgp = SingleTaskGP(X, Y, input_transform=Normalize(d=1, bounds=bounds))
    fit_gpytorch_mll(ExactMarginalLogLikelihood(stgp.likelihood, stgp))
    gp_noise = float((stgp.likelihood.noise.sqrt() * stgp.outcome_transform.stdvs)[0])
    model = HysteresisGP(X, Y, hysteresis={0: _preisach(12)}, bounds=bounds)
    res = fit_hysteresis_gp(model, restarts=2, max_iter=150)
    # the H-GP explains the branches with the state: noise within 2x of truth
    # (60 residuals estimate sigma to ~10 %), the plain GP calls them noise
    assert 0.5 * noise < res.noise_sigma < 2.0 * noise
    assert gp_noise > 3.0 * noise
    with torch.no_grad():
        rmse = (model.posterior_on_history().mean.squeeze(-1) - f).pow(2).mean().sqrt()
    assert rmse < noise


def _affine_residual(a: torch.Tensor, b: torch.Tensor) -> float:
    """Rms of ``b`` minus its best affine fit in ``a``."""
    A = torch.stack([a, torch.ones_like(a)], dim=-1)
    coef = torch.linalg.lstsq(A, b.unsqueeze(-1)).solution
    return float((A @ coef).squeeze(-1).sub(b).pow(2).mean().sqrt())


def test_fit_recovers_magnetization_and_noise_of_known_density() -> None:
    # response linear in the true magnetisation and a linear kernel: the H-GP is
    # a Bayesian Preisach fit, and what the history identifies of the density is
    # the magnetisation trajectory (up to the affine map the GP absorbs)
    noise = 0.01
    u = _cycles(3, 20)
    with torch.no_grad():
        m_true = 0.5 * (_truth().magnetization(u) + 1.0)
    gen = torch.Generator().manual_seed(0)
    Y = m_true + noise * torch.randn(m_true.shape, generator=gen, dtype=DT)
    model = HysteresisGP(
        u.unsqueeze(-1),
        Y.unsqueeze(-1),
        hysteresis={0: _preisach(10)},
        covar_module=LinearKernel(),
    )
    with torch.no_grad():
        start = _affine_residual(model.train_features()[:, 0], m_true)
    res = fit_hysteresis_gp(model, restarts=1, max_iter=50)
    with torch.no_grad():
        fitted = _affine_residual(model.train_features()[:, 0], m_true)
    # uniform start: loops of the wrong shape, ~9 % of the swing off
    assert start > 0.05
    # fitted on a coarser mesh (55 vs 210 hysterons): within ~1 % of the swing,
    # the level a 0.01 noise allows from 60 points
    assert fitted < 0.015
    # 60 residuals estimate sigma to ~9 %; mesh mismatch adds a little
    assert 0.7 * noise < res.noise_sigma < 1.5 * noise


def test_restarts_discard_not_psd_failures(monkeypatch: pytest.MonkeyPatch) -> None:
    import diffaccel.hysteresis.hgp as hgp_module

    real = hgp_module.fit_gpytorch_mll_scipy
    calls: list[int] = []

    def first_fails(mll, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise NotPSDError("matrix not positive definite (injected)")
        return real(mll, **kwargs)

    monkeypatch.setattr(hgp_module, "fit_gpytorch_mll_scipy", first_fails)
    model = _small_model()
    res = fit_hysteresis_gp(model, restarts=2, max_iter=20)
    # BoTorch's fallback caught the failure and kept the sampled restart
    assert res.restart_mlls[0] == -math.inf
    assert res.best_restart == 1
    assert math.isfinite(res.mll)

    def always_fails(mll, **kwargs):
        raise NotPSDError("matrix not positive definite (injected)")

    monkeypatch.setattr(hgp_module, "fit_gpytorch_mll_scipy", always_fails)
    with pytest.raises(RuntimeError, match="every one of the 2 H-GP fit restarts"):
        fit_hysteresis_gp(_small_model(), restarts=2, max_iter=20)


def test_weak_response_does_not_collapse_into_noise() -> None:
    # response amplitude only ~4x the noise: the reference joint GP tends to
    # explain everything as noise here; priors + restarts must not
    noise = 0.02
    X, _, _ = _data(seed=5, noise=noise, n_cycles=3, n_per_cycle=20)
    with torch.no_grad():
        m = _truth().magnetization(X[:, 0])
    gen = torch.Generator().manual_seed(6)
    Y = (0.08 * m + noise * torch.randn(m.shape, generator=gen, dtype=DT)).unsqueeze(-1)
    model = HysteresisGP(X, Y, hysteresis={0: _preisach(12)})
    res = fit_hysteresis_gp(model, restarts=2, max_iter=100)
    assert res.noise_sigma < 2.0 * noise
    assert len(res.restart_mlls) == 2
    # the kept restart is the best one; its MLL recomputed to round-off
    assert res.mll == pytest.approx(max(res.restart_mlls), abs=1e-10)


def test_extended_keeps_parameters_and_continues_history() -> None:
    model = _small_model(smoothing=0.0)
    fit_hysteresis_gp(model, restarts=1, max_iter=30)
    X2 = torch.tensor([[3.0], [7.0]], dtype=DT)
    Y2 = torch.tensor([[0.5], [0.6]], dtype=DT)
    new = model.condition_on_observations(X2, Y2)
    assert new.train_X.shape[0] == model.train_X.shape[0] + 2
    torch.testing.assert_close(
        new.hysteresis_models[0].raw_density, model.hysteresis_models[0].raw_density
    )
    torch.testing.assert_close(
        new.gp.covar_module.lengthscale, model.gp.covar_module.lengthscale
    )
    # the new history's last states are those of the continued sequence
    expect = model.features(X2.unsqueeze(0))[0, -1, 0]
    torch.testing.assert_close(new.train_features()[-1, 0], expect, rtol=0, atol=1e-12)


# ---------------------------------------------------- BoTorch compatibility


def test_ucb_acquisition_optimisation_end_to_end() -> None:
    model = _small_model(d_plain=1)
    fit_hysteresis_gp(model, restarts=1, max_iter=30)
    bounds = torch.tensor([[0.0, 0.0], [I_MAX, 1.0]], dtype=DT)
    torch.manual_seed(0)
    cand, value = optimize_acqf(
        UpperConfidenceBound(model, beta=2.0),
        bounds=bounds,
        q=1,
        num_restarts=2,
        raw_samples=32,
    )
    assert cand.shape == (1, 2)
    assert ((cand >= bounds[0]) & (cand <= bounds[1])).all()
    assert torch.isfinite(value).all()


def test_qlogei_acquisition_optimisation_end_to_end() -> None:
    model = _small_model()
    fit_hysteresis_gp(model, restarts=1, max_iter=30)
    bounds = torch.tensor([[0.0], [I_MAX]], dtype=DT)
    torch.manual_seed(0)
    acq = qLogExpectedImprovement(model, best_f=model.train_Y.max())
    cand, value = optimize_acqf(acq, bounds=bounds, q=2, num_restarts=2, raw_samples=32)
    assert cand.shape == (2, 1)
    assert ((cand >= 0) & (cand <= I_MAX)).all()
    assert torch.isfinite(value).all()


# ------------------------------------------------------------------ units


def test_results_do_not_depend_on_output_units() -> None:
    # a beam size in m (1e-4 + 1e-5 * response) and one of range 1e-9 are the
    # same standardised problem as the response itself: noise and predictive
    # sigma scale with the output (GPyTorch's absolute variance floor of 1e-10
    # and BoTorch's skipped standardisation below std 1e-8 must not show)
    X, Y, _ = _data(0, 0.02, n_cycles=2, n_per_cycle=16)
    sigmas, noises = [], []
    for scale in (1.0, 1e-5, 1e-9):
        model = HysteresisGP(X, 1e-4 + scale * Y, hysteresis={0: _preisach(8)})
        fit_hysteresis_gp(model, restarts=1, max_iter=30)
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("error")  # no "Negative variance values" rounding
            post = model.posterior_on_history()
            cand = model.posterior(X[-3:].unsqueeze(-2), observation_noise=True)
            sigmas.append(
                torch.cat([post.variance, cand.variance.squeeze(-1)]).sqrt() / scale
            )
        noises.append(float(model.noise_sigma.detach()) / scale)
    # same optimisation in standardised units: only round-off (and L-BFGS
    # amplifying it over 30 iterations) differs between the scales
    for sigma, noise in zip(sigmas[1:], noises[1:], strict=True):
        torch.testing.assert_close(sigma, sigmas[0], rtol=1e-4, atol=0.0)
        assert noise == pytest.approx(noises[0], rel=1e-4)
    # and the unit-scale model is a sensible one: sigma well below the range 1
    assert 0.002 < float(sigmas[0].mean()) < 0.1


@pytest.mark.parametrize("where", ["history", "dense-q-batch"])
def test_samples_follow_the_rescaled_variance_in_tiny_units(where: str) -> None:
    # an output in units of 1e-7 (variances ~1e-17): samples used to be drawn
    # in those units, where the Cholesky jitter GPyTorch adds to a nearly
    # singular covariance (absolute, 1e-8) made their spread 10^4-10^5 times
    # posterior.variance.sqrt(); acquisition functions draw such samples
    X, Y, _ = _data(0, 0.02, n_cycles=2, n_per_cycle=16)
    scale = 1e-7
    model = HysteresisGP(X, 1e-4 + scale * Y, hysteresis={0: _preisach(8)})
    fit_hysteresis_gp(model, restarts=1, max_iter=30)
    n = 4000
    with torch.no_grad():
        if where == "history":
            post = model.posterior_on_history()
        else:  # 40 close settings: a nearly singular joint covariance
            post = model.posterior(torch.linspace(0.0, I_MAX, 40, dtype=DT)[:, None])
        sigma = post.variance.sqrt()
        torch.manual_seed(0)
        samples = post.rsample(torch.Size([n]))
        base = torch.randn(n, *post.base_sample_shape, dtype=DT)
        from_base = post.rsample_from_base_samples(torch.Size([n]), base)
    assert samples.shape == from_base.shape == (n, *post.mean.shape)
    assert float(sigma.min()) > 1e-3 * scale  # not GPyTorch's floor
    for s in (samples, from_base):
        # sample std within 10 % (its own error is ~1.1 %), the mean within
        # 5 standard errors of the posterior mean
        torch.testing.assert_close(s.std(0), sigma, rtol=0.1, atol=0.0)
        assert ((s.mean(0) - post.mean).abs() <= 5 * sigma / math.sqrt(n)).all()


# -------------------------------------------------------------- failures


@pytest.mark.parametrize(
    ("X", "Y", "match"),
    [
        (
            torch.zeros(2, 1, dtype=DT),
            torch.tensor([[0.0], [1.0]], dtype=DT),
            "too few",
        ),
        (torch.rand(6, 1, dtype=DT), torch.full((6, 1), 0.3, dtype=DT), "constant"),
        (
            torch.rand(6, 1, dtype=DT),
            torch.tensor([[0.0], [1.0], [float("nan")], [2.0], [1.0], [0.0]], dtype=DT),
            "NaN",
        ),
        (
            torch.tensor([[0.0], [1.0], [float("nan")], [2.0]], dtype=DT),
            torch.rand(4, 1, dtype=DT),
            "NaN",
        ),
        (torch.rand(6, 1, dtype=DT), torch.rand(6, dtype=DT), r"shape \(n, 1\)"),
        (torch.rand(2, 6, 1, dtype=DT), torch.rand(2, 6, 1, dtype=DT), r"\(n, d\)"),
        (
            torch.rand(4, 1, dtype=DT),
            torch.tensor([[0.0], [1.0], [1e160], [2.0]], dtype=DT),
            r"train_Y row 2, column 0 is 1e\+160: beyond 1e\+100",
        ),
        (
            torch.tensor([[0.0], [1.0], [-1e159], [0.5]], dtype=DT),
            torch.rand(4, 1, dtype=DT),
            r"train_X row 2, column 0 is -1e\+160: beyond 1e\+100",
        ),
    ],
    ids=[
        "too-few",
        "constant",
        "nan-y",
        "nan-x",
        "y-shape",
        "batched-x",
        "huge-y",
        "huge-x",
    ],
)
def test_bad_training_data_raises(X: torch.Tensor, Y: torch.Tensor, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        HysteresisGP(X * I_MAX, Y, hysteresis={0: _preisach(5)})


def test_bad_hysteretic_column_and_candidates_raise() -> None:
    X, Y, _ = _data(0, 0.02, n_cycles=1, n_per_cycle=10)
    with pytest.raises(ValueError, match="column 3 does not exist"):
        HysteresisGP(X, Y, hysteresis={3: _preisach(5)})
    model = HysteresisGP(X, Y, hysteresis={0: _preisach(5)})
    with pytest.raises(ValueError, match="d=1"):
        model.posterior(torch.rand(2, 1, 2, dtype=DT))
    with pytest.raises(ValueError, match="NaN"):
        model.posterior(torch.full((1, 1, 1), float("nan"), dtype=DT))


def test_current_outside_preisach_range_raises() -> None:
    X, Y, _ = _data(0, 0.02, n_cycles=1, n_per_cycle=10)
    with pytest.raises(ValueError, match="input_range"):
        HysteresisGP(X + 20.0, Y, hysteresis={0: _preisach(5)})


# ------------------------------------------------- input feature, data priors


def test_current_feature_appends_the_normalised_input() -> None:
    X, Y, _ = _data(0, 0.02, n_cycles=2, n_per_cycle=16)
    model = HysteresisGP(X, Y, hysteresis={0: _preisach(8)}, current_feature=True)
    feats = model.train_features()
    assert feats.shape == (X.shape[0], 2)
    torch.testing.assert_close(feats[:, 1], X[:, 0] / I_MAX, rtol=0, atol=1e-15)
    assert model.gp.covar_module.lengthscale.shape[-1] == 2
    # candidates: the same column, after the magnetisation of the sequence
    future = torch.tensor([[2.0], [8.0], [4.0]], dtype=DT)
    f = model.features(future.unsqueeze(0), exact=True)[0]
    torch.testing.assert_close(f[:, 1], future[:, 0] / I_MAX, rtol=0, atol=1e-15)
    assert model.posterior_sequence(future).mean.shape == (3, 1)
    new = model.extended(future, torch.zeros(3, 1, dtype=DT))
    assert new.current_feature and new.train_features().shape == (X.shape[0] + 3, 2)


def test_noise_likelihood_is_centred_on_the_estimate() -> None:
    from diffaccel.hysteresis.hgp import MIN_NOISE_VARIANCE, noise_likelihood

    Y = torch.linspace(0.0, 3.0, 40, dtype=DT).unsqueeze(-1)
    std = float(Y.std())
    lik = noise_likelihood(1e-3 * std, Y)
    prior = lik.noise_covar.noise_prior
    assert float(prior.loc) == pytest.approx(math.log(1e-6))
    assert float(lik.noise) == pytest.approx(1e-6, rel=1e-6)
    assert lik.noise_covar.raw_noise_constraint.lower_bound == pytest.approx(1e-7)
    # a large estimate starts at BoTorch's prior mode, floor at most 1e-4
    lik = noise_likelihood(0.5 * std, Y)
    assert float(lik.noise) == pytest.approx(math.exp(-5.0), rel=1e-6)
    assert lik.noise_covar.raw_noise_constraint.lower_bound == pytest.approx(1e-4)
    lik = noise_likelihood(1e-9 * std, Y)
    bound = lik.noise_covar.raw_noise_constraint.lower_bound
    assert float(bound) == pytest.approx(MIN_NOISE_VARIANCE)
    with pytest.raises(ValueError, match="noise_std"):
        noise_likelihood(0.0, Y)


def test_density_starts_are_ranked_by_marginal_likelihood() -> None:
    from diffaccel.hysteresis.hgp import joint_gp_from_preisach

    X, Y, _ = _data(2, 0.02, n_cycles=2, n_per_cycle=16)
    given = _preisach(8)
    model, start = joint_gp_from_preisach(X, Y, given, steps=50)
    assert model.current_feature and start.preisach_rmse > 0
    pre, uni = start.density_starts
    torch.testing.assert_close(uni[0], given.raw_density.detach())
    assert not torch.equal(pre[0], uni[0])  # the Preisach fit moved the density
    res = fit_hysteresis_gp(
        model, restarts=3, max_iter=30, density_starts=start.density_starts
    )
    # 2 optimisations from the Preisach density (one prior sample), 1 uniform
    assert len(res.restart_mlls) == 3
    assert res.mll == pytest.approx(max(res.restart_mlls), abs=1e-6)
    with pytest.raises(ValueError, match="density start shapes"):
        fit_hysteresis_gp(model, density_starts=[(torch.zeros(3, dtype=DT),)])
